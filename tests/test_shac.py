"""The identities behind D.Va, as tests: Theorem 1, APG = DPG + control regularisation, the
stop-gradient on observations, and TD-λ targets against a hand-computed case."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.algorithms.shac import SHAC, SHACConfig, clip_gradient_per_env, td_lambda_targets
from dva.envs.observations import PixelObservations
from dva.tasks import make_task

HORIZON, NUM_ENVS = 6, 2


def agent(gradient: str) -> SHAC:
    config = SHACConfig(
        observation="state",
        gradient=gradient,
        num_envs=NUM_ENVS,
        horizon=HORIZON,
        actor_hidden=(16,),
        critic_hidden=(16,),
        critic_minibatches=2,
        actor_backward_chunk=0,
    )
    return SHAC(PixelObservations(make_task("cartpole_swingup"), NUM_ENVS), config)


@pytest.fixture(scope="module")
def setup():
    shac = agent("decoupled")
    train = jax.jit(shac.init)(jax.random.PRNGKey(0))
    noise = jax.random.normal(jax.random.PRNGKey(1), (HORIZON, NUM_ENVS, 1))
    return shac, train, noise


@pytest.fixture(scope="module")
def decoupled(setup):
    """The decoupled rollout's loss L, what it took (observations, actions) and the gradients of L
    w.r.t. the actor parameters and the open-loop actions (an offset on a_t reaches L only through
    the dynamics, later actions held fixed): one compile shared by the identities below."""
    shac, train, noise = setup
    loss_of = lambda params, offsets: shac.rollout(params, train, noise, offsets)
    (loss, aux), (grad_params, grad_actions) = jax.jit(jax.value_and_grad(loss_of, argnums=(0, 1), has_aux=True))(
        train.actor_params, jnp.zeros_like(noise)
    )
    return loss, aux.taken, grad_params, grad_actions


def flat(tree) -> np.ndarray:
    return np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])


@pytest.mark.parametrize("beta", [0.1, 1.0, 10.0])
def test_theorem1_decoupled_gradient_is_behaviour_cloning_gradient(setup, decoupled, beta):
    shac, train, noise = setup
    _, taken, grad_loss, grad_loss_actions = decoupled
    grad_theta = jax.tree.map(jnp.negative, grad_loss)  # the decoupled trajectory gradient of J = −L
    grad_actions = -grad_loss_actions  # the open-loop gradient ∇_A J
    observations, actions = taken["observations"], taken["actions"]
    improved = actions + beta * grad_actions  # ā = a + β ∇_a J

    @jax.jit  # compiled: op by op its gradient costs ≈ 100 small compiles
    @jax.grad
    def grad_bc_loss(params):
        mean, log_std = jax.vmap(lambda o: shac.actor.apply(params, o))(observations)
        return jnp.sum((mean + jnp.exp(log_std) * noise - improved) ** 2) / (2 * beta)

    minus_grad_bc = jax.tree.map(jnp.negative, grad_bc_loss(train.actor_params))
    np.testing.assert_allclose(
        flat(grad_theta), flat(minus_grad_bc), rtol=2e-3, atol=1e-4 * np.abs(flat(grad_theta)).max()
    )  # float32
    assert np.abs(flat(grad_theta)).max() > 0


def test_full_gradient_is_decoupled_plus_control_regularisation(setup, decoupled):
    """APG = DPG + B, with B = Σ_t ∂L/∂a_t · ∂a_t/∂o_t · do_t/dθ computed on its own (state obs)."""
    _, train, noise = setup
    _, _, dpg, action_grad = decoupled  # ∂L/∂a_t with the observations cut: the open-loop action gradient
    full = agent("full")
    params = train.actor_params
    apg = jax.jit(jax.grad(lambda p: full.rollout(p, train, noise)[0]))(params)

    @jax.jit  # one compile: op by op the two VJPs cost ≈ 500 small ones (40 s on 2 cores)
    def control_regularisation_of(params, action_grad):
        observations_of = lambda p: full.rollout(p, train, noise)[1].taken["observations"]
        observations, observation_vjp = jax.vjp(observations_of, params)  # closed-loop do_t/dθ
        _, actor_vjp = jax.vjp(lambda o: full.pre_tanh_action(params, o, None), observations)  # ∂a_t/∂o_t
        return observation_vjp(actor_vjp(action_grad)[0])[0]

    control_regularisation = control_regularisation_of(params, action_grad)
    scale = np.abs(flat(apg)).max()
    assert np.abs(flat(control_regularisation)).max() > 1e-3 * scale  # not trivially zero
    np.testing.assert_allclose(flat(apg), flat(dpg) + flat(control_regularisation), rtol=2e-3, atol=1e-5 * scale)


def test_decoupled_rollout_cuts_the_observation_path(setup):
    """The first action depends on s0 only through the observation: zero gradient when decoupled."""
    shac, train, noise = setup

    def first_action(shac, qvel_offset):
        env = train.env.replace(obs=train.env.obs + qvel_offset)
        return shac.rollout(train.actor_params, train.replace(env=env), noise)[1].taken["actions"][0].sum()

    offset = jnp.zeros_like(train.env.obs)
    gradient = lambda name: jax.jit(jax.grad(lambda w: first_action(agent(name), w)))(
        offset
    )  # compiled: 1, not ≈ 50, compiles
    assert float(jnp.abs(gradient("decoupled")).max()) == 0.0
    assert float(jnp.abs(gradient("full")).max()) > 0.0


def test_per_env_gradient_clipping_rescales_only_large_cotangents():
    # Env 0's cotangent (3, 4 | 12) has norm 13 → scaled to 2; env 1's (0.3, 0.4 | 0) stays.
    qpos = jnp.array([[1.0, 2.0], [3.0, 4.0]])
    qvel = jnp.array([[5.0], [6.0]])
    upstream = (jnp.array([[3.0, 4.0], [0.3, 0.4]]), jnp.array([[12.0], [0.0]]))

    def loss(q, v):
        q, v = clip_gradient_per_env((q, v), 2.0)
        return jnp.sum(q * upstream[0]) + jnp.sum(v * upstream[1])

    assert float(loss(qpos, qvel)) == pytest.approx(3 + 8 + 0.9 + 1.6 + 60)  # the forward is the identity
    grad_q, grad_v = jax.grad(loss, argnums=(0, 1))(qpos, qvel)
    np.testing.assert_allclose(grad_q, [[3 * 2 / 13, 4 * 2 / 13], [0.3, 0.4]], rtol=1e-6)
    np.testing.assert_allclose(grad_v, [[12 * 2 / 13], [0.0]], rtol=1e-6)


def test_state_gradient_clipping_in_the_rollout(setup, decoupled):
    """A bound far above the real cotangents changes nothing; a tiny one shrinks the gradient
    that reaches earlier actions, and the loss (the forward) is the same either way."""
    shac, train, noise = setup

    def action_grad(clip):
        clipped = SHAC(shac.env, dataclasses.replace(shac.config, state_grad_clip=clip))
        return jax.jit(jax.value_and_grad(lambda w: clipped.rollout(train.actor_params, train, noise, w)[0]))(
            jnp.zeros_like(noise)
        )

    exact_loss, _, _, exact = decoupled  # state_grad_clip None: exact
    loose_loss, loose = action_grad(1e9)
    tight_loss, tight = action_grad(1e-6)
    # the same forward, compiled three times: equal up to how XLA fused each program
    for loss in (loose_loss, tight_loss):
        assert float(loss) == pytest.approx(float(exact_loss), rel=1e-6)
    np.testing.assert_allclose(loose, exact, rtol=1e-6)
    # The last action's gradient reaches no later state; earlier ones keep only their own step's
    # reward (the path through the next states is cut).
    np.testing.assert_allclose(tight[-1], exact[-1], rtol=1e-6)
    assert np.linalg.norm(tight[:-1]) < 0.5 * np.linalg.norm(exact[:-1])


def test_td_lambda_targets_hand_computed():
    gamma, lam = 0.9, 0.5
    reward = jnp.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0]])
    # env 0 terminates after step 1 (no bootstrap); env 1 is truncated there (bootstraps on 25).
    next_value = jnp.array([[10.0, 10.0], [0.0, 25.0], [30.0, 30.0], [40.0, 40.0]])
    boundary = jnp.array([[False, False], [True, True], [False, False], [True, True]])
    targets = np.asarray(td_lambda_targets(reward, next_value, boundary, gamma, lam))
    # Step 3 ends the window: 4 + 0.9·40.  Step 2: (1−λ)G¹ + λG² = 0.5·30 + 0.5·39.
    r3, r2 = 40.0, 0.5 * (3 + 0.9 * 30) + 0.5 * (3 + 0.9 * 4 + 0.81 * 40)
    expected_env0 = [1 + 0.9 * (0.5 * 10 + 0.5 * 2.0), 2.0, r2, r3]
    expected_env1 = [1 + 0.9 * (0.5 * 10 + 0.5 * 24.5), 2 + 0.9 * 25, r2, r3]
    np.testing.assert_allclose(targets[:, 0], expected_env0, rtol=1e-6)
    np.testing.assert_allclose(targets[:, 1], expected_env1, rtol=1e-6)


@pytest.fixture(scope="module")
def batched(setup):
    """The decoupled fast path's loss and gradient (physics backward for ∂L/∂a, then the actor's
    backward passes the rollout kept, step by step)."""
    shac, train, noise = setup
    loss, _, grads = jax.jit(shac.actor_gradient)(train.actor_params, train, noise)
    return loss, grads


def test_batched_actor_gradient_equals_reverse_mode_through_the_rollout(batched, decoupled):
    """The fast path gives the same gradient as differentiating the rollout directly."""
    (loss, fast), (direct_loss, _, direct, _) = batched, decoupled
    assert float(loss) == pytest.approx(float(direct_loss), rel=1e-6)
    np.testing.assert_allclose(flat(fast), flat(direct), rtol=1e-4, atol=1e-6 * np.abs(flat(direct)).max())


@pytest.mark.parametrize("chunk", [1, 2])
def test_chunked_actor_backward_equals_the_kept_one(setup, batched, chunk):
    """Recomputing the actor one or two steps at a time (less memory; 1 is the default) gives the
    same gradient as the rollout's kept backward passes. (The reshape into chunks is the same for
    pixel observations; small compiles here keep the suite short.)"""
    shac, train, noise = setup
    _, batched = batched
    chunked_agent = SHAC(shac.env, dataclasses.replace(shac.config, actor_backward_chunk=chunk))
    _, _, chunked = jax.jit(chunked_agent.actor_gradient)(train.actor_params, train, noise)
    assert np.abs(flat(batched)).max() > 0
    np.testing.assert_allclose(flat(chunked), flat(batched), rtol=1e-5, atol=1e-7 * np.abs(flat(batched)).max())
    for bad in (4, -1):
        with pytest.raises(ValueError, match=f"actor_backward_chunk = {bad} is not allowed"):
            dataclasses.replace(shac.config, actor_backward_chunk=bad)


def test_without_the_critic_the_loss_is_the_windows_discounted_reward(setup, decoupled):
    """The value ablation: nothing is bootstrapped at the window's end (no episode ends within
    these 6 steps of Cart-pole), so the loss is −Σ_t γ^t r_t averaged over envs and steps."""
    shac, train, noise = setup
    with_critic = decoupled[0]
    ablated = SHAC(shac.env, dataclasses.replace(shac.config, use_critic=False))
    loss, aux = jax.jit(ablated.rollout)(train.actor_params, train, noise)
    reward = np.asarray(aux.trajectory.reward)
    assert not np.asarray(aux.trajectory.boundary)[:-1].any()
    discounts = shac.config.gamma ** np.arange(HORIZON)[:, None]
    assert float(loss) == pytest.approx(-(discounts * reward).sum() / (NUM_ENVS * HORIZON), rel=1e-5)
    assert float(with_critic) != pytest.approx(float(loss), rel=1e-5)  # the critic's bootstrap is there


def test_pre_tanh_penalty_adds_its_hand_computed_loss_and_action_gradient(setup, decoupled):
    """``pre_tanh_penalty`` adds ``weight · mean(u²)`` to the loss and ``2·weight·u / (h·N·A)`` to
    each open-loop action's gradient (u the taken pre-tanh actions), through the batched path too."""
    shac, train, noise = setup
    loss, taken, _, grad_actions = decoupled
    weight = 0.3
    penalised = SHAC(shac.env, dataclasses.replace(shac.config, pre_tanh_penalty=weight))
    loss_of = lambda offsets: penalised.rollout(train.actor_params, train, noise, offsets)
    (new_loss, aux), new_grad = jax.jit(jax.value_and_grad(loss_of, has_aux=True))(jnp.zeros_like(noise))
    u = np.asarray(taken["actions"])
    assert float(new_loss) == pytest.approx(float(loss) + weight * np.mean(u**2), rel=1e-5)
    np.testing.assert_allclose(
        np.asarray(new_grad), np.asarray(grad_actions) + 2 * weight * u / u.size, rtol=1e-4, atol=1e-7
    )


def test_init_log_std_sets_the_exploration_noise_of_the_taken_actions(setup):
    """``init_log_std`` is the initial log σ: a taken pre-tanh action is ``μ + e^{init_log_std} ε``."""
    shac, train, noise = setup
    wide = SHAC(shac.env, dataclasses.replace(shac.config, init_log_std=0.5))
    params = wide.actor.init(jax.random.PRNGKey(2), jnp.zeros((NUM_ENVS, wide.task.obs_dim)))
    observation = jax.random.normal(jax.random.PRNGKey(3), (NUM_ENVS, wide.task.obs_dim))
    mean = wide.pre_tanh_action(params, observation, None)
    taken = wide.pre_tanh_action(params, observation, noise[0])
    np.testing.assert_allclose(np.asarray(taken - mean), np.exp(0.5) * np.asarray(noise[0]), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(shac.actor.apply(train.actor_params, observation)[1]), -1.0)


def test_pixel_gradient_flows_for_visual_shac_and_is_cut_for_dva():
    """Through pixels: the second action depends on the first state only via the rendered frame
    (and the physics in between); visual SHAC differentiates that path, D.Va cuts it exactly."""
    from dva.envs.rendering import PixelRenderer
    from dva.envs.soft_rendering import SoftRenderer

    task = make_task("cartpole_swingup")
    noise = jax.random.normal(jax.random.PRNGKey(1), (3, NUM_ENVS, 1))

    def second_action_gradient(gradient: str, renderer) -> np.ndarray:
        config = SHACConfig(
            observation="pixels",
            gradient=gradient,
            num_envs=NUM_ENVS,
            horizon=3,
            image_size=16,
            actor_hidden=(8,),
            critic_hidden=(8,),
            critic_minibatches=2,
        )
        shac = SHAC(PixelObservations(task, NUM_ENVS, renderer, config.frame_stack), config)
        train = jax.jit(shac.init)(jax.random.PRNGKey(0))

        def second_action(qpos_offset):
            data = train.env.data.replace(qpos=train.env.data.qpos + qpos_offset)
            return (
                shac.rollout(train.actor_params, train.replace(env=train.env.replace(data=data)), noise)[1]
                .taken["actions"][1]
                .sum()
            )

        return np.asarray(jax.jit(jax.grad(second_action))(jnp.zeros_like(train.env.data.qpos)))

    assert np.abs(second_action_gradient("full", SoftRenderer(task, NUM_ENVS, 16))).max() > 0
    assert np.abs(second_action_gradient("decoupled", PixelRenderer(task, NUM_ENVS, 16))).max() == 0.0
    with pytest.raises(ValueError, match="needs a differentiable renderer"):
        SHAC(
            PixelObservations(task, NUM_ENVS, PixelRenderer(task, NUM_ENVS, 16)),
            SHACConfig(observation="pixels", gradient="full", num_envs=NUM_ENVS),
        )


def test_state_prediction_adds_its_weighted_mean_squared_error_to_the_actor_gradient():
    """D.Va's auxiliary loss: the actor's gradient is reverse mode through the decoupled rollout
    plus ``weight ·`` the gradient of the encoder's mean squared error on the normalised states it
    saw, and the reported loss is that error (kept backward passes and recomputed chunks alike)."""
    from dva.envs.rendering import PixelRenderer

    task, weight = make_task("cartpole_swingup"), 0.7
    config = SHACConfig(
        observation="pixels",
        num_envs=NUM_ENVS,
        horizon=2,
        image_size=16,
        actor_hidden=(8,),
        critic_hidden=(8,),
        critic_minibatches=2,
        state_prediction=weight,
    )
    env = PixelObservations(task, NUM_ENVS, PixelRenderer(task, NUM_ENVS, 16), config.frame_stack)
    shac = SHAC(env, config)
    train = jax.jit(shac.init)(jax.random.PRNGKey(0))
    noise = jax.random.normal(jax.random.PRNGKey(1), (2, NUM_ENVS, 1))
    taken = jax.jit(shac.rollout)(train.actor_params, train, noise)[1].taken

    def mean_squared_error(params):
        flat_obs = taken["observations"].reshape((-1,) + taken["observations"].shape[2:])
        predicted = shac.actor.apply(params, flat_obs, predict_state=True)[2]
        return jnp.mean((predicted - taken["states"].reshape(predicted.shape)) ** 2)

    def reference(params):
        return shac.rollout(params, train, noise)[0] + weight * mean_squared_error(params)

    expected = jax.jit(jax.grad(reference))(train.actor_params)
    assert np.abs(flat(expected["params"]["state_head"])).max() > 0
    error = float(jax.jit(mean_squared_error)(train.actor_params))
    for chunk in (0, 1):
        chunked = SHAC(env, dataclasses.replace(config, actor_backward_chunk=chunk))
        _, aux, grads = jax.jit(chunked.actor_gradient)(train.actor_params, train, noise)
        np.testing.assert_allclose(flat(grads), flat(expected), rtol=1e-4, atol=1e-6 * np.abs(flat(expected)).max())
        assert float(aux.stats["state_prediction_loss"]) == pytest.approx(error, rel=1e-5)
    with pytest.raises(ValueError, match="state_prediction = 0.5 is not allowed"):
        SHACConfig(observation="state", state_prediction=0.5)

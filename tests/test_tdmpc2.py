"""TD-MPC2: its pieces against hand-computed values (SimNorm, two-hot targets on its bins, the
discount rule, the loss weights at an episode's end), the planner against a known model, and a
tiny pixel agent through the training loop (logs, evaluation with the plan as memory, the
target-Q average). Learning Cart-pole is measured in docs/results.md."""

from __future__ import annotations

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fakes import output_layer

from dva.algorithms import build_agent, make_config
from dva.algorithms.model_based_math import twohot, twohot_decode
from dva.algorithms.replay import Step
from dva.algorithms.tdmpc2 import TDMPC2, discount_for
from dva.envs.observations import PixelObservations
from dva.networks.tdmpc2 import simnorm
from dva.runner.compiled import load_run
from dva.runner.training import train
from dva.tasks import make_task

# 48² frames through 4-channel convolutions: a 2·2·4 = 16-entry latent; 2 envs, no action repeat.
TINY = dict(
    num_envs=2,
    image_size=48,
    channels=4,
    action_repeat=1,
    batch_size=4,
    latent_dim=16,
    encoder_dim=16,
    mlp_dim=16,
    num_q=2,
    num_bins=21,
    num_samples=16,
    num_elites=4,
    num_pi_trajs=2,
    mppi_iterations=2,
    replay_size=200,
    seed_steps=8,
    updates_per_iteration=2,
    lr=3e-3,
)


def rows(run_dir) -> list[dict]:
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def tdmpc2_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("tdmpc2") / "run"
    # Evaluated on the training envs: TD-MPC2 plans at every evaluation step, for every episode.
    train("cartpole_balance", "tdmpc2", iterations=20, run_dir=run_dir, eval_every=10, eval_episodes=None, **TINY)
    return run_dir


def test_simnorm_makes_every_group_of_entries_a_softmax():
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 16)) * 3.0
    out = np.asarray(simnorm(x, 8))
    groups = np.asarray(x).reshape(3, 2, 8)
    expected = np.exp(groups) / np.exp(groups).sum(-1, keepdims=True)
    np.testing.assert_allclose(out, expected.reshape(3, 16), rtol=1e-5)
    np.testing.assert_allclose(out.reshape(3, 2, 8).sum(-1), 1.0, rtol=1e-6)
    # a constant added to one group changes nothing: the latent lives on the simplices
    np.testing.assert_allclose(simnorm(x.at[:, :8].add(5.0), 8), out, rtol=1e-5)


def test_twohot_targets_on_tdmpc2s_bins_decode_to_the_value():
    agent = small_agent()
    bins = agent.bins
    assert len(bins) == 21 and float(bins[0]) == -10.0 and float(bins[-1]) == 10.0
    values = jnp.array([-500.0, -2.5, 0.0, 0.3, 7.0, 3000.0])
    target = twohot(values, bins)
    np.testing.assert_allclose(target.sum(-1), 1.0, rtol=1e-6)
    assert int((target > 0).sum(-1).max()) <= 2
    # logits = log(target): the head's prediction is the value, its cross-entropy gradient zero
    logits = jnp.log(target + 1e-30)
    np.testing.assert_allclose(twohot_decode(logits, bins), values, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(jax.nn.softmax(logits) - target, 0.0, atol=1e-6)


def test_discount_follows_the_episode_length_rule():
    assert discount_for(500) == pytest.approx(0.99)  # DMC's 1000 steps at action repeat 2
    assert discount_for(120) == pytest.approx(23 / 24)  # Cart-pole's 240 at action repeat 2
    assert discount_for(20) == 0.95 and discount_for(100_000) == 0.995


def small_agent(observation: str = "state", task: str = "cartpole_balance", **overrides) -> TDMPC2:
    values = {**TINY, **overrides}
    if observation == "state":
        values.pop("image_size")
    algo = "tdmpc2-state" if observation == "state" else "tdmpc2"
    return build_agent(task, algo, make_config(task, algo, "cpu", **values))


def one_sequence(terminated_at: int | None = None, truncated_at: int | None = None) -> Step:
    """A replayed state sequence of 1 + H = 4 steps (batch 1) ending at the given step."""
    flags = lambda at: jnp.zeros((1, 4), bool) if at is None else jnp.zeros((1, 4), bool).at[0, at].set(True)
    return Step(
        frame=jnp.arange(4.0)[None, :, None] * jnp.ones((1, 4, 5)),
        first=jnp.zeros((1, 4), bool),
        action=jnp.zeros((1, 4, 1)),
        reward=jnp.array([[1.0, 2.0, 3.0, 4.0]]),
        terminated=flags(terminated_at),
        truncated=flags(truncated_at),
    )


def test_losses_stop_at_an_episode_end():
    agent = small_agent()
    # a termination at step 1: its reward and value (no bootstrap) count; its next observation
    # (the next episode's first) and everything after do not
    batch = agent.sequences(one_sequence(terminated_at=1))
    np.testing.assert_array_equal(batch.reached[:, 0], [True, True, False, False])
    np.testing.assert_array_equal(batch.bootstrap[:, 0], [True, False, False])
    np.testing.assert_array_equal(batch.terminated[:, 0], [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(batch.reward[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(batch.obs[:, 0, 0], [0.0, 1.0, 2.0, 3.0])
    # a time limit at step 0: its reward counts, its value does not (its successor was replaced)
    batch = agent.sequences(one_sequence(truncated_at=0))
    np.testing.assert_array_equal(batch.reached[:, 0], [True, False, False, False])
    np.testing.assert_array_equal(batch.bootstrap[:, 0], [False, False, False])
    value_weight = batch.reached[:-1] & ~batch.truncated
    np.testing.assert_array_equal(value_weight[:, 0], [False, False, False])


class KnownModel(TDMPC2):
    """A planner over a model known in closed form: the latent's first entry moves by half the
    action, the reward is ``−(position − 1)²`` after the move, no value at the end, and a policy
    prior that always pushes the wrong way (−0.5)."""

    def next(self, params, z, action):
        return z.at[..., 0].add(0.5 * action[..., 0])

    def reward(self, params, z, action):
        return -((z[..., 0] + 0.5 * action[..., 0] - 1.0) ** 2)

    def terminated(self, params, z):
        return jnp.zeros(z.shape[:-1], bool)

    def q_value(self, q_params, z, action, key, reduce):
        return jnp.zeros(z.shape[:-1])

    def policy_sample(self, policy, z, key):
        action = jnp.full(z.shape[:-1] + (1,), -0.5)
        return action, action, jnp.zeros(z.shape[:-1])


NO_PARAMS = {"policy": {}, "q": {}}  # the known model needs none


def test_the_planner_improves_on_the_prior_under_a_known_model():
    env = PixelObservations(make_task("cartpole_balance"), 2)
    config = make_config("cartpole_balance", "tdmpc2-state", "cpu", num_envs=2, num_samples=256, num_elites=32)
    agent = KnownModel(env, config)
    z = jnp.zeros(config.latent_dim)
    plan = jax.jit(lambda key: agent.plan(NO_PARAMS, z, jnp.zeros((3, 1)), key, False))
    action, mean, _ = plan(jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(1)
    value = lambda actions: float(agent.trajectory_value(NO_PARAMS, z[None], actions[:, None], key)[0])
    prior = jnp.full((3, 1), -0.5)
    # the best plan moves to 1 in two steps of +1 and stays (return −0.25 − 0 − 0 = −0.25); the
    # prior's moves away (−1.5625 − 2.25 − 3.0625 discounted)
    assert value(mean) > -0.5 > value(prior)
    assert float(action[0]) > 0.6


def test_tdmpc2_trains_and_evaluates_through_the_loop(tdmpc2_run):
    log = rows(tdmpc2_run)
    assert [int(r["iteration"]) for r in log] == list(range(21))
    # seed phase: 8 env steps, at least one 3 − 1 + 3 + 1 = 6-step sequence per env: 6 rounds of 2
    assert [int(r["env_steps"]) for r in log] == [12 + 2 * i for i in range(21)]
    evaluations = [float(r["eval_return"]) for r in log if r["eval_return"] != ""]
    assert len(evaluations) == 3 and all(np.isfinite(evaluations))
    _, agent, state = load_run(tdmpc2_run, evaluation_episodes=None)
    assert int(state.iteration) == 20 and int(state.replay.current_index) == 6 + 20
    assert all(np.isfinite(float(r[name])) for r in log[1:] for name in agent.metric_names)
    # the reward head starts at 0 for every reward (zero output layer) and learns the replay's
    reward_loss = [float(r["reward_loss"]) for r in log[1:]]
    assert np.mean(reward_loss[-3:]) < 0.7 * np.mean(reward_loss[:3])


def test_an_update_moves_the_target_qs_by_tau(tdmpc2_run):
    _, agent, state = load_run(tdmpc2_run, evaluation_episodes=None)
    updated, metrics = jax.jit(agent.update)(state, jax.random.PRNGKey(3))
    tau = agent.config.tau
    expected = jax.tree.map(lambda q, target: tau * q + (1 - tau) * target, updated.params["q"], state.target_q)
    for got, want in zip(jax.tree.leaves(updated.target_q), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    assert float(metrics["q_scale"]) >= 1.0
    changed = lambda name: any(
        np.abs(np.asarray(a) - np.asarray(b)).max() > 0
        for a, b in zip(jax.tree.leaves(updated.params[name]), jax.tree.leaves(state.params[name]))
    )
    assert changed("policy") and changed("dynamics") and changed("encoder")


class LoudPolicyLoss(TDMPC2):
    """The policy prior's loss times 1000 (its gradient and its Adam step change)."""

    def policy_loss(self, *args):
        loss, q_scale = super().policy_loss(*args)
        return 1000.0 * loss, q_scale


def test_the_policy_update_trains_only_the_prior_and_the_model_update_not_the_prior(tdmpc2_run):
    """The world model's new parameters do not depend on the policy prior's loss (another loss,
    the same model), and the model loss passes no gradient to the prior (its TD target's actions
    come from the prior without gradient, as in the reference)."""
    _, agent, state = load_run(tdmpc2_run, evaluation_episodes=None)
    loud = LoudPolicyLoss(agent.env, agent.config)
    key = jax.random.PRNGKey(3)
    updated, _ = jax.jit(agent.update)(state, key)
    updated_loud, _ = jax.jit(loud.update)(state, key)
    for name in ("encoder", "dynamics", "reward", "termination", "q"):
        for a, b in zip(jax.tree.leaves(updated.params[name]), jax.tree.leaves(updated_loud.params[name])):
            np.testing.assert_array_equal(a, b)
    policy_moved = [np.abs(np.asarray(a) - np.asarray(b)).max() for a, b in zip(
        jax.tree.leaves(updated.params["policy"]), jax.tree.leaves(updated_loud.params["policy"]))]  # fmt: skip
    assert max(policy_moved) > 0  # the loud loss did reach the prior

    batch = agent.sequences(agent.replay.sample_sequences(state.replay, key))
    obs = agent.augment(batch.obs, key)
    next_z = agent.encode(state.params, obs[1:])
    model = {name: value for name, value in state.params.items() if name != "policy"}

    def model_loss_of_the_prior(policy):
        td_target = agent.td_target({**state.params, "policy": policy}, state.target_q, batch, next_z, key)
        return agent.model_loss(model, batch, obs[0], next_z, td_target, key)[0]

    gradient = jax.grad(model_loss_of_the_prior)(state.params["policy"])
    assert all(float(jnp.abs(g).max()) == 0.0 for g in jax.tree.leaves(gradient))


def test_the_planner_refits_twice_more_for_twenty_or_more_actions():
    """The reference's rule for large action spaces: the Humanoid's 21 actions get two more MPPI
    refits than configured, Cart-pole's one does not."""
    assert small_agent().mppi_iterations == TINY["mppi_iterations"]
    assert small_agent(task="humanoid").mppi_iterations == TINY["mppi_iterations"] + 2


def controlled_policy(agent: TDMPC2, mean: float, raw_log_std: float) -> dict:
    """Policy-prior parameters whose output is the constant ``(mean, raw_log_std)`` per action."""
    params = agent.policy_net.init(jax.random.PRNGKey(0), jnp.zeros((1, agent.latent_dim)))
    last = output_layer(params["params"])
    action_dim = agent.task.action_dim
    bias = jnp.concatenate([jnp.full(action_dim, mean), jnp.full(action_dim, raw_log_std)])
    params["params"][last] = {"kernel": jnp.zeros_like(params["params"][last]["kernel"]), "bias": bias}
    return params


def test_the_policy_samples_a_squashed_gaussian_with_the_scaled_entropy_term():
    """``tanh(μ + σε)``, and the entropy term ``−A · log N(ε; 0, σ)`` summed over the A actions
    (the reference's scaled entropy), by hand for a prior whose output is known, on the Hopper's
    three actions."""
    agent = small_agent(task="hopper")
    cfg = agent.config
    policy = controlled_policy(agent, mean=0.3, raw_log_std=-0.5)
    z = jax.random.uniform(jax.random.PRNGKey(1), (5, agent.latent_dim))
    key = jax.random.PRNGKey(2)
    action, mean_action, entropy = agent.policy_sample(policy, z, key)
    log_std = cfg.log_std_min + 0.5 * (cfg.log_std_max - cfg.log_std_min) * (np.tanh(-0.5) + 1.0)
    noise = np.asarray(jax.random.normal(key, (5, 3)))
    np.testing.assert_allclose(action, np.tanh(0.3 + noise * np.exp(log_std)), rtol=1e-5)
    np.testing.assert_allclose(mean_action, np.full((5, 3), np.tanh(0.3)), rtol=1e-6)
    log_prob = np.sum(-0.5 * noise**2 - log_std - 0.5 * np.log(2 * np.pi), -1)
    np.testing.assert_allclose(entropy, -3 * log_prob, rtol=1e-5)


def test_the_td_target_bootstraps_the_smaller_of_two_target_qs_at_the_priors_action():
    """``r + γ (1 − terminated) min(Q̄₁, Q̄₂)(z', π(z'))`` by hand with a two-member ensemble."""
    agent = small_agent()
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    params = state.params
    # a target ensemble whose members disagree (the initial output layers are zero)
    target_q = jax.tree.map(lambda x: x + 0.3 * jax.random.normal(jax.random.PRNGKey(4), x.shape), state.target_q)
    batch = agent.sequences(one_sequence(terminated_at=1))
    next_z = jax.random.uniform(jax.random.PRNGKey(1), (3, 1, agent.latent_dim))
    key = jax.random.PRNGKey(2)
    target = np.asarray(agent.td_target(params, target_q, batch, next_z, key))
    policy_key, _ = jax.random.split(key)
    action = agent.policy_sample(params["policy"], next_z, policy_key)[0]
    members = np.asarray(twohot_decode(agent.q.apply(target_q, jnp.concatenate([next_z, action], -1)), agent.bins))
    assert np.abs(members[0] - members[1]).max() > 1e-3
    expected = np.array([1.0, 2.0, 3.0])[:, None] + agent.gamma * np.array([1.0, 0.0, 1.0])[:, None] * members.min(0)
    np.testing.assert_allclose(target, expected, rtol=1e-5, atol=1e-6)


def test_the_policy_loss_rewards_q_over_its_scale_and_entropy_and_updates_the_scale():
    """``−Σ_t ρ^t (α · entropy + Q / S) / (B (H + 1))`` with S moved towards the first latents'
    5th–95th percentile spread of Q (at least 1) by ``tau`` — by hand from its pieces; its sign:
    raising Q lowers the loss. Dropout off, so that Q is the members' plain mean."""
    agent = small_agent(dropout=0.0, batch_size=8)
    cfg = agent.config
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    q_params = jax.tree.map(lambda x: x + 0.5 * jax.random.normal(jax.random.PRNGKey(4), x.shape), state.params["q"])
    zs = jax.random.uniform(jax.random.PRNGKey(1), (cfg.horizon + 1, 8, agent.latent_dim))
    reached = jnp.ones((cfg.horizon + 1, 8), bool).at[2:, 0].set(False)
    key, old_scale = jax.random.PRNGKey(2), jnp.asarray(1.5)
    loss, q_scale = agent.policy_loss(state.params["policy"], q_params, zs, reached, old_scale, key)

    action_key, _, _ = jax.random.split(key, 3)
    action, _, entropy = agent.policy_sample(state.params["policy"], zs, action_key)
    q = np.asarray(twohot_decode(agent.q.apply(q_params, jnp.concatenate([zs, action], -1)), agent.bins)).mean(0)
    spread = np.percentile(q[0], 95) - np.percentile(q[0], 5)
    expected_scale = 1.5 + cfg.tau * (max(spread, 1.0) - 1.5)
    weight = cfg.rho ** np.arange(cfg.horizon + 1)[:, None] * np.asarray(reached)
    expected = -np.sum(weight * (cfg.entropy_coef * np.asarray(entropy) + q / expected_scale)) / (8 * (cfg.horizon + 1))
    np.testing.assert_allclose(q_scale, expected_scale, rtol=1e-5)
    np.testing.assert_allclose(loss, expected, rtol=1e-4)
    raised = jax.tree.map(lambda x: x, q_params)  # every member's output bias + 1: Q rises by ≈ 1
    higher = lambda p: agent.policy_loss(state.params["policy"], p, zs, reached, old_scale, key)[0]
    last = output_layer(raised["params"])
    bins = np.asarray(agent.bins)
    shift = np.zeros(len(bins), np.float32)
    shift[-1] = 50.0  # all probability on the top bin: Q at its largest
    raised["params"][last]["bias"] = raised["params"][last]["bias"] + shift
    assert float(higher(raised)) < float(loss)


def test_evaluation_carries_the_plan_and_the_first_step_plans_afresh(tdmpc2_run):
    _, agent, state = load_run(tdmpc2_run, evaluation_episodes=None)
    policy, observation = agent.policy(state), agent.env.observe(state.env)
    act = jax.jit(agent.act_recurrent)
    fresh = agent.initial_memory(agent.config.num_envs)
    key = jax.random.PRNGKey(0)
    first_action, plan = act(policy, observation, fresh, key)
    np.testing.assert_allclose(first_action, jax.jit(agent.act)(policy, observation), atol=1e-6)
    assert plan.shape == (2, 3, 1) and np.all(np.abs(np.asarray(first_action)) <= 1.0)
    # the next step starts from the plan, shifted: a different start, a different plan
    _, next_plan = act(policy, observation, plan, key)
    assert np.abs(np.asarray(next_plan - plan)).max() > 1e-5


def test_the_cpu_preset_updates_twice_per_agent_step_on_the_legged_robots_pixels():
    """The Hopper sweep's best rate is the legged robots' on pixels; Cart-pole, the state agent and
    the paper preset keep the reference's one update per agent step of each env."""
    legged = make_config("hopper", "tdmpc2", "cpu")
    assert legged.updates_per_iteration / legged.num_envs == 2
    for config in (
        make_config("cartpole_balance", "tdmpc2", "cpu"),
        make_config("hopper", "tdmpc2-state", "cpu"),
        make_config("hopper", "tdmpc2", "paper"),
    ):
        assert config.updates_per_iteration / config.num_envs == 1
    at_one_per_step = make_config("hopper", "tdmpc2", "cpu", updates_per_iteration=4)
    assert dataclasses.replace(legged, updates_per_iteration=4) == at_one_per_step  # the only difference


def test_bad_tdmpc2_settings_name_the_value():
    with pytest.raises(ValueError, match="num_q = 1 .* ≥ 2"):
        make_config("cartpole_balance", "tdmpc2", "cpu", num_q=1)
    with pytest.raises(ValueError, match="num_elites = 300, .* num_samples = 128"):
        make_config("cartpole_balance", "tdmpc2", "cpu", num_elites=300)
    with pytest.raises(ValueError, match="simnorm_group = 7 .* 512 entries"):
        make_config("cartpole_balance", "tdmpc2", "cpu", simnorm_group=7)
    with pytest.raises(ValueError, match="image_size = 32 .* ≥ 39"):
        make_config("cartpole_balance", "tdmpc2", "cpu", image_size=32)


def test_an_unhealthy_update_names_every_loss_and_its_value():
    agent = small_agent()
    metrics = {name: 1.5 for name in agent.metric_names} | {"value_loss": float("nan")}
    reason = agent.abort_reason(metrics)
    assert reason.startswith("a NaN or infinite loss (") and "value_loss nan" in reason and "reward_loss 1.5" in reason

"""DreamerV3 through the training loop (a tiny model on Cart-pole balance): logs, evaluation with
its recurrent state, a checkpoint that restores its replay and latents, a world model whose
reconstruction improves, the policy's memory (reset at episode starts), and the train-ratio
arithmetic. Its numerical pieces are tested in ``test_model_based_math.py``; learning to balance is a
slow test (``test_learning.py``)."""

from __future__ import annotations

import copy
import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from fakes import output_layer

from dva.algorithms import build_agent, make_config
from dva.algorithms.dreamerv3 import clip_straight_through, sample_onehot
from dva.algorithms.model_based_math import lambda_returns, normalized_advantage, twohot_decode, update_return_scale
from dva.networks.dreamer import LayerNormGRU
from dva.runner.compiled import load_run
from dva.runner.training import train

# 4 × 8 replayed steps per update at ratio 16 over 2 envs: collect 1 step, update once. No action
# repeat: one env step to compile where the loop has one (collection, seed phase, evaluation).
TINY = dict(
    num_envs=2,
    image_size=16,
    action_repeat=1,
    batch_size=4,
    batch_length=8,
    train_ratio=16.0,
    deter=32,
    units=32,
    stoch=4,
    classes=4,
    cnn_depth=4,
    num_bins=31,
    horizon=5,
    replay_size=200,
    seed_steps=8,
    model_lr=1e-3,
)


# Evaluations on a batch of another size than training's: the policy's memory must follow it.
EVAL_EPISODES = 3


def rows(run_dir) -> list[dict]:
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def dreamer_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("dreamerv3") / "run"
    # one call: resuming is the loop's, tested with SHAC and DrQ-v2 in test_training.py (a second call
    # here would cost a minute of this file's loading and compiling on a 2-core CI box)
    train(
        "cartpole_balance",
        "dreamerv3",
        preset="cpu",
        iterations=20,
        run_dir=run_dir,
        eval_every=10,
        eval_episodes=EVAL_EPISODES,
        checkpoint_every=10,
        **TINY,
    )
    return run_dir


def test_train_ratio_sets_steps_and_updates_per_iteration():
    paper = make_config("cartpole_balance", "dreamerv3", "paper")
    # 16 × 64 replayed steps per update, 512 per policy step of 4 envs: 2 updates per step.
    assert (paper.collect_steps, paper.updates) == (1, 2)
    cpu = make_config("cartpole_balance", "dreamerv3", "cpu")
    # 8 × 32 per update at ratio 16 over 4 envs: one update per 4 steps.
    assert (cpu.collect_steps, cpu.updates) == (4, 1)
    legged = make_config("hopper", "dreamerv3", "cpu")
    # The legged robots' ratio 256, the Hopper sweep's best: four updates per step of the 4 envs.
    assert (legged.train_ratio, legged.collect_steps, legged.updates) == (256.0, 1, 4)
    assert make_config("hopper", "dreamerv3-state", "cpu").train_ratio == 16.0  # the state agent keeps its own
    for config in (paper, cpu, legged):
        replayed = config.updates * config.batch_size * config.batch_length
        assert replayed / (config.num_envs * config.collect_steps) == config.train_ratio


def test_the_cpu_preset_gives_the_state_agent_its_own_actor_rate():
    """On the state the CPU preset's actor learns at 2e-4 (at 8e-5 it learned balance and drifted
    back); the pixel agent and the paper preset keep their rates, the rest of the preset is shared."""
    pixels, state = (make_config("cartpole_balance", algo, "cpu") for algo in ("dreamerv3", "dreamerv3-state"))
    assert (pixels.actor_lr, state.actor_lr) == (8e-5, 2e-4)
    assert (state.model_lr, state.critic_lr, state.units) == (pixels.model_lr, pixels.critic_lr, pixels.units)
    paper_state = make_config("cartpole_balance", "dreamerv3-state", "paper")
    assert paper_state.actor_lr == make_config("cartpole_balance", "dreamerv3", "paper").actor_lr == 3e-5


def test_bad_dreamerv3_settings_name_the_value():
    with pytest.raises(ValueError, match="image_size = 50 .* multiple of 16"):
        make_config("cartpole_balance", "dreamerv3", "cpu", image_size=50)
    with pytest.raises(ValueError, match="frame_stack = 3 .* use 1"):
        make_config("cartpole_balance", "dreamerv3", "cpu", frame_stack=3)
    with pytest.raises(ValueError, match="actor_gradient = 'dynamics' .* 'backprop' or 'reinforce'"):
        make_config("cartpole_balance", "dreamerv3", "cpu", actor_gradient="dynamics")


def test_dreamerv3_trains_checkpoints_and_evaluates_through_the_loop(dreamer_run):
    log = rows(dreamer_run)
    assert [int(r["iteration"]) for r in log] == list(range(21))
    # seed phase: 8 steps of 2 envs (one sequence each) = 16 env steps; then 2 per iteration
    assert [int(r["env_steps"]) for r in log] == [16 + 2 * i for i in range(21)]
    evaluations = [float(r["eval_return"]) for r in log if r["eval_return"] != ""]
    assert len(evaluations) == 3 and all(np.isfinite(evaluations))
    _, agent, state = load_run(dreamer_run, EVAL_EPISODES)
    assert int(state.iteration) == 20 and int(state.replay.current_index) == 8 + 20
    assert all(np.isfinite(float(r[name])) for r in log[1:] for name in agent.metric_names)


def test_world_model_reconstruction_improves(dreamer_run):
    loss = [float(r["reconstruction_loss"]) for r in rows(dreamer_run)[1:]]
    assert np.mean(loss[-3:]) < 0.7 * np.mean(loss[:3])


def test_policy_memory_carries_the_past_and_forgets_it_at_a_restart(dreamer_run):
    _, agent, state = load_run(dreamer_run, EVAL_EPISODES)
    policy, observation = agent.policy(state), agent.env.observe(state.env)
    act = jax.jit(agent.act_recurrent)
    fresh = agent.initial_memory(agent.config.num_envs)
    key = jax.random.PRNGKey(0)  # the latent is sampled: the same key, the same sample
    first_action, first_memory = act(policy, observation, fresh, key)
    np.testing.assert_allclose(first_action, jax.jit(agent.act)(policy, observation), atol=1e-6)
    assert first_action.shape == (2, 1) and np.all(np.abs(np.asarray(first_action)) <= 1.0)
    # the same image seen again, now after a step: a different latent state
    _, memory = act(policy, observation, first_memory, key)
    assert np.abs(np.asarray(memory.deter - first_memory.deter)).max() > 1e-5
    # a restart forgets everything before it: the first step's state and action again
    restarted, restarted_memory = act(policy, observation, memory.replace(restart=jnp.ones(2, bool)), key)
    np.testing.assert_allclose(restarted, first_action, atol=1e-6)
    np.testing.assert_allclose(restarted_memory.deter, first_memory.deter, atol=1e-6)


def test_replayed_sequences_restart_the_latent_at_episode_starts(dreamer_run):
    _, agent, state = load_run(dreamer_run, EVAL_EPISODES)
    steps = agent.replay.sample_sequences(state.replay, jax.random.PRNGKey(0))
    steps = steps.replace(first=jnp.zeros_like(steps.first).at[:, 3].set(True))
    loss, ((deter, stoch), terms) = jax.jit(agent.world_model_loss)(state.params["model"], steps, jax.random.PRNGKey(1))
    deter = np.asarray(deter)
    assert np.isfinite(float(loss)) and deter.shape == (4, 8, 32) and stoch.shape == (4, 8, 4, 4)
    # h is zeros at the sequence's start and at the episode start inside it, carried elsewhere
    assert np.all(deter[:, [0, 3]] == 0.0)
    assert np.all(np.abs(deter[:, [1, 2, 4, 5]]).max(axis=-1) > 0.0)
    assert np.allclose(np.asarray(stoch).sum(-1), 1.0)  # one-hot categoricals


class ImaginedActorLoss:
    """The entropy-free actor loss on one batch of imagination starts of the test run, with its
    value, aux and gradient in the actor, from one compile per actor gradient."""

    def __init__(self, run_dir) -> None:
        _, self.agent, self.state = load_run(run_dir, EVAL_EPISODES)
        steps = self.agent.replay.sample_sequences(self.state.replay, jax.random.PRNGKey(0))
        _, ((deter, stoch), _) = jax.jit(self.agent.world_model_loss)(
            self.state.params["model"], steps, jax.random.PRNGKey(1)
        )
        self.deter, self.stoch = deter.reshape(-1, deter.shape[-1]), stoch.reshape((-1,) + stoch.shape[2:])
        self.scale, self.key = jnp.asarray(3.0), jax.random.PRNGKey(2)
        self._compiled = {}

    def __call__(self, actor, model, actor_gradient: str = "backprop"):
        """``((loss, aux), actor gradient)`` with the world model ``model``."""
        if actor_gradient not in self._compiled:
            agent = copy.copy(self.agent)
            agent.config = dataclasses.replace(self.agent.config, entropy=0.0, actor_gradient=actor_gradient)
            loss = lambda a, m: agent.actor_loss(
                a, m, self.state.params["critic"], self.scale, self.deter, self.stoch, self.key
            )
            self._compiled[actor_gradient] = jax.jit(jax.value_and_grad(loss, has_aux=True))
        return self._compiled[actor_gradient](actor, model)


@pytest.fixture(scope="module")
def imagined_actor_loss(dreamer_run):
    return ImaginedActorLoss(dreamer_run)


def test_a_backprop_actor_step_raises_the_imagined_advantage(imagined_actor_loss):
    """The default actor gradient for continuous actions is the normalised advantage's own gradient
    through the frozen model and critic: with the entropy bonus off, a small step along it raises
    the advantage imagined with the same samples; REINFORCE's gradient on the same trajectories differs."""
    assert imagined_actor_loss.agent.config.actor_gradient == "backprop"
    actor, model = imagined_actor_loss.state.params["actor"], imagined_actor_loss.state.params["model"]
    (loss, _), backprop_grad = imagined_actor_loss(actor, model)
    norm = float(optax.tree.norm(backprop_grad))
    assert np.isfinite(norm) and norm > 0.0
    stepped = jax.tree.map(lambda p, g: p - 1e-3 * g / norm, actor, backprop_grad)
    (stepped_loss, _), _ = imagined_actor_loss(stepped, model)
    assert float(stepped_loss) < float(loss)  # the imagined advantage (its negative: the loss) rose

    _, reinforce_grad = imagined_actor_loss(actor, model, "reinforce")
    cosine = optax.tree.vdot(backprop_grad, reinforce_grad) / (norm * float(optax.tree.norm(reinforce_grad)))
    assert abs(float(cosine)) < 0.99


def test_imagined_actions_carry_no_gradient_to_the_states_they_were_chosen_in(imagined_actor_loss):
    """As in the reference implementation, the actor reads imagined states through a stop-gradient:
    an action's gradient is its effect on the future, with later actions held, so the imagined
    actions do not depend (differentiably) on where imagination started while the states do."""
    agent, params = imagined_actor_loss.agent, imagined_actor_loss.state.params
    stoch = imagined_actor_loss.stoch[:2]
    imagine = lambda start: agent.imagine(params["model"], params["actor"], start, stoch, jax.random.PRNGKey(2))
    feats_jacobian, *policy_jacobians = jax.jit(jax.jacrev(imagine))(imagined_actor_loss.deter[:2])
    assert float(jnp.abs(feats_jacobian[1:]).max()) > 1e-3  # later states do depend on the start
    assert all(float(jnp.abs(jacobian).max()) == 0.0 for jacobian in policy_jacobians)  # actions, means, stds


def test_the_backprop_actor_loss_is_the_normalised_advantage_with_the_continuation_mode(imagined_actor_loss):
    """The actor's loss by hand from the imagined trajectory: λ-returns of the predicted rewards and
    the continuation's mode (1 where its logit is > 0), minus the critic's values, over max(1, S),
    weighted by γ^t times the chance of reaching step t (the reference's cumprod(γ · cont) / γ).
    Being a mode, the continuation carries no
    gradient: doubling the continuation head's logits leaves the actor's gradient as it was."""
    agent, params = imagined_actor_loss.agent, imagined_actor_loss.state.params
    cfg, model, critic, actor = agent.config, params["model"], params["critic"], params["actor"]
    (loss, (_, returns, weight, new_scale, _)), actor_grad = imagined_actor_loss(actor, model)

    feats, *_ = agent.imagine(
        model, actor, imagined_actor_loss.deter, imagined_actor_loss.stoch, imagined_actor_loss.key
    )
    reward = np.asarray(twohot_decode(agent.reward_head.apply(model["reward"], feats[1:]), agent.bins))
    cont = np.asarray(agent.cont_head.apply(model["cont"], feats[1:])[..., 0] > 0.0, np.float32)
    value = np.asarray(twohot_decode(agent.critic.apply(critic, feats), agent.bins))
    # the pieces are checked against hand-computed values in test_model_based_math.py; here, what goes in
    expected_returns = np.asarray(lambda_returns(reward, value, cont, cfg.gamma, cfg.lam))
    expected_weight = cfg.gamma ** np.arange(len(cont))[:, None] * np.cumprod(
        np.concatenate([np.ones_like(cont[:1]), cont[:-1]]), axis=0
    )
    expected_scale = update_return_scale(imagined_actor_loss.scale, expected_returns, cfg.return_decay)
    advantage = np.asarray(normalized_advantage(expected_returns, value[:-1], expected_scale))
    np.testing.assert_allclose(returns, expected_returns, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(weight, expected_weight, rtol=1e-6)
    np.testing.assert_allclose(new_scale, expected_scale, rtol=1e-4)
    np.testing.assert_allclose(loss, -np.mean(expected_weight * advantage), rtol=1e-4, atol=1e-6)

    last = output_layer(model["cont"]["params"])
    sharper = jax.tree.map(lambda x: x, model)
    sharper["cont"]["params"][last] = jax.tree.map(lambda x: 2.0 * x, model["cont"]["params"][last])
    _, sharper_grad = imagined_actor_loss(actor, sharper)
    for before, after in zip(jax.tree.leaves(actor_grad), jax.tree.leaves(sharper_grad)):
        np.testing.assert_allclose(before, after, rtol=1e-5, atol=1e-8)


def numpy_twohot(values: np.ndarray, bins: np.ndarray) -> np.ndarray:
    """Two-hot of symlog(values) by hand: the weight split between the two bins around each."""
    y = np.clip(np.sign(values) * np.log1p(np.abs(values)), bins[0], bins[-1])
    upper = np.clip(np.searchsorted(bins, y, side="right"), 1, len(bins) - 1)
    lower = upper - 1
    above = (y - bins[lower]) / (bins[upper] - bins[lower])
    encoded = np.zeros(values.shape + (len(bins),))
    np.put_along_axis(encoded, lower[..., None], (1.0 - above)[..., None], -1)
    np.put_along_axis(encoded, upper[..., None], above[..., None], -1)
    return encoded


def test_the_critic_learns_the_returns_and_stays_near_its_slow_copy(imagined_actor_loss):
    """The critic's loss by hand: per imagined step, weighted as the actor's, the cross-entropy of
    its distribution with the two-hot λ-return plus the cross-entropy with the two-hot of the slow
    critic's value; after an update the slow critic is ``ema · slow + (1 − ema) · critic``."""
    agent, state = imagined_actor_loss.agent, imagined_actor_loss.state
    params = state.params
    (_, (feats, returns, weight, _, _)), _ = imagined_actor_loss(params["actor"], params["model"])
    slow = jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.PRNGKey(5), x.shape), params["critic"])
    loss = agent.critic_loss(params["critic"], slow, feats, returns, weight)

    bins = np.asarray(agent.bins, np.float64)
    log_p = np.asarray(jax.nn.log_softmax(agent.critic.apply(params["critic"], feats[:-1]), -1), np.float64)
    slow_p = np.asarray(jax.nn.softmax(agent.critic.apply(slow, feats[:-1]), -1), np.float64)
    slow_symlog = slow_p @ bins
    slow_value = np.sign(slow_symlog) * np.expm1(np.abs(slow_symlog))
    assert np.abs(slow_value - np.asarray(returns)).max() > 1e-2  # two different targets
    to_returns = -np.sum(numpy_twohot(np.asarray(returns, np.float64), bins) * log_p, -1)
    to_slow = -np.sum(numpy_twohot(slow_value, bins) * log_p, -1)
    np.testing.assert_allclose(loss, np.mean(np.asarray(weight) * (to_returns + to_slow)), rtol=1e-4)

    starts = (imagined_actor_loss.deter[None], imagined_actor_loss.stoch[None])
    new_params, new_slow, *_ = jax.jit(agent.behaviour_update)(
        params, slow, dict(state.opt_states), jnp.asarray(1.0), starts, jax.random.PRNGKey(6)
    )
    ema = agent.config.critic_ema
    for got, old, critic in zip(
        jax.tree.leaves(new_slow), jax.tree.leaves(slow), jax.tree.leaves(new_params["critic"])
    ):
        np.testing.assert_allclose(got, ema * np.asarray(old) + (1 - ema) * np.asarray(critic), rtol=1e-5, atol=1e-7)


def test_actions_reach_the_model_clipped_by_value_with_their_gradient_kept():
    """Inside the box an action passes as it is; outside, the model reads the clipped value and
    the actor still gets the gradient scaled by 1 / |a| (``jnp.clip`` would give none)."""
    actions = jnp.array([-2.5, -1.0, 0.3, 0.99, 4.0])
    np.testing.assert_allclose(clip_straight_through(actions), jnp.clip(actions, -1.0, 1.0), rtol=1e-7)
    gradient = jax.grad(lambda a: jnp.sum(jnp.arange(1.0, 6.0) * clip_straight_through(a)))(actions)
    np.testing.assert_allclose(gradient, [1 / 2.5, 2.0, 3.0, 4.0, 5 / 4.0], rtol=1e-6)


def test_the_gru_keeps_a_share_of_its_state_set_by_the_update_bias():
    """The reference's GRU: with the gates' Dense at zero, LayerNorm gives zero pre-activations, the
    candidate tanh(σ(0) · 0) = 0 and the update gate σ(0 − 1): ``h' = (1 − σ(−1)) h``; with
    weights, ``h'`` is the gated formula by hand."""
    cell = LayerNormGRU(4)
    deter, x = jax.random.normal(jax.random.PRNGKey(0), (3, 4)), jax.random.normal(jax.random.PRNGKey(1), (3, 5))
    params = cell.init(jax.random.PRNGKey(2), deter, x)
    zero = jax.tree.map(jnp.zeros_like, params)
    zero["params"]["LayerNorm_0"]["scale"] = jnp.ones(12)
    np.testing.assert_allclose(cell.apply(zero, deter, x), (1 - 1 / (1 + np.e)) * np.asarray(deter), rtol=1e-6)

    kernel = np.asarray(params["params"]["Dense_0"]["kernel"])
    pre = np.concatenate([deter, x], -1) @ kernel
    normed = (pre - pre.mean(-1, keepdims=True)) / np.sqrt(pre.var(-1, keepdims=True) + 1e-6)
    sigmoid = lambda v: 1 / (1 + np.exp(-v))
    reset, candidate, update = np.split(normed, 3, -1)
    candidate, update = np.tanh(sigmoid(reset) * candidate), sigmoid(update - 1)
    expected = update * candidate + (1 - update) * np.asarray(deter)
    np.testing.assert_allclose(cell.apply(params, deter, x), expected, rtol=1e-4, atol=1e-6)


def test_evaluation_samples_the_actor_and_keys_make_it_reproducible(dreamer_run):
    """As the 2023 reference's eval mode: the action is a sample of the actor's Gaussian (two keys,
    two actions; one key, one action), inside the box."""
    _, agent, state = load_run(dreamer_run, EVAL_EPISODES)
    policy, observation = agent.policy(state), agent.env.observe(state.env)
    memory = agent.initial_memory(agent.config.num_envs)
    act = jax.jit(agent.act_recurrent)
    first, _ = act(policy, observation, memory, jax.random.PRNGKey(0))
    again, _ = act(policy, observation, memory, jax.random.PRNGKey(0))
    other, _ = act(policy, observation, memory, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(first, again)
    assert np.abs(np.asarray(first - other)).max() > 1e-3 and np.all(np.abs(np.asarray(first)) <= 1.0)


def test_onehot_samples_follow_the_probabilities_and_carry_their_gradient():
    """The inverse-CDF sampler: one class per categorical, drawn as often as its probability says
    (20,000 draws: each frequency within 5 standard errors), and the straight-through gradient of
    the softmax."""
    logits = jnp.array([[2.0, 0.0, -1.0, 0.5, -3.0], [0.0, 0.0, 0.0, 0.0, 0.0]])
    samples = jax.vmap(lambda key: sample_onehot(logits, key))(jax.random.split(jax.random.PRNGKey(0), 20_000))
    np.testing.assert_array_equal(np.asarray(samples).sum(-1), 1.0)
    probs = np.asarray(jax.nn.softmax(logits, -1))
    error = np.sqrt(probs * (1 - probs) / 20_000)
    assert np.all(np.abs(np.asarray(samples).mean(0) - probs) < 5 * error + 1e-6)
    weights = jnp.arange(10.0).reshape(2, 5)
    straight_through = jax.grad(lambda x: jnp.sum(weights * sample_onehot(x, jax.random.PRNGKey(1))))(logits)
    softmax = jax.grad(lambda x: jnp.sum(weights * jax.nn.softmax(x, -1)))(logits)
    np.testing.assert_allclose(straight_through, softmax, rtol=1e-6)


def test_a_world_model_on_the_state_predicts_held_out_rewards_better_than_their_mean():
    """DreamerV3's world model on Cart-pole's state, trained on one fixed replay of random actions,
    predicts the rewards of another replay (other episodes, 16 batches) with less than 0.75 of the
    squared error of the training rewards' mean (≈ 0.6 with several update seeds; random actions
    on swing-up leave much of the reward to chance)."""
    config = make_config(
        "cartpole_swingup",
        "dreamerv3-state",
        "cpu",
        **{
            **TINY,
            "deter": 64,
            "units": 64,
            "stoch": 8,
            "classes": 8,
            "num_bins": 63,
            "seed_steps": 400,
            "replay_size": 2000,
        }
        | {"batch_length": 16, "batch_size": 16},
    )
    agent = build_agent("cartpole_swingup", "dreamerv3-state", config)
    train_state, held_out = (jax.jit(agent.init)(jax.random.PRNGKey(seed)) for seed in (0, 1))
    model, optimizer = train_state.params["model"], agent.optimizers["model"]

    def update(carry, key):
        model, opt_state = carry
        sample_key, loss_key = jax.random.split(key)
        steps = agent.replay.sample_sequences(train_state.replay, sample_key)
        grads = jax.grad(lambda m: agent.world_model_loss(m, steps, loss_key)[0])(model)
        updates, opt_state = optimizer.update(grads, opt_state, model)
        return (optax.apply_updates(model, updates), opt_state), None

    trained = jax.jit(lambda model, keys: jax.lax.scan(update, (model, optimizer.init(model)), keys)[0][0])(
        model, jax.random.split(jax.random.PRNGKey(2), 1000)
    )

    seen = train_state.replay.experience.reward  # the training replay's rewards (its unfilled slots are 0)
    seen_mean = jnp.mean(seen[:, : int(train_state.replay.current_index)])

    def errors(key):
        """Squared errors of the model's and the mean's predictions on one held-out batch."""
        steps = agent.replay.sample_sequences(held_out.replay, key)
        arrived = agent.observe_sequences(trained, steps, key)[-1]
        reward = steps.reward[:, :-1]
        return jnp.mean((agent.predicted_reward(trained, arrived[:, 1:]) - reward) ** 2), jnp.mean(
            (reward - seen_mean) ** 2
        )

    model_error, mean_error = (
        float(jnp.mean(e)) for e in jax.jit(jax.vmap(errors))(jax.random.split(jax.random.PRNGKey(3), 16))
    )
    assert model_error < 0.75 * mean_error, (model_error, mean_error)

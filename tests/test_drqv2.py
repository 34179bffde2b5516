"""DrQ-v2 and its frame replay: random shifts pixel-exact, n-step targets and frame stacks against
hand-computed cases, sampling that never reads unwritten slots or crosses an episode, the target
network's Polyak update, and the agent running through the training loop."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fakes import small_off_policy_agent

from dva.algorithms import make_config
from dva.algorithms.augmentation import shift_images
from dva.algorithms.replay import FrameReplay, Step, stack_at
from dva.envs.rendering import push_frame, reset_frame_stack


def test_shift_images_is_pixel_exact():
    image = jnp.arange(16, dtype=jnp.uint8).reshape(1, 4, 4, 1)
    shift = lambda dy, dx: np.asarray(shift_images(image, jnp.array([[dy, dx]]), pad=1))[0, ..., 0]
    np.testing.assert_array_equal(shift(1, 1), np.asarray(image[0, ..., 0]))  # (pad, pad): identity
    rows, cols = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    original = np.arange(16).reshape(4, 4)
    # Offset (0, 0): the image moves down-right by one, edge pixels repeated into the gap.
    np.testing.assert_array_equal(shift(0, 0), original[np.maximum(rows - 1, 0), np.maximum(cols - 1, 0)])
    # Offset (2, 0): up by one, right by one.
    np.testing.assert_array_equal(shift(2, 0), original[np.minimum(rows + 1, 3), np.maximum(cols - 1, 0)])


def steps_from(rewards, terminated=(), truncated=(), first=(), state=False) -> Step:
    """One sampled sequence (L steps) with frame t filled with the value t + 1 (and with ``state``
    a state vector [t + 1, −(t + 1)])."""
    length = len(rewards)
    flag = lambda where: jnp.array([t in where for t in range(length)])
    states = jnp.arange(1, length + 1, dtype=jnp.float32)[:, None] * jnp.array([1.0, -1.0])
    return Step(
        frame=jnp.broadcast_to(jnp.arange(1, length + 1, dtype=jnp.uint8)[:, None, None, None], (length, 2, 2, 3)),
        first=flag(first),
        action=jnp.arange(length, dtype=jnp.float32)[:, None],
        reward=jnp.asarray(rewards, jnp.float32),
        terminated=flag(terminated),
        truncated=flag(truncated),
        state=states if state else None,
    )


def test_n_step_transition_against_hand_computed_returns():
    replay = FrameReplay(num_envs=1, capacity=100, batch_size=1, frame_stack=3, n_step=3, gamma=0.5)
    rewards = [9.0, 9.0, 1.0, 2.0, 4.0, 9.0]  # the window starts at position 2 (frame_stack − 1)
    running = replay.transition(steps_from(rewards))
    assert float(running.reward) == 1 + 0.5 * 2 + 0.25 * 4 and float(running.discount) == 0.125
    assert bool(running.valid) and float(running.action[0]) == 2.0
    assert int(running.obs[0, 0, -1]) == 3 and int(running.next_obs[0, 0, -1]) == 6  # o_t and o_{t+3}
    ended = replay.transition(steps_from(rewards, terminated={3}))  # fails after r = 2: no bootstrap
    assert float(ended.reward) == 1 + 0.5 * 2 and float(ended.discount) == 0.0 and bool(ended.valid)
    timed_out = replay.transition(steps_from(rewards, truncated={3}))  # o_{t+2} was replaced by a reset
    assert not bool(timed_out.valid)
    earlier = replay.transition(steps_from(rewards, terminated={1}, truncated={0}))  # before o_t: irrelevant
    assert float(earlier.reward) == running.reward and bool(earlier.valid)
    assert running.state is None  # kept only for a privileged agent: then o_t's own
    np.testing.assert_array_equal(replay.transition(steps_from(rewards, state=True)).state, [3.0, -3.0])


def test_frame_stacks_rebuilt_from_single_frames_match_the_wrapper():
    """Push frames through the wrapper's own stacking (with episode restarts), store only the
    newest frame and the episode-start flag, and rebuild every stack from the stored frames."""
    frames = jnp.arange(1, 13, dtype=jnp.uint8)[:, None, None, None, None] * jnp.ones((1, 1, 2, 2, 3), jnp.uint8)
    restarts = {4, 6, 7}  # the observation at these steps starts an episode
    stacks, stack = [], reset_frame_stack(frames[0], 3)
    for t in range(12):
        if t > 0:
            stack = push_frame(stack, frames[t], jnp.array([t in restarts]))
        stacks.append(stack[0])
    first = jnp.array([t == 0 or t in restarts for t in range(12)])
    for t in range(2, 12):
        np.testing.assert_array_equal(np.asarray(stack_at(frames[:, 0], first, t, 3)), np.asarray(stacks[t]))


def test_replay_samples_only_written_steps_and_never_crosses_an_episode():
    num_envs, gamma = 2, 0.5
    replay = FrameReplay(num_envs, capacity=200, batch_size=256, frame_stack=3, n_step=3, gamma=gamma)
    example = Step(
        frame=jnp.zeros((2, 2, 3), jnp.uint8),
        first=jnp.zeros((), bool),
        action=jnp.zeros(1),
        reward=jnp.zeros(()),
        terminated=jnp.zeros((), bool),
        truncated=jnp.zeros((), bool),
    )
    state = replay.init(example)
    length, end = 9, {(0, 4)}  # env 0 fails at step 4; frame value = 10·env + t + 1 tells a step apart
    for t in range(length):
        value = jnp.array([10 * e + t + 1 for e in range(num_envs)], jnp.uint8)
        state = replay.add(
            state,
            Step(
                frame=jnp.broadcast_to(value[:, None, None, None], (num_envs, 2, 2, 3)),
                first=jnp.array([t == 0 or (e, t - 1) in end for e in range(num_envs)]),
                action=jnp.zeros((num_envs, 1)),
                reward=jnp.full(num_envs, float(t)),
                terminated=jnp.array([(e, t) in end for e in range(num_envs)]),
                truncated=jnp.zeros(num_envs, bool),
            ),
        )
    batch = jax.device_get(replay.sample(state, jax.random.PRNGKey(0)))
    assert batch.obs.min() > 0 and batch.next_obs.min() > 0  # every frame was written
    for obs, reward, discount in zip(batch.obs, batch.reward, batch.discount):
        env, t = divmod(int(obs[0, 0, -1]) - 1, 10)
        assert 2 <= t <= length - 4  # room for two earlier frames and three later steps
        window = range(t, t + 3)
        fails = [i for i in window if (env, i) in end]
        last = fails[0] if fails else t + 2
        expected = sum(gamma ** (i - t) * i for i in range(t, last + 1))
        assert reward == pytest.approx(expected) and discount == (0.0 if fails else gamma**3)


@pytest.fixture(scope="module")
def small_agent():
    # 6 × 4 envs × 2 repeats = 48 env steps: past the seed phase; one update per iteration, so the
    # last iteration's learner is one update from the one before.
    return small_off_policy_agent("drqv2", 6, seed_steps=32, updates_per_iteration=1, reward_scale=0.5)


def test_drqv2_learns_after_the_seed_phase_and_moves_the_target_by_tau(small_agent):
    agent, previous, state, metrics = small_agent
    logged = metrics.logged
    assert np.isfinite(logged["critic_loss"]) and np.isfinite(logged["actor_loss"]) and metrics.healthy
    assert logged["exploration"] < 1.0  # the std schedule has started
    learner, updated = previous.learner, state.learner
    tau = agent.config.target_tau
    expected = jax.tree.map(
        lambda online, old: tau * online + (1 - tau) * old, updated.params["critic"], learner.target_critic
    )
    for got, want in zip(jax.tree.leaves(updated.target_critic), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    moved = [np.abs(a - b).max() for a, b in zip(jax.tree.leaves(updated.params), jax.tree.leaves(learner.params))]
    assert min(moved) > 0  # encoder, actor and critic all learn


def test_drqv2_acts_with_the_actors_mean(small_agent):
    agent, _, state, _ = small_agent
    observation = agent.env.observe(state.env)
    action = agent.act(agent.policy(state), observation)
    assert action.shape == (4, 1) and np.all(np.abs(np.asarray(action)) <= 1.0)
    params = state.learner.params
    np.testing.assert_allclose(
        action, agent.actor.apply(params["actor"], agent.encoder.apply(params["encoder"], observation["pixels"]))
    )


def test_replay_stores_rewards_times_reward_scale(small_agent):
    agent, _, state, _ = small_agent  # reward_scale 0.5
    action = jnp.full((4, 1), 0.3)
    after, finished = jax.jit(agent.collect)(state, action)
    stored = after.replay.experience.reward[:, after.replay.current_index - 1]
    np.testing.assert_allclose(stored, 0.5 * np.asarray(after.env.reward), rtol=1e-6)
    # the logged episode returns stay in the task's units
    np.testing.assert_allclose(after.episode_return + finished, state.episode_return + after.env.reward, rtol=1e-6)


def test_drqv2_privileged_adds_the_weighted_state_error_to_the_encoders_loss():
    """drqv2-privileged: its replay keeps each observation's state (the env's own), its encoder and
    state head learn ``weight ·`` the mean squared error of the head's prediction of the state
    normalised by the replayed states' running statistics — the reported loss, computed here by
    hand from the learner before the update — and the gradient of that term reaches the encoder
    on top of the critic's."""
    weight = 3.0
    agent, previous, state, metrics = small_off_policy_agent(
        "drqv2-privileged", 6, seed_steps=32, updates_per_iteration=1, state_prediction=weight
    )
    assert agent.keeps_state and "state_prediction_loss" in agent.metric_names
    after, _ = jax.jit(agent.collect)(state, jnp.zeros((4, 1)))
    stored = after.replay.experience.state[:, after.replay.current_index - 1]
    np.testing.assert_array_equal(stored, state.env.obs)  # the state of the observation acted in

    learner = previous.learner
    batch = agent.replay.sample(previous.replay, jax.random.PRNGKey(5))
    pixels = batch.obs.astype(jnp.float32)  # any observations: the identity holds for all
    stats = learner.state_stats.update(batch.state)
    target = (batch.state - stats.mean) / jnp.sqrt(stats.var + 1e-5)

    def by_hand(params):
        features = agent.encoder.apply(params["encoder"], pixels)
        return weight * jnp.mean(
            (
                features @ params["state_head"]["params"]["kernel"]
                + params["state_head"]["params"]["bias"]
                - jnp.clip(target, -5, 5)
            )
            ** 2
        )

    auxiliary = agent.state_prediction_loss(stats, batch.state)
    features = agent.encoder.apply(learner.params["encoder"], pixels)
    assert float(auxiliary(learner.params, features)) == pytest.approx(float(by_hand(learner.params)), rel=1e-5)
    weights = jnp.ones(len(batch.reward)) / len(batch.reward)
    fit = jax.jit(
        lambda extra: agent.fit_critic(
            learner.params, learner.critic_opt_state, pixels, batch.action, batch.reward, weights, extra
        ),
        static_argnums=0,
    )
    plain, with_state = fit(None), fit(auxiliary)
    assert float(with_state[2]) == pytest.approx(float(plain[2]), rel=1e-6)  # the critic's loss alone
    assert float(with_state[5]) == pytest.approx(float(by_hand(learner.params)), rel=1e-5)
    moved = np.abs(np.asarray(jax.tree.leaves(with_state[0]["encoder"])[0] - jax.tree.leaves(plain[0]["encoder"])[0]))
    assert moved.max() > 0  # the state's error reaches the encoder
    assert np.isfinite(metrics.logged["state_prediction_loss"]) and metrics.logged["state_prediction_loss"] > 0


def test_cpu_preset_updates_per_round_by_task():
    """The legged robots get the update rate the Hopper sweep chose (4 per round of 16 envs, one
    per 4 agent steps); Cart-pole and dm_control's tasks keep DrQ-v2's own one per 2 agent steps;
    the privileged variant follows DrQ-v2."""
    rate = lambda task, algo="drqv2": make_config(task, algo, "cpu").updates_per_iteration
    for task in ("hopper", "cheetah", "ant", "humanoid", "quadruped"):
        assert rate(task) == rate(task, "drqv2-privileged") == 4, task
    assert rate("cartpole_swingup") == rate("dmc:cartpole-swingup") == 8
    assert make_config("hopper", "drqv2", "paper").updates_per_iteration == 16

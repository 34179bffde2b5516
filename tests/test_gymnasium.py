"""The Gymnasium environments: registration, spaces, seeding, the three autoreset modes as
Gymnasium defines them (state and frame stack), termination against truncation, Gymnasium's own
vector wrappers and env checker, and bad input."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import dva  # noqa: F401  (registers dva/<task>-v0)
from dva.envs.gymnasium import DvaEnv, DvaVectorEnv, env_id
from dva.tasks import BUILTIN_TASKS

NUM_ENVS = 2


@pytest.fixture(scope="module")
def state_env():
    return gymnasium.make_vec("dva/cartpole_swingup-v0", num_envs=NUM_ENVS, autoreset_mode=AutoresetMode.SAME_STEP)


@pytest.fixture(scope="module")
def pixel_env():
    return gymnasium.make_vec(
        "dva/cartpole_swingup-v0",
        num_envs=NUM_ENVS,
        obs_type="both",
        image_size=16,
        frame_stack=2,
        autoreset_mode=AutoresetMode.SAME_STEP,
    )


@pytest.fixture(scope="module")
def next_step_env():
    """Gymnasium's default mode, with pixels."""
    env = gymnasium.make_vec(
        "dva/cartpole_swingup-v0", num_envs=NUM_ENVS, obs_type="both", image_size=16, frame_stack=2
    )
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    return env


def test_every_task_is_registered_with_a_vector_entry_point():
    for task in BUILTIN_TASKS:
        spec = gymnasium.spec(env_id(task))
        assert spec.vector_entry_point == "dva.envs.gymnasium:DvaVectorEnv"
        assert spec.kwargs == {"task": task}


@pytest.mark.parametrize("task", list(BUILTIN_TASKS))
def test_every_task_makes_a_vector_env_whose_space_holds_its_first_observation(task):
    env = gymnasium.make_vec(env_id(task), num_envs=NUM_ENVS)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (NUM_ENVS, *env.single_observation_space.shape) and env.observation_space.contains(obs)
    assert env.single_action_space.shape == (env.unwrapped.task.action_dim,)


def test_spaces_contain_what_reset_and_step_return(state_env, pixel_env):
    assert isinstance(state_env, DvaVectorEnv)
    assert state_env.single_observation_space.shape == (5,)
    assert state_env.single_action_space == gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    pixels = pixel_env.single_observation_space["pixels"]
    assert (pixels.shape, pixels.dtype, pixels.low.min(), pixels.high.max()) == ((16, 16, 6), np.uint8, 0, 255)
    for env in (state_env, pixel_env):
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs) and info == {}
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert reward.shape == terminated.shape == truncated.shape == (NUM_ENVS,)
        assert reward.dtype == np.float32 and terminated.dtype == truncated.dtype == np.bool_


def test_a_seed_makes_the_episodes_reproducible(state_env):
    actions = np.random.default_rng(0).uniform(-1, 1, (20, NUM_ENVS, 1)).astype(np.float32)

    def run(seed):
        observations = [state_env.reset(seed=seed)[0]]
        observations += [state_env.step(action)[0] for action in actions]
        return np.stack(observations)

    first = run(3)
    np.testing.assert_array_equal(run(3), first)
    assert np.abs(run(4) - first).max() > 1e-3
    assert np.abs(first[0, 0] - first[0, 1]).max() > 0  # the sub-environments start apart


def push_off_the_rail(env):
    """Push right from a seeded reset until some cart leaves the rail: the observation before
    that step, and that step's outputs."""
    obs, _ = env.reset(seed=1)
    for _ in range(239):
        previous, (obs, reward, terminated, truncated, info) = obs, env.step(np.ones((NUM_ENVS, 1), np.float32))
        if terminated.any():
            return previous, obs, reward, terminated, truncated, info
    raise AssertionError("no cart left the rail")


def test_running_off_the_rail_terminates_and_resets_in_the_same_step(state_env):
    """Pushing right drives the cart past x = 2.5 (termination, not truncation); that step returns
    the next episode's first observation and the one it reached in info["final_obs"]."""
    previous, obs, reward, terminated, truncated, info = push_off_the_rail(state_env)
    assert terminated.any() and not truncated.any()
    np.testing.assert_array_equal(info["_final_obs"], terminated)
    ended = np.flatnonzero(terminated)
    final = info["final_obs"][ended]
    assert np.all(final[:, 0] >= 2.5) and np.all(np.abs(final[:, 0] - previous[ended, 0]) < 0.2)
    assert np.all(np.abs(obs[ended, 0]) < 0.5)  # the cart is back near the centre
    assert np.all(reward[ended] != 0)


def test_the_episode_length_truncates_every_sub_environment(state_env):
    state_env.reset(seed=2)
    zero = np.zeros((NUM_ENVS, 1), np.float32)
    for _ in range(239):
        _, _, terminated, truncated, info = state_env.step(zero)
        assert not (terminated.any() or truncated.any()) and info == {}
    _, _, terminated, truncated, info = state_env.step(zero)
    assert truncated.all() and not terminated.any() and info["_final_obs"].all()


def test_the_final_frame_stack_continues_the_previous_one(pixel_env):
    """At an episode's end the returned stack restarts as one frame tiled; the final one is the
    previous stack shifted by one frame plus a frame of the pose the step reached."""
    previous, obs, _, terminated, _, info = push_off_the_rail(pixel_env)
    env = int(np.flatnonzero(terminated)[0])
    final = info["final_obs"]["pixels"][env]
    np.testing.assert_array_equal(final[..., :3], previous["pixels"][env][..., 3:])
    restarted = obs["pixels"][env]
    np.testing.assert_array_equal(restarted[..., :3], restarted[..., 3:])
    assert np.abs(final[..., 3:].astype(int) - restarted[..., 3:].astype(int)).max() > 0
    assert info["final_obs"]["state"][env, 0] >= 2.5


def test_next_step_returns_the_reached_observation_then_resets_on_the_next_step(next_step_env):
    """Gymnasium's NEXT_STEP: the ending step returns the observation (and frame stack) it reached;
    the next step ignores that sub-environment's action and returns its new episode's first
    observation with reward 0 and no flags, while the others step on."""
    previous, obs, reward, terminated, truncated, info = push_off_the_rail(next_step_env)
    ended = np.flatnonzero(terminated)
    running = np.flatnonzero(~terminated)
    assert len(ended) and info == {} and not truncated.any()
    assert np.all(obs["state"][ended, 0] >= 2.5) and np.all(reward[ended] != 0)
    np.testing.assert_array_equal(obs["pixels"][ended][..., :3], previous["pixels"][ended][..., 3:])
    after, reward, terminated, truncated, info = next_step_env.step(np.ones((NUM_ENVS, 1), np.float32))
    assert np.all(np.abs(after["state"][ended, 0]) < 0.5) and np.all(reward[ended] == 0)
    assert not terminated[ended].any() and not truncated[ended].any() and info == {}
    restarted = after["pixels"][ended]
    np.testing.assert_array_equal(restarted[..., :3], restarted[..., 3:])  # one frame, repeated
    assert np.all(reward[running] != 0) and np.all(after["state"][running, 0] != obs["state"][running, 0])
    after2, reward, *_ = next_step_env.step(np.zeros((NUM_ENVS, 1), np.float32))
    assert np.all(reward[ended] != 0) and np.all(after2["state"][ended, 0] != after["state"][ended, 0])


def test_disabled_autoreset_waits_for_a_masked_reset():
    """DISABLED: the ending step returns the observation it reached; reset with a mask restarts
    only the masked sub-environments and leaves the others' observations as they were."""
    env = gymnasium.make_vec("dva/cartpole_swingup-v0", num_envs=NUM_ENVS, autoreset_mode="DISABLED")
    assert env.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    _, obs, _, terminated, _, info = push_off_the_rail(env)
    ended = np.flatnonzero(terminated)
    assert info == {} and np.all(obs[ended, 0] >= 2.5)
    reset_obs, _ = env.reset(options={"reset_mask": terminated})
    assert np.all(np.abs(reset_obs[ended, 0]) < 0.5)
    np.testing.assert_array_equal(reset_obs[~terminated], obs[~terminated])
    _, reward, *_ = env.step(np.zeros((NUM_ENVS, 1), np.float32))
    assert np.all(reward != 0)


def test_gymnasiums_vector_wrappers_run_episodes():
    """The wrappers CleanRL stacks, on the default (NEXT_STEP) env, through several episodes."""
    vector = gymnasium.wrappers.vector
    env = gymnasium.make_vec("dva/cartpole_swingup-v0", num_envs=NUM_ENVS)
    env = vector.RecordEpisodeStatistics(env)
    env = vector.ClipAction(env)
    env = vector.NormalizeObservation(env)
    env = vector.TransformObservation(env, lambda obs: np.clip(obs, -10, 10))
    env = vector.NormalizeReward(env)
    obs, _ = env.reset(seed=0)
    episodes = []
    rng = np.random.default_rng(0)
    for _ in range(3 * 240 + 3):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-2, 2, (NUM_ENVS, 1)))
        assert np.isfinite(obs).all() and np.abs(obs).max() <= 10 and np.isfinite(reward).all()
        if "episode" in info:
            episodes += list(info["episode"]["l"][info["_episode"]])
    assert len(episodes) >= 3 * NUM_ENVS and all(0 < length <= 240 for length in episodes)
    assert abs(float(obs.mean())) < 3  # normalised


def test_gymnasium_imports_the_package_from_the_env_id():
    """Gymnasium's module-import form, in a fresh interpreter that never imported dva."""
    code = "import gymnasium; env = gymnasium.make('dva:dva/hopper-v0'); print(env.reset(seed=0)[0].shape)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("(11,)"), out.stderr


def test_one_environment_returns_the_final_observation_and_renders():
    env = gymnasium.make("dva/cartpole_swingup-v0", render_mode="rgb_array", render_size=32)
    assert isinstance(env.unwrapped, DvaEnv)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (5,) and env.observation_space.contains(obs)
    for _ in range(239):
        obs, reward, terminated, truncated, _ = env.step(np.ones(1, np.float32))
        if terminated:
            break
    assert terminated and not truncated and obs[0] >= 2.5 and isinstance(reward, float)
    frame = env.render()
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8 and frame.std() > 0
    frames = env.unwrapped.vector.render()  # a vector env renders a tuple of frames, one per env
    assert isinstance(frames, tuple) and len(frames) == 1 and np.array_equal(frames[0], frame)


def test_bad_arguments_name_the_value_and_what_is_allowed(state_env):
    with pytest.raises(ValueError, match="obs_type 'rgb' is not allowed; use one of state, pixels, both"):
        DvaVectorEnv("hopper", obs_type="rgb")
    with pytest.raises(ValueError, match="array_type 'torch' is not allowed"):
        DvaVectorEnv("hopper", array_type="torch")
    with pytest.raises(ValueError, match="unknown task 'walker'"):
        DvaVectorEnv("walker")
    state_env.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions have shape \(3, 1\); this env needs \(2, 1\)"):
        state_env.step(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="non-finite"):
        state_env.step(np.full((NUM_ENVS, 1), np.nan))
    with pytest.raises(ValueError, match=r"reset options \['seed_all'\] are not supported"):
        state_env.reset(options={"seed_all": True})
    with pytest.raises(ValueError, match=r"reset_mask must be a bool array of shape \(2,\)"):
        state_env.reset(options={"reset_mask": np.ones(3, bool)})
    with pytest.raises(ValueError, match="autoreset_mode 'LATER' is not allowed; use one of NEXT_STEP, SAME_STEP"):
        DvaVectorEnv("hopper", autoreset_mode="LATER")


# The state differs per task; the pixel observation is one renderer and frame stack for all of
# them, so its check runs on a planar robot and a free-floating one (each costs a renderer build
# and compiled reset and step: ~15 s).
CHECKED = [("state", task) for task in BUILTIN_TASKS] + [("pixels", "cartpole_swingup"), ("pixels", "ant")]


@pytest.mark.parametrize(("obs_type", "task"), CHECKED)
def test_gymnasiums_own_env_checker_passes(task, obs_type):
    """Gymnasium's ``check_env`` (seeding, spaces, determinism under a seed, step and reset
    signatures) on a single environment of every task's state and of pixels."""
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make(env_id(task), obs_type=obs_type, image_size=16)
    check_env(env.unwrapped, skip_render_check=True)

"""dm_control's own tasks (``dmc:<domain>-<task>``): the adapter steps, repeats actions, restarts
episodes and stacks frames as dm_control and the off-policy wrapper do, and a baseline trains on it."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from dva.configs import drqv2_dmc_std_decay_steps
from dva.errors import DvaUsageError


def dm_control_or_skip_reason() -> str:
    """Why these tests cannot run here ('' when they can): the extra and a headless OpenGL."""
    try:
        from dva.envs.dmc import make_dmc_task

        env = make_dmc_task("dmc:cartpole-swingup").load(0)
        env.reset()
        env.physics.render(8, 8, camera_id=0)
        env.physics.free()
    except Exception as error:  # noqa: BLE001 - any failure to load or render is the reason to skip
        return f"dm_control tasks unavailable here: {type(error).__name__}: {str(error).splitlines()[0]}"
    return ""


SKIP_REASON = dm_control_or_skip_reason()
needs_dm_control = pytest.mark.skipif(bool(SKIP_REASON), reason=SKIP_REASON)


def test_drqv2_explores_on_its_own_schedule_per_task():
    """DrQ-v2's linear(1.0, 0.1, S) over S agent steps, S by its task class, × action repeat 2."""
    assert drqv2_dmc_std_decay_steps("dmc:cartpole-swingup") == 200_000  # easy
    assert drqv2_dmc_std_decay_steps("dmc:ball_in_cup-catch") == 200_000  # easy
    assert drqv2_dmc_std_decay_steps("dmc:cheetah-run") == 1_000_000  # medium
    assert drqv2_dmc_std_decay_steps("dmc:humanoid-run") == 4_000_000  # hard


@needs_dm_control
def test_names_sizes_and_presets():
    from dva.algorithms import make_config
    from dva.envs.dmc import make_dmc_task
    from dva.envs.factory import check_env_name

    task = make_dmc_task("dmc:cartpole-swingup")
    assert (task.domain, task.task, task.obs_dim, task.action_dim, task.camera) == ("cartpole", "swingup", 5, 1, 0)
    assert make_dmc_task("dmc:quadruped-run").camera == 2
    check_env_name("dmc:cheetah-run")
    with pytest.raises(
        DvaUsageError, match="unknown dm_control task 'dmc:cartpole-spin'; choose one of: .*dmc:cartpole-swingup"
    ):
        check_env_name("dmc:cartpole-spin")
    config = make_config("dmc:cartpole-swingup", "drqv2", "cpu")
    assert (config.reward_scale, config.action_repeat, config.std_decay_steps) == (1.0, 2, 200_000)


@needs_dm_control
def test_a_step_holds_the_action_and_sums_the_rewards_as_dm_control_does():
    from dva.envs.dmc import HostEnvs, flat_observation, make_dmc_task

    task = make_dmc_task("dmc:cartpole-swingup")
    host = HostEnvs(task, 1, None, action_repeat=3)
    first, _ = host.on_thread(host.reset, np.int64(7))
    obs, reached, frames, reward, terminated, truncated = host.on_thread(
        host.step, np.full((1, 1), 0.5, np.float32), np.int64(0)
    )
    reference = task.load(7)
    start = reference.reset()
    np.testing.assert_array_equal(first[0], flat_observation(start.observation))
    steps = [reference.step(np.array([0.5])) for _ in range(3)]
    np.testing.assert_allclose(reward[0], sum(step.reward for step in steps), rtol=1e-6)
    np.testing.assert_allclose(obs[0], flat_observation(steps[-1].observation), rtol=1e-6)
    np.testing.assert_array_equal(reached, obs)  # no episode ended: nothing restarted
    assert frames.shape == (1, 0) and not terminated[0] and not truncated[0]


@needs_dm_control
def test_episodes_end_truncated_after_1000_control_steps_and_restart():
    from dva.envs.dmc import HostEnvs, make_dmc_task

    host = HostEnvs(make_dmc_task("dmc:cartpole-swingup"), 2, None, action_repeat=8)
    host.on_thread(host.reset, np.int64(0))
    zero = np.zeros((2, 1), np.float32)
    for _ in range(124):
        *_, terminated, truncated = host.on_thread(host.step, zero, np.int64(0))
        assert not truncated.any() and not terminated.any()
    obs, reached, _, _, terminated, truncated = host.on_thread(host.step, zero, np.int64(0))
    assert truncated.all() and not terminated.any()  # 125 × 8 = 1000 control steps: the time limit
    assert not np.allclose(obs, reached)  # the restarted episode's observation, not the one reached


@needs_dm_control
def test_frames_with_the_smaller_shadow_map_are_the_suites_but_for_shadow_edges():
    """The adapter's environments draw shadows from a map sized for their frames (8 texels per
    pixel, at least 512: 512² at 48², where the suite's is 2048²); the frames stay the suite's."""
    from dva.envs.dmc import make_dmc_task

    task = make_dmc_task("dmc:cartpole-swingup")
    suite_env, small_map_env = task.load(3), task.load(3, image_size=48)
    assert suite_env.physics.model.vis.quality.shadowsize == 2048
    assert small_map_env.physics.model.vis.quality.shadowsize == 512
    assert task.load(3, image_size=400).physics.model.vis.quality.shadowsize == 2048  # never above the suite's
    frames = []
    for env in (suite_env, small_map_env):
        env.reset()
        drawn = []
        for _ in range(8):
            for _ in range(10):
                env.step(np.ones(1))
            drawn.append(env.physics.render(48, 48, camera_id=task.camera).astype(int))
        frames.append(np.stack(drawn))
        env.physics.free()
    differing = (frames[0] != frames[1]).any(-1).mean()
    assert frames[0].std() > 0 and differing < 1e-3, differing


@needs_dm_control
def test_the_jitted_env_stacks_frames_and_evaluates_on_its_own_batch():
    from dva.envs.dmc import DMCEnv, make_dmc_task

    env = DMCEnv(make_dmc_task("dmc:cartpole-swingup"), 2, image_size=32, frame_stack=3)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert state.frames.shape == (2, 32, 32, 9) and state.frames.std() > 0
    np.testing.assert_array_equal(state.frames[..., :3], state.frames[..., 6:])  # the first frame, tiled
    moved = jax.jit(env.step)(state, np.ones((2, 1), np.float32))
    np.testing.assert_array_equal(moved.frames[..., :6], state.frames[..., 3:])  # the oldest frame dropped
    assert not np.array_equal(moved.frames[..., 6:], state.frames[..., 6:])  # the cart moved
    training_envs = list(env.host.envs)
    evaluation = env.evaluation_env()
    assert evaluation is not env and evaluation is env.evaluation_env()
    jax.jit(evaluation.reset)(jax.random.PRNGKey(1))
    assert env.host.envs == training_envs and evaluation.host.envs[0] is not training_envs[0]


@needs_dm_control
def test_drqv2_trains_on_dm_control_and_the_differentiable_methods_refuse_it(tmp_path):
    import csv

    from dva.algorithms import build_agent, make_config
    from dva.runner.training import train

    small = dict(
        num_envs=1, seed_steps=8, batch_size=8, hidden=(32, 32), feature_dim=16, updates_per_iteration=1, image_size=32
    )
    # One evaluation episode per training env: dm_control steps each evaluation env in Python.
    run_dir = tmp_path / "run"
    train("dmc:cartpole-swingup", "drqv2", iterations=2, run_dir=run_dir, eval_every=2, eval_episodes=None, **small)
    with (run_dir / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    steps = [int(r["env_steps"]) for r in rows]
    assert np.diff(steps).tolist() == [2, 2]  # 1 env × action repeat 2 per iteration, after the seed phase
    assert 0 < float(rows[-1]["eval_return"]) <= 1000  # dm_control's rewards: at most 1 per control step
    with pytest.raises(
        DvaUsageError, match="dva needs this project's differentiable tasks; on dmc:cartpole-swingup use: drqv2"
    ):
        build_agent("dmc:cartpole-swingup", "dva", make_config("dmc:cartpole-swingup", "dva", "cpu"))

"""The examples in examples/ run and do what their docs say."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import gymnasium
import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_ppo_through_gymnasium_learns_cartpole_swingup_from_the_state():
    """CleanRL-style PPO on gymnasium.make_vec("dva/cartpole_swingup-v0"): the first rollouts'
    episodes score ≈ 150 (random actions ≈ 300); after 65k env steps it swings the pole up (the
    last five rollouts' episodes ≈ 1000–1300 measured, as float rounding steers the run; 1900
    after 400k)."""
    ppo = load("ppo_gymnasium")
    curve = ppo.main(ppo.Args(total_steps=65_536))
    first, end = curve[0][1], np.mean([r for _, r in curve[-5:]])
    assert first < 500 and end > 800, curve


def test_a_task_from_the_examples_own_mjcf_trains_with_dva(tmp_path):
    """examples/own_task.py: a pendulum defined in the example's file from its own MJCF string,
    registered with dva.register_task and trained with D.Va from pixels (a few small iterations
    here): the run logs every iteration, finite losses and an evaluation at each end."""
    from dva.tasks import REGISTERED_TASKS, make_task

    own_task = load("own_task")
    try:
        rows = own_task.main(3, tmp_path / "run", num_envs=4, horizon=4, image_size=16, critic_minibatches=2)
    finally:
        REGISTERED_TASKS.pop("pendulum_swingup", None)
        gymnasium.registry.pop("dva/pendulum_swingup-v0", None)
        make_task.cache_clear()
    assert [row["iteration"] for row in rows] == ["0", "1", "2", "3"]
    assert all(math.isfinite(float(row["actor_loss"])) for row in rows[1:])
    # evaluated untrained and at the end; the reward is at most 1 per step over 240 steps
    assert all(math.isfinite(float(rows[i]["eval_return"])) and float(rows[i]["eval_return"]) <= 240 for i in (0, -1))

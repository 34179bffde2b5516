"""A task of your own, defined outside the package, is one call: ``dva.register_task``. The
command line's task check, the presets, Gymnasium and the training loop take it from there."""

from __future__ import annotations

import gymnasium
import jax.numpy as jnp
import numpy as np
import pytest

import dva
from dva.algorithms import make_config
from dva.cli import main
from dva.errors import DvaUsageError
from dva.runner.training import train
from dva.tasks import REGISTERED_TASKS, TARGET_RETURNS, make_task, task_names
from dva.tasks.cartpole import CartpoleSwingup


class CentredCartpole(CartpoleSwingup):
    """Cart-pole swing-up that also pays 1 per step for the cart within 0.5 m of the centre."""

    name = "centred_cartpole"

    def reward(self, data, action):
        return super().reward(data, action) + (jnp.abs(data.qpos[0]) < 0.5)


@pytest.fixture
def registered():
    dva.register_task("centred_cartpole", CentredCartpole, target_return=600.0)
    yield
    REGISTERED_TASKS.pop("centred_cartpole")
    TARGET_RETURNS.pop("centred_cartpole")
    gymnasium.registry.pop("dva/centred_cartpole-v0")
    make_task.cache_clear()


def test_a_task_registered_from_outside_trains_and_is_a_gymnasium_env(registered, tmp_path):
    assert task_names()[-1] == "centred_cartpole" and TARGET_RETURNS["centred_cartpole"] == 600.0
    task = make_task("centred_cartpole")
    assert isinstance(task, CentredCartpole) and task.obs_dim == make_task("cartpole_swingup").obs_dim
    assert make_config("centred_cartpole", "shac", "cpu").num_envs == 16  # presets fall back
    env = gymnasium.make_vec("dva/centred_cartpole-v0", num_envs=2)
    obs, _ = env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros((2, 1), np.float32))
    assert obs.shape == (2, task.obs_dim) and np.all(reward > 0)
    run_dir = train("centred_cartpole", "shac", iterations=2, eval_every=None, run_dir=tmp_path / "run")
    assert (run_dir / "run.json").exists()
    main(
        [
            "train",
            "--task",
            "centred_cartpole",
            "--algo",
            "shac",
            "--iterations",
            "1",
            "--no-report",
            "--run-dir",
            str(tmp_path / "cli"),
        ]
    )  # the command line takes it too
    assert (tmp_path / "cli" / "progress.csv").exists()


def test_a_registered_name_must_be_new_and_well_formed():
    with pytest.raises(DvaUsageError, match="task name 'hopper' is taken by a built-in task"):
        dva.register_task("hopper", CentredCartpole)
    with pytest.raises(DvaUsageError, match="task name 'dmc:x' is not allowed"):
        dva.register_task("dmc:x", CentredCartpole)

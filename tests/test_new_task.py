"""Adding a task is its module and one line in dva.envs.registry: the command line, presets,
Gymnasium and the training loop take it from there. (Its own file: it reloads dva.tasks.)"""

from __future__ import annotations

import importlib

import gymnasium
import numpy as np

TOY_MODULE = '''
import jax.numpy as jnp

from dva.tasks.cartpole import CartpoleSwingup


class CentredCartpole(CartpoleSwingup):
    """Cart-pole swing-up that also pays 1 per step for the cart within 0.5 m of the centre."""

    name = "centred_cartpole"

    def reward(self, data, action):
        return super().reward(data, action) + (jnp.abs(data.qpos[0]) < 0.5)
'''


def test_a_new_task_is_one_module_and_one_registry_line(tmp_path, monkeypatch):
    import dva
    import dva.tasks
    from dva.algorithms import make_config
    from dva.envs.registry import TASK_CLASSES
    from dva.runner.training import train

    (tmp_path / "toy_task.py").write_text(TOY_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(TASK_CLASSES, "centred_cartpole", "toy_task:CentredCartpole")  # the one line
    tasks = importlib.reload(dva.tasks)
    try:
        task = tasks.make_task("centred_cartpole")
        assert task.action_dim == 1 and task.obs_dim == tasks.make_task("cartpole_swingup").obs_dim
        assert make_config("centred_cartpole", "shac", "cpu").num_envs == 16  # presets fall back
        assert make_config("centred_cartpole", "drqv2", "cpu").num_envs > 0
        dva.register_envs()
        env = gymnasium.make_vec("dva/centred_cartpole-v0", num_envs=2)
        obs, _ = env.reset(seed=0)
        _, reward, *_ = env.step(np.zeros((2, 1), np.float32))
        assert obs.shape == (2, task.obs_dim) and np.all(reward > 0)
        run_dir = train("centred_cartpole", "shac", iterations=2, eval_every=None, run_dir=tmp_path / "run")
        assert (run_dir / "run.json").exists()
    finally:
        gymnasium.registry.pop("dva/centred_cartpole-v0", None)
        monkeypatch.undo()
        importlib.reload(dva.tasks)

"""Every task by name and where its class lives: adding a task is its module and one line here.

This module imports nothing heavy, so that ``import dva`` can register the Gymnasium ids
(``dva/<task>-v0``) without loading MuJoCo; :data:`dva.tasks.TASKS` imports the classes.
"""

from __future__ import annotations

TASK_CLASSES: dict[str, str] = {
    "cartpole_swingup": "dva.tasks.cartpole:CartpoleSwingup",
    "cartpole_balance": "dva.tasks.cartpole:CartpoleBalance",
    "hopper": "dva.tasks.planar:Hopper",
    "cheetah": "dva.tasks.planar:Cheetah",
    "ant": "dva.tasks.legged:Ant",
    "humanoid": "dva.tasks.legged:Humanoid",
    "quadruped": "dva.tasks.legged:Quadruped",
}

# dm_control's own tasks (dva.envs.dmc) are named dmc:<domain>-<task>, e.g. dmc:ball_in_cup-catch.
DMC_PREFIX = "dmc:"


def is_dmc(name: str) -> bool:
    """Whether ``name`` names a dm_control task."""
    return name.startswith(DMC_PREFIX)


def dmc_domain_task(name: str) -> tuple[str, str]:
    """dm_control's (domain, task) of ``dmc:<domain>-<task>`` (its task names use ``_``)."""
    domain, _, task = name.removeprefix(DMC_PREFIX).partition("-")
    return domain, task.replace("-", "_")

"""Every task by name and where its class lives: adding a task is its module and one line here
(and, if it has one, a line of :data:`TARGET_RETURNS`).

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

# The return whose first crossing `dva compare` times when no --threshold is given: the paper's
# Fig 4 thresholds on its robots, fixed before their runs; on Cart-pole twice a random policy's
# return on swing-up (275) and 1.9× it on balance (1044), where 2× would be near the maximum 2400.
TARGET_RETURNS: dict[str, float] = {
    "cartpole_swingup": 550.0,
    "cartpole_balance": 1984.0,
    "hopper": 3000.0,
    "cheetah": 3000.0,
    "ant": 1500.0,
    "humanoid": 1000.0,
    "quadruped": 2000.0,
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

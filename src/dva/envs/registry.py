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

"""The task suite: ``make_task(name)`` builds one; ``TASKS`` lists them."""

from __future__ import annotations

import functools
import importlib

from dva.envs.registry import TASK_CLASSES, is_dmc
from dva.errors import DvaUsageError
from dva.tasks.base import CONTROL_DT, EnvState, Task
from dva.tasks.physics import PHYSICS, check_physics


def task_class(path: str) -> type[Task]:
    """The class at ``"module:Class"``."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


# Filled from dva.envs.registry (one line per task), in its order.
TASKS: dict[str, type[Task]] = {name: task_class(path) for name, path in TASK_CLASSES.items()}


def check_task_name(name: str) -> None:
    """Raise a one-line ``ValueError`` naming ``name`` and the tasks there are (``dmc:`` names:
    dm_control's, see :mod:`dva.envs.dmc`)."""
    if is_dmc(name):
        from dva.envs.dmc import make_dmc_task

        make_dmc_task(name)
    elif name not in TASKS:
        raise DvaUsageError(f"unknown task {name!r}; choose one of: {', '.join(TASKS)}, or dmc:<domain>-<task>")


@functools.cache
def make_task(name: str, physics: str | None = None) -> Task:
    """The task called ``name`` with its default or the given contact model (built once per
    process); ``physics`` is one of :data:`PHYSICS` (see :mod:`dva.tasks.physics`)."""
    check_task_name(name)
    return TASKS[name](physics)


__all__ = ["CONTROL_DT", "EnvState", "PHYSICS", "TASKS", "Task", "check_physics", "check_task_name", "make_task"]

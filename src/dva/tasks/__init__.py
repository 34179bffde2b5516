"""The task suite: ``make_task(name)`` builds one; ``TASKS`` lists them."""

from __future__ import annotations

import functools

from dva.tasks.base import CONTROL_DT, EnvState, Task
from dva.tasks.cartpole import CartpoleSwingup
from dva.tasks.legged import Ant, Humanoid
from dva.tasks.planar import Cheetah, Hopper

TASKS: dict[str, type[Task]] = {
    cls.name: cls for cls in (CartpoleSwingup, Hopper, Cheetah, Ant, Humanoid)
}


def check_task_name(name: str) -> None:
    """Raise a one-line ``ValueError`` naming ``name`` and the tasks there are."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of: {', '.join(TASKS)}")


@functools.cache
def make_task(name: str) -> Task:
    """The task called ``name`` (built once per process)."""
    check_task_name(name)
    return TASKS[name]()


__all__ = ["CONTROL_DT", "EnvState", "TASKS", "Task", "check_task_name", "make_task"]

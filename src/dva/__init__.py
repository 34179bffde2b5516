"""dva: visual policies from parallel differentiable simulation (D.Va, SHAC and baselines).

Importing dva changes nothing in the process but Gymnasium's registry (``dva/<task>-v0``, how
Gymnasium finds env packages). :func:`configure` sets what fast runs need; the ``dva`` command,
its worker processes, the benchmarks and the examples call it first. :func:`register_task` adds
a task of your own.
"""

from dva import tasks
from dva.envs.gymnasium import register_envs
from dva.runner.runtime import configure

register_envs()  # gymnasium.make_vec("dva/<task>-v0", ...)


def register_task(name: str, make: tasks.TaskMaker, target_return: float | None = None) -> None:
    """Add the task ``name``, built by ``make(physics)`` (e.g. a subclass of
    :class:`dva.tasks.base.Task`), to everything that takes a task name — ``make_task``, the
    training loop, ``dva compare`` — and to Gymnasium as ``dva/<name>-v0``; ``target_return``: the
    return ``dva compare`` times runs to (see :func:`dva.tasks.register_task`)."""
    tasks.register_task(name, make, target_return)
    register_envs()


__version__ = "0.2.0"
__all__ = ["configure", "register_envs", "register_task"]

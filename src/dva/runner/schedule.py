"""When the training loop does what: one scheduler, "every N iterations or M minutes", for its
evaluations, checkpoints and logs, and the run's own clock."""

from __future__ import annotations

import time


class Every:
    """Due at every ``iterations``-th iteration, or once ``minutes`` have passed since it was last
    :meth:`done` (either, both or neither given: never due)."""

    def __init__(self, iterations: int | None = None, minutes: float | None = None) -> None:
        self.iterations, self.minutes = iterations, minutes
        self.last = time.perf_counter()

    @property
    def on(self) -> bool:
        """Whether it is ever due."""
        return bool(self.iterations or self.minutes)

    def due(self, iteration: int) -> bool:
        return bool(self.iterations and iteration % self.iterations == 0) or bool(
            self.minutes and time.perf_counter() - self.last >= 60 * self.minutes
        )

    def done(self) -> None:
        """Record that it was done now (the minutes count again from here)."""
        self.last = time.perf_counter()


class RunClock:
    """Seconds of a :func:`train` call on the run's clock: everything but evaluations and what was
    paid for elsewhere (a teacher, counted through the agent's ``prior_cost``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def seconds(self) -> float:
        return time.perf_counter() - self.start

    def exclude(self, seconds: float) -> None:
        """Take ``seconds`` off the clock."""
        self.start += seconds

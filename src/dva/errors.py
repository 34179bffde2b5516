"""The one exception type for bad input."""

from __future__ import annotations


class DvaUsageError(ValueError):
    """A value dva does not allow (a task, an option, a budget, a run directory): its message names
    the value and what is allowed, and the command line prints it as one line. Every other
    exception is a bug somewhere and keeps its traceback."""

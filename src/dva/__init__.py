"""dva: visual policies from parallel differentiable simulation (D.Va, SHAC and baselines).

Importing dva changes nothing in the process but Gymnasium's registry (``dva/<task>-v0``, how
Gymnasium finds env packages). :func:`configure` sets what fast runs need; the ``dva`` command,
its worker processes, the benchmarks and the examples call it first.
"""

from dva.envs.gymnasium import register_envs
from dva.runner.runtime import configure

register_envs()  # gymnasium.make_vec("dva/<task>-v0", ...)

__version__ = "0.2.0"
__all__ = ["configure", "register_envs"]

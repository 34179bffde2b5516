"""dva: visual policies from parallel differentiable simulation (D.Va, SHAC and baselines)."""

from dva.gymnasium_envs import register_envs
from dva.runtime import configure_caches, configure_xla

configure_xla()
configure_caches()
register_envs()  # gymnasium.make_vec("dva/<task>-v0", ...)

__version__ = "0.1.0"

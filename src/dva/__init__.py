"""dva: visual policies from parallel differentiable simulation (D.Va, SHAC and baselines)."""

from dva.runtime import configure_caches, configure_xla

configure_xla()
configure_caches()

__version__ = "0.1.0"

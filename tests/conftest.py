"""Shared fixtures. Tasks are built once per session (float32); float64 tests build their own."""

from __future__ import annotations

import os
import sys


def selects_slow_tests(argv: list[str]) -> bool:
    """Whether the command line asks for the slow learning checks (``-m slow``, ``-m "slow and …"``)."""
    for i, arg in enumerate(argv):
        expression = argv[i + 1] if arg == "-m" and i + 1 < len(argv) else arg[2:] if arg.startswith("-m") else ""
        if "slow" in expression and "not slow" not in expression:
            return True
    return False


# The default suite compiles far more than it computes (tiny configurations, each compiled once),
# so it runs XLA's CPU code generated without LLVM optimisation, which compiles several times
# faster (measured on the CI box with cold caches: tests/test_dreamerv3.py 527 s → 88 s), and with
# XLA's older elemental emitters in place of its fusion emitters, which compile the physics' reverse
# passes about twice as fast again (on one core: tests/test_tree.py 392 s → 164 s,
# tests/test_shac.py 378 s → 179 s). The slow learning checks, timed in minutes of training, keep
# XLA's defaults. Set here, before anything imports JAX: its CPU client reads XLA_FLAGS once.
FAST_COMPILE_FLAGS = ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false")
if not selects_slow_tests(sys.argv):
    flags = os.environ.get("XLA_FLAGS", "")
    chosen = [f for f in FAST_COMPILE_FLAGS if f.split("=")[0] not in flags]
    os.environ["XLA_FLAGS"] = " ".join([flags, *chosen]).strip()

import pytest  # noqa: E402

import dva  # noqa: E402  (imports JAX: after XLA_FLAGS)

dva.configure()  # what the command line sets up: the encoder's CPU convolutions, compile caches

from dva.tasks import BUILTIN_TASKS, make_task  # noqa: E402

ALL_TASKS = list(BUILTIN_TASKS)


@pytest.fixture(params=ALL_TASKS)
def task(request: pytest.FixtureRequest):
    return make_task(request.param)

"""Where a cold test suite's time goes: XLA compiles and tracing per test.

As a pytest plugin it records, per test, how many XLA compiles ran and how long they and the
tracing took (JAX's monitoring events), and writes one JSON file per pytest-xdist worker;
as a script it prints the tests with the most compile time. Many small compiles in one test
mean code that runs op by op outside ``jax.jit`` (each primitive compiled on its own):

    DVA_CACHE_DIR=$(mktemp -d) PYTHONPATH=benchmarks .venv/bin/python -m pytest -q -n 2 \\
        --dist loadfile -p compile_profile          # writes compile_profile_gw0.json, …
    python benchmarks/compile_profile.py compile_profile_*.json [--top 30]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import time
from pathlib import Path

import pytest

EVENTS = {
    "compile": "/jax/core/compile/backend_compile_duration",
    "trace": "/jax/core/compile/jaxpr_trace_duration",
    "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration",
}

_current_test: list[str | None] = [None]
_stats: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)


def _record(event: str, seconds: float, **_) -> None:
    for name, key in EVENTS.items():
        if event == key:
            test = _current_test[0] or "<collection and fixtures outside tests>"
            _stats[test][f"{name}_s"] += seconds
            _stats[test][f"{name}_n"] += 1


def pytest_configure(config: pytest.Config) -> None:
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_record)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    _current_test[0] = item.nodeid
    start = time.perf_counter()
    yield
    _stats[item.nodeid]["wall_s"] += time.perf_counter() - start
    _current_test[0] = None


def pytest_unconfigure(config: pytest.Config) -> None:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    Path(f"compile_profile_{worker}.json").write_text(json.dumps({k: dict(v) for k, v in _stats.items()}, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", type=Path)
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()
    rows = [(test, stats) for file in args.files for test, stats in json.loads(file.read_text()).items()]
    rows.sort(key=lambda row: -row[1].get("wall_s", 0.0))
    print("| test | wall (s) | compiles | compile (s) | trace + lower (s) |\n|---|---|---|---|---|")
    for test, s in rows[: args.top]:
        print(
            f"| {test} | {s.get('wall_s', 0):.1f} | {s.get('compile_n', 0)} | {s.get('compile_s', 0):.1f} "
            f"| {s.get('trace_s', 0) + s.get('lower_s', 0):.1f} |"
        )
    total = lambda key: sum(s.get(key, 0.0) for _, s in rows)
    print(
        f"\nall tests: {total('wall_s'):.0f} s of test time (summed over workers), {total('compile_n'):.0f} "
        f"compiles taking {total('compile_s'):.0f} s, tracing and lowering {total('trace_s') + total('lower_s'):.0f} s"
    )


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

"""Timing, memory and table helpers shared by the scripts in ``benchmarks/``."""

from __future__ import annotations

import csv
import resource
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax

# The machine's one-line description lives with the process set-up (the runner records it in each
# run's folder); the benchmarks import it from here with the rest of their helpers.
from dva.runner.runtime import machine_description as machine_description


def timed(fn: Callable[..., Any], *args: Any, repeats: int = 3) -> tuple[float, float, Any]:
    """(compile-and-first-run seconds, best steady-state seconds, output) of ``fn(*args)``."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return first, best, out


def peak_memory_mb() -> float:
    """Peak memory so far: the device's peak bytes where it reports them (GPU), else the
    process's peak resident set (CPU: includes everything the process holds)."""
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """``rows`` (dicts with the same keys) as a CSV file with a header; returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)

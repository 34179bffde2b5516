"""Timing, memory and table helpers shared by the scripts in ``benchmarks/``."""

from __future__ import annotations

import csv
import os
import platform
import resource
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax


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


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name with its family and model numbers as the OS reports them (Linux's
    /proc/cpuinfo, first processor; else ``platform``), or "unknown CPU". Machines of one kind can
    differ in it — a model name alone can be as vague as "AMD EPYC" across generations — and their
    wall-clock numbers with it."""
    fields: dict[str, str] = {}
    if cpuinfo.exists():
        for line in cpuinfo.read_text(errors="replace").split("\n\n")[0].splitlines():
            key, _, value = line.partition(":")
            fields[key.strip()] = value.strip()
    name = fields.get("model name") or platform.processor() or "unknown CPU"
    if "cpu family" in fields and "model" in fields:
        return f"{name}, family {fields['cpu family']} model {fields['model']}"
    return name


def machine_description() -> str:
    """One line naming the CPU model, CPU count, backend and device the numbers came from."""

    device = jax.devices()[0]
    cpu = f"{platform.machine()} {os.cpu_count()} cores ({cpu_model()})"
    return f"{cpu}, JAX {jax.__version__} on {device.platform} ({device.device_kind})"

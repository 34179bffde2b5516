"""Process-wide set-up, done by :func:`configure` and never on import: XLA's CPU convolutions,
persistent compile caches; and the one-line description of the machine the process runs on.

Call ``dva.configure()`` at the start of a script, before JAX computes anything: JAX reads
``XLA_FLAGS`` once, when it starts its CPU client, and Warp reads ``WARP_CACHE_PATH`` when it is
imported. The ``dva`` command, its worker processes, the benchmarks and the examples call it.
"""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

import jax


def cache_root() -> Path:
    """Directory for all of dva's caches (``$DVA_CACHE_DIR`` or ``~/.cache/dva``)."""
    return Path(os.environ.get("DVA_CACHE_DIR", Path.home() / ".cache" / "dva"))


# XLA (jaxlib 0.10) hands unpadded convolutions to YNNPACK on the CPU, which runs the encoder's
# 3×3 × 32-channel layers at ≈ 18 GFLOP/s forward; with YNN's fusions off they run in XLA's Eigen
# kernels at ≈ 110 (docs/development.md, "CPU speed notes"). CPU-only: GPUs ignore it.
YNN_FUSION_FLAG = "xla_cpu_experimental_ynn_fusion_type"
CPU_FLAGS = f"--{YNN_FUSION_FLAG}="  # an empty list: no YNN fusions


def configure_xla() -> None:
    """Add :data:`CPU_FLAGS` to ``XLA_FLAGS`` unless the caller already chose a YNN fusion setting.

    Takes effect only if JAX has not started its backends yet (importing ``dva`` first does that).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if YNN_FUSION_FLAG not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {CPU_FLAGS}".strip()


def configure_caches() -> None:
    """Point Warp's kernel cache and JAX's persistent compilation cache at :func:`cache_root`.

    Both compilers are slow on a small CPU (Warp's renderer kernels take ~50 s, a jitted training
    iteration tens of seconds); caching makes every run after the first start in seconds.
    """
    root = cache_root()
    os.environ.setdefault("WARP_CACHE_PATH", str(root / "warp"))

    jax.config.update("jax_compilation_cache_dir", str(root / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def configure() -> None:
    """Everything a fast run needs, for scripts that use dva: :func:`configure_xla` (the pixel
    encoder's CPU convolutions) and :func:`configure_caches` (compile caches).
    Call it first; calling it again changes nothing."""
    configure_xla()
    configure_caches()


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


def machine_line(iteration: int) -> str:
    """A line of a run's machines.txt: the machine that trains it from ``iteration`` on."""
    return f"iteration {iteration}: {machine_description()}"


# What machine_line writes, read back by machine_in_line.
MACHINE_LINE = re.compile(r"iteration \d+: .*? cores \((?P<cpu>.*)\), JAX \S+ on (?P<platform>\w+) \((?P<device>.*)\)")


def machine_in_line(line: str) -> str | None:
    """The machine a machines.txt line names: its CPU model, and its accelerator when the run did
    not run on the CPU; None if ``line`` is not such a line."""
    if not (match := MACHINE_LINE.fullmatch(line.strip())):
        return None
    return match["cpu"] if match["platform"] == "cpu" else f"{match['cpu']} + {match['device']}"

"""Paper Fig 10 and Table 1: what one actor gradient costs, D.Va vs visual SHAC.

Both compute the same policy gradient's inputs from the same rollout; visual SHAC differentiates
through the (differentiable) renderer and every step's encoder inside the reverse scan, D.Va
only through the physics, then through the encoder a chunk of steps at a time. Measured
per task in one process: backward seconds (gradient minus forward, steady state) and the memory
XLA allocates for the gradient computation (arguments, outputs and temporaries; on CPU the
process's resident set would mix all tasks measured before, and the compiler's own).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed
from tqdm import tqdm

from dva.algorithms import make_config
from dva.algorithms.shac import SHAC, TrainState
from dva.analysis.bench import markdown_table, timed, write_csv
from dva.analysis.profile import build_shac

COMPARED = ("dva", "shac-pixels")  # the method and its baseline (paper's "SHAC + diff. rendering")
DVA_VARIANTS = ("dva", "dva-privileged")  # what an analysis may put in the method's place
PAPER_BACKWARD_S = {  # the paper's Table 1 (RTX 4080): (D.Va, visual SHAC)
    "cartpole_swingup": (0.11, 0.36),
    "hopper": (0.19, 0.51),
    "ant": (0.21, 0.58),
    "humanoid": (0.68, 1.38),
}


def gradient_cost(agent: SHAC, state: TrainState, timing: bool = True) -> dict[str, float]:
    """Forward and backward seconds of one actor gradient at ``state``, and its planned peak
    memory. The times are NaN when that peak would not fit in the memory available now, or
    without ``timing`` (then ``state`` may be shapes only: the gradient is only compiled)."""
    cfg = agent.config
    noise = jax.random.normal(jax.random.PRNGKey(1), (cfg.horizon, cfg.num_envs, agent.task.action_dim))
    args = (state.actor_params, state, noise)
    gradient = jax.jit(lambda p, s, n: agent.actor_gradient(p, s, n)[2]).lower(*args).compile()
    peak_bytes = planned_memory_bytes(gradient)
    cost = {"forward_s": float("nan"), "backward_s": float("nan"), "peak_memory_mb": peak_bytes / 2**20}
    if timing and peak_bytes < 0.8 * available_memory_bytes():
        forward = jax.jit(lambda p, s, n: agent.rollout(p, s, n)[0])
        cost["forward_s"] = timed(forward, *args, repeats=1)[1]
        cost["backward_s"] = timed(gradient, *args, repeats=1)[1] - cost["forward_s"]
    return cost


def planned_memory_bytes(compiled: jax.stages.Compiled) -> int:
    """What XLA allocates to run ``compiled``: arguments, outputs and the temporaries of its buffer
    assignment (one block on CPU; scan residuals included). XLA's own ``peak_memory_in_bytes`` is
    not usable on CPU: it reports 2 MB for a scan whose residuals take 128 MB."""
    stats = compiled.memory_analysis()
    if stats is None:
        raise RuntimeError(f"XLA reports no memory analysis on {jax.default_backend()}")
    return (
        stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes - stats.alias_size_in_bytes
    )


def available_memory_bytes() -> float:
    """Free device memory (GPU) or available physical memory (CPU)."""
    stats = jax.devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return stats["bytes_limit"] - stats.get("bytes_in_use", 0)
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def measure_costs(
    tasks: list[str],
    num_envs: int = 32,
    horizon: int = 32,
    image_size: int = 84,
    seed: int = 0,
    chunk: int = 1,
    kept: bool = False,
    timing: bool = True,
) -> list[dict]:
    """One row per task and variant: D.Va with ``actor_backward_chunk = chunk``, with ``kept`` also
    D.Va reusing the rollout's kept backward passes (chunk 0), and visual SHAC — same networks,
    envs, horizon, images. Without ``timing`` only the memory, from compiling (minutes instead of
    an hour)."""
    variants: list[tuple[str, int | None, str]] = [("dva", chunk, f"dva, chunk {chunk}")]
    if kept:
        variants.append(("dva", 0, "dva, kept"))
    variants.append((COMPARED[1], None, COMPARED[1]))
    rows = []
    for task in tqdm(tasks, desc="gradient cost", dynamic_ncols=True):
        for algo, algo_chunk, variant in variants:
            overrides = {"actor_backward_chunk": algo_chunk} if algo == COMPARED[0] else {}
            config = make_config(
                task, algo, "paper", num_envs=num_envs, horizon=horizon, image_size=image_size, **overrides
            )
            agent = build_shac(task, algo, config)
            init = jax.jit(agent.init) if timing else lambda key: jax.eval_shape(agent.init, key)
            state = init(jax.random.PRNGKey(seed))
            rows.append(
                {
                    "task": task,
                    "algo": algo,
                    "variant": variant,
                    "actor_backward_chunk": "" if algo_chunk is None else algo_chunk,  # 0: kept
                    **gradient_cost(agent, state, timing),
                }
            )
    return rows


def ratios(rows: list[dict]) -> list[dict]:
    """Per task and D.Va variant: visual SHAC ÷ D.Va for backward time and peak memory, next to the
    paper's backward ratio."""
    out = []
    for task in dict.fromkeys(r["task"] for r in rows):
        shac = next(r for r in rows if r["task"] == task and r["algo"] == COMPARED[1])
        paper = PAPER_BACKWARD_S.get(task)
        for dva in (r for r in rows if r["task"] == task and r["algo"] == COMPARED[0]):
            out.append(
                {
                    "task": task,
                    "variant": dva["variant"],
                    "backward_ratio": shac["backward_s"] / dva["backward_s"],
                    "memory_ratio": shac["peak_memory_mb"] / dva["peak_memory_mb"],
                    "paper_backward_ratio": paper[1] / paper[0] if paper else float("nan"),
                }
            )
    return out


def write_cost_report(rows: list[dict], out_dir: Path, title: str) -> tuple[list[Path], str]:
    """``cost.csv``, ``cost_ratios.csv``, ``cost.png`` (bars per task) and a markdown table."""
    table = write_csv(out_dir / "cost.csv", rows)
    ratio_rows = ratios(rows)
    ratio_table = write_csv(out_dir / "cost_ratios.csv", ratio_rows)
    tasks = list(dict.fromkeys(r["task"] for r in rows))
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    by_key = {(r["task"], r["variant"]): r for r in rows}
    # Memory only (--no-timing): the times are NaN and get no panel.
    panels = [
        (key, label)
        for key, label in (
            ("backward_s", "backward time per iteration (s)"),
            ("peak_memory_mb", "peak memory of the gradient (MB)"),
        )
        if np.isfinite([r[key] for r in rows]).any()
    ]
    fig = Figure(figsize=(5 * len(panels), 3.8), dpi=120)
    axes = fig.subplots(1, len(panels), squeeze=False)
    axes = axes[0]
    x = np.arange(len(tasks))
    width = 0.8 / len(variants)
    for ax, (key, label) in zip(axes, panels):
        for i, variant in enumerate(variants):
            values = [by_key[(task, variant)][key] for task in tasks]
            ax.bar(x + (i - (len(variants) - 1) / 2) * width, values, width, label=variant)
        ax.set_xticks(x, tasks, fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    figure = out_dir / "cost.png"
    fig.savefig(figure)
    markdown = markdown_table(
        [
            "task",
            "D.Va variant",
            "backward D.Va (s)",
            "backward visual SHAC (s)",
            "ratio",
            "paper ratio",
            "memory D.Va (MB)",
            "memory visual SHAC (MB)",
            "ratio",
        ],
        [
            (
                r["task"],
                r["variant"],
                f"{by_key[(r['task'], r['variant'])]['backward_s']:.3f}",
                f"{by_key[(r['task'], COMPARED[1])]['backward_s']:.3f}",
                f"{r['backward_ratio']:.1f}×",
                f"{r['paper_backward_ratio']:.1f}×" if np.isfinite(r["paper_backward_ratio"]) else "–",
                f"{by_key[(r['task'], r['variant'])]['peak_memory_mb']:.0f}",
                f"{by_key[(r['task'], COMPARED[1])]['peak_memory_mb']:.0f}",
                f"{r['memory_ratio']:.1f}×",
            )
            for r in ratio_rows
        ],
    )
    (out_dir / "cost.md").write_text(f"{title}\n\n{markdown}\n")
    return [table, ratio_table, figure, out_dir / "cost.md"], markdown

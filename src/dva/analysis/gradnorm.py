"""Paper Fig 9: the actor gradient norm over training, D.Va vs visual SHAC, per task.

Each pair is trained with the same preset and seed (no evaluations: only the norms matter). The
divergence guard is lifted to NaN only — an update from a huge gradient is still clipped to
``clip_grad_norm`` — so the norm can be followed as far as it goes; a run that turns NaN ends there
and the report says where.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

from dva.analysis.bench import markdown_table, write_csv
from dva.analysis.cost import COMPARED
from dva.analysis.plots import read_curve
from dva.runner.training import TrainingDiverged, train


def gradient_norms(
    tasks: list[str],
    iterations: int,
    out_dir: Path,
    seed: int = 0,
    preset: str = "cpu",
    algos: tuple[str, ...] = COMPARED,
    **overrides,
) -> tuple[list[dict], list[dict]]:
    """Train every algorithm of ``algos`` (D.Va and visual SHAC) on every task for ``iterations``.

    Returns per-iteration rows (task, algo, iteration, actor_grad_norm) and one summary row per
    run (median and max norm, and the iteration it diverged at, if it did).
    """
    rows, summary = [], []
    for task in tasks:
        for algo in algos:
            run_dir = out_dir / "runs" / f"{task}_{algo}_s{seed}"
            shutil.rmtree(run_dir, ignore_errors=True)  # a fresh run each time the analysis runs
            diverged: TrainingDiverged | None = None
            try:
                train(
                    task,
                    algo,
                    preset=preset,
                    seed=seed,
                    iterations=iterations,
                    run_dir=run_dir,
                    eval_every=None,
                    checkpoint_every=iterations,
                    abort_grad_norm=float("inf"),
                    **overrides,
                )
            except TrainingDiverged as error:
                diverged = error
            curve = read_curve(run_dir, "actor_grad_norm")
            norms = list(curve["actor_grad_norm"])
            steps = list(range(1, len(norms) + 1))
            if diverged is not None:  # the rejected update's norm was not logged
                norms.append(float(diverged.logged["actor_grad_norm"]))
                steps.append(diverged.iteration)
            rows += [{"task": task, "algo": algo, "iteration": i, "actor_grad_norm": g} for i, g in zip(steps, norms)]
            finite = np.array([g for g in norms if np.isfinite(g)])
            summary.append(
                {
                    "task": task,
                    "algo": algo,
                    "iterations": len(norms),
                    "median_norm": float(np.median(finite)) if finite.size else float("nan"),
                    "max_norm": float(finite.max()) if finite.size else float("nan"),
                    "diverged_at": diverged.iteration if diverged else "",
                }
            )
    return rows, summary


def write_gradnorm_report(rows: list[dict], summary: list[dict], out_dir: Path, title: str) -> tuple[list[Path], str]:
    """``gradnorm.csv`` (per iteration), ``gradnorm_summary.csv``/``.md`` and ``gradnorm.png``
    (one panel per task, log scale; a cross where a run diverged)."""
    table = write_csv(out_dir / "gradnorm.csv", rows)
    summary_table = write_csv(out_dir / "gradnorm_summary.csv", summary)
    tasks = list(dict.fromkeys(r["task"] for r in summary))
    fig = Figure(figsize=(4 * len(tasks), 3.4), dpi=120)
    axes = fig.subplots(1, len(tasks), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for algo in dict.fromkeys(r["algo"] for r in summary):
            run = [r for r in rows if r["task"] == task and r["algo"] == algo]
            (line,) = ax.semilogy([r["iteration"] for r in run], [r["actor_grad_norm"] for r in run], label=algo, lw=1)
            end = next(s for s in summary if s["task"] == task and s["algo"] == algo)
            if end["diverged_at"] != "" and run and np.isfinite(run[-1]["actor_grad_norm"]):
                ax.plot(run[-1]["iteration"], run[-1]["actor_grad_norm"], "x", color=line.get_color(), ms=9)
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("actor gradient norm (before clipping)")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    figure = out_dir / "gradnorm.png"
    fig.savefig(figure)
    markdown = markdown_table(
        ["task", "algo", "iterations", "median norm", "max norm", "diverged at"],
        [
            (
                s["task"],
                s["algo"],
                s["iterations"],
                f"{s['median_norm']:.3g}",
                f"{s['max_norm']:.3g}",
                s["diverged_at"] or "–",
            )
            for s in summary
        ],
    )
    (out_dir / "gradnorm.md").write_text(f"{title}\n\n{markdown}\n")
    return [table, summary_table, figure, out_dir / "gradnorm.md"], markdown

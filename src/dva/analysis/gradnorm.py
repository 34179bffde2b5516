"""Paper Fig 9: the actor gradient norm over training, D.Va vs visual SHAC, per task.

Each pair is trained with the same preset and seed (no evaluations: only the norms matter). The
divergence guard is lifted to NaN only — an update from a huge gradient is still clipped to
``clip_grad_norm`` — so the norm can be followed as far as it goes; a run that turns NaN ends there
and the report says where. Runs checkpoint every few minutes: running the analysis again resumes an
interrupted run, extends a shorter one and reuses a finished one (a run of another configuration in
its folder is refused).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

from dva.analysis.bench import markdown_table, write_csv
from dva.analysis.compare import Setting, check_same_setting, saved_iteration
from dva.analysis.cost import COMPARED
from dva.analysis.plots import read_curve
from dva.runner.training import TrainingDiverged, train

# Where a run that turned NaN records its last iteration and norm (the rejected update is not in
# its log), so that a later analysis of the same run reports it again without training.
DIVERGED = "diverged.json"


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
            diverged = train_for_norms(task, algo, iterations, run_dir, seed, preset, overrides)
            if diverged is not None and diverged["iteration"] > iterations:
                diverged = None  # a longer run of the same setting: its first ``iterations`` were healthy
            curve = read_curve(run_dir, "actor_grad_norm")
            norms = list(curve["actor_grad_norm"])[:iterations]
            steps = list(range(1, len(norms) + 1))
            if diverged is not None:  # the rejected update's norm was not logged
                norms.append(diverged["actor_grad_norm"])
                steps.append(diverged["iteration"])
            rows += [{"task": task, "algo": algo, "iteration": i, "actor_grad_norm": g} for i, g in zip(steps, norms)]
            finite = np.array([g for g in norms if np.isfinite(g)])
            summary.append(
                {
                    "task": task,
                    "algo": algo,
                    "iterations": len(norms),
                    "median_norm": float(np.median(finite)) if finite.size else float("nan"),
                    "max_norm": float(finite.max()) if finite.size else float("nan"),
                    "diverged_at": diverged["iteration"] if diverged else "",
                }
            )
    return rows, summary


def train_for_norms(
    task: str, algo: str, iterations: int, run_dir: Path, seed: int, preset: str, overrides: dict[str, Any]
) -> dict | None:
    """Train, resume or reuse the run in ``run_dir`` until it has ``iterations``; returns where it
    diverged (``{"iteration", "actor_grad_norm"}``), or None."""
    settings = dict(overrides, abort_grad_norm=float("inf"))
    if (run_dir / "run.json").exists():
        check_same_setting(Setting(algo, task, algo, tuple(settings.items())), preset, run_dir)
    marker = run_dir / DIVERGED
    if marker.exists():
        return json.loads(marker.read_text())
    done = saved_iteration(run_dir)
    if done is None:
        shutil.rmtree(run_dir, ignore_errors=True)  # a start that never reached its first checkpoint
        how: dict[str, Any] = dict(preset=preset, seed=seed, iterations=iterations, **settings)
    elif done < iterations:
        how = dict(resume=True, iterations=iterations - done)
    else:
        return None
    try:
        train(task, algo, run_dir=run_dir, eval_every=None, **how)  # checkpoints every few minutes
    except TrainingDiverged as error:
        diverged = {"iteration": error.iteration, "actor_grad_norm": float(error.logged["actor_grad_norm"])}
        marker.write_text(json.dumps(diverged))
        return diverged
    return None


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

"""The paper's comparisons, one command each (``dva compare FIGURE``): every setting × task × seed
trained for the same wall-clock budget through the one training loop, then the return curves (vs
wall-clock and vs env steps, mean ± std over seeds) and a table of final returns and time to a
threshold, as PNG + CSV + markdown under ``out``.

Runs live in ``out/runs/<task>_<setting>_s<seed>``. A run that finished its budget is skipped, a
run cut short (a crash, a smaller earlier budget) resumes from its last checkpoint for the minutes
it lacks, so a comparison survives a crash and grows with more seeds or minutes.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import typing
from pathlib import Path
from typing import Literal

FigureName = Literal["fig4", "fig6", "fig7", "ablation-value", "ablation-frames"]
FIGURES: tuple[str, ...] = typing.get_args(FigureName)
COMPLETE = "complete.json"  # written into a run directory when its budget is spent


@dataclasses.dataclass(frozen=True)
class Setting:
    """One curve of a comparison: ``algo`` on ``task`` with config ``overrides``."""

    label: str
    task: str
    algo: str
    overrides: tuple[tuple[str, object], ...] = ()

    @property
    def slug(self) -> str:
        return re.sub(r"[^a-z0-9]+", "_", f"{self.task} {self.label}".lower()).strip("_")


def figure_settings(figure: str, tasks: list[str]) -> list[Setting]:
    """The settings a figure compares on each of ``tasks``.

    fig4: D.Va against the model-free (DrQ-v2, CURL) and model-based (DreamerV3) visual baselines; fig6:
    D.Va vs state-to-visual DAgger (its teacher's time included); fig7: D.Va vs visual SHAC;
    ablation-value: D.Va with and without its critic; ablation-frames: D.Va with 1–6 frames.
    """
    if figure not in FIGURES:
        raise ValueError(f"figure {figure!r} is not allowed; use one of: {', '.join(FIGURES)}")
    if figure == "ablation-value":
        per_task = [("D.Va", "dva", ()), ("D.Va without critic", "dva", (("use_critic", False),))]
    elif figure == "ablation-frames":
        per_task = [(f"D.Va, {k} frame{'s' * (k > 1)}", "dva", (("frame_stack", k),)) for k in range(1, 7)]
    else:
        algos = {"fig4": ("dva", "drqv2", "curl", "dreamerv3"), "fig6": ("dva", "dagger"),
                 "fig7": ("dva", "shac-pixels")}[figure]
        per_task = [(algo, algo, ()) for algo in algos]
    return [Setting(label, task, algo, overrides) for task in tasks for label, algo, overrides in per_task]


def run_setting(setting: Setting, seed: int, minutes: float, preset: str, run_dir: Path) -> str:
    """Train, resume or skip one run so that it has had ``minutes``; returns what it did."""
    from dva.training import checkpoint_manager, read_progress, train

    marker = run_dir / COMPLETE
    if marker.exists() and json.loads(marker.read_text())["minutes"] >= minutes:
        return "skipped (complete)"
    if (run_dir / "run.json").exists() and checkpoint_manager(run_dir).latest_step() is not None:
        logged = read_progress(run_dir)  # the minutes it has, wall_time of its last row
        train(setting.task, setting.algo, run_dir=run_dir, resume=True,
              minutes=max(minutes - float(logged[-1]["wall_time"]) / 60 if logged else minutes, 0.0))
        action = "resumed"
    else:
        shutil.rmtree(run_dir, ignore_errors=True)  # a start that never reached its first checkpoint
        train(setting.task, setting.algo, preset=preset, seed=seed, minutes=minutes, run_dir=run_dir,
              **dict(setting.overrides))
        action = "trained"
    marker.write_text(json.dumps({"minutes": minutes}))
    return action


def compare(figure: str, tasks: list[str], seeds: list[int], minutes: float, out: Path, preset: str = "cpu",
            threshold: float | None = None) -> tuple[list[Path], str]:
    """Run (or complete) every run of ``figure`` and write its curves and table into ``out``."""
    from dva.analysis.plots import plot_runs, write_summary  # matplotlib: only when plotting

    settings = figure_settings(figure, tasks)
    labels: dict[Path, str] = {}
    for setting in settings:
        for seed in seeds:
            run_dir = out / "runs" / f"{setting.slug}_s{seed}"
            action = run_setting(setting, seed, minutes, preset, run_dir)
            print(f"{setting.label} on {setting.task}, seed {seed}: {action}")
            labels[run_dir] = f"{setting.label} on {setting.task}"
    figures = plot_runs(list(labels), out, labels=labels)
    table, markdown = write_summary(list(labels), out, threshold=threshold, labels=labels)
    return [*figures, table, out / "summary.md"], markdown

"""The paper's comparisons, one command each (``dva compare FIGURE``): every setting × task × seed
trained for the same wall-clock budget through the one training loop, then the return curves (vs
wall-clock and vs env steps, mean ± std over seeds) and a table of final returns and time to a
threshold, as PNG + CSV + markdown under ``out``.

Runs live in ``out/runs/<task>_<setting>_s<seed>``. A run that finished its budget is skipped, a
run cut short (a crash, a smaller earlier budget) resumes from its last checkpoint for the minutes
it lacks, so a comparison survives a crash and grows with more seeds or minutes.

With ``workers`` > 1 the runs go to that many child processes at once, each pinned to its own
equal share of the CPUs (``python -m dva.analysis.compare`` runs one), so that every run of a
wall-clock comparison gets the same compute however many run beside it; each child's output goes
to ``out/runs/<run>.log``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import typing
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Literal

FigureName = Literal["fig4", "fig6", "fig7", "fig13", "ablation-value", "ablation-frames"]
FIGURES: tuple[str, ...] = typing.get_args(FigureName)
FRAME_STACKS: tuple[int, ...] = (1, 2, 3, 4, 5, 6)  # ablation-frames' settings, as the paper's
COMPLETE = "complete.json"  # written into a run directory when its budget is spent
# Every run is evaluated once per minute of its own clock, whatever its iteration time (D.Va ≈ 1 s,
# DAgger's student ≈ 12 s on the CPU preset), so times to a threshold have the same resolution.
EVAL_MINUTES = 1.0


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


def figure_settings(figure: str, tasks: list[str], frames: Sequence[int] | None = None) -> list[Setting]:
    """The settings a figure compares on each of ``tasks``.

    fig4: D.Va against the model-free (DrQ-v2, CURL) and model-based (DreamerV3) visual baselines; fig6:
    D.Va vs state-to-visual DAgger (its teacher's time included); fig7: D.Va vs visual SHAC; fig13:
    SHAC vs DPG on the state (the full gradient against the decoupled one, no pixels);
    ablation-value: D.Va with and without its critic; ablation-frames: D.Va with each number of
    stacked frames in ``frames`` (default 1–6; a subset makes a long per-run budget affordable).
    """
    if figure not in FIGURES:
        raise ValueError(f"figure {figure!r} is not allowed; use one of: {', '.join(FIGURES)}")
    if frames is not None and figure != "ablation-frames":
        raise ValueError(f"frames = {list(frames)} is only allowed with ablation-frames, not with {figure!r}")
    if frames is not None and (
        not frames or len(set(frames)) != len(frames) or not all(isinstance(k, int) and k >= 1 for k in frames)
    ):
        raise ValueError(f"frames = {list(frames)} is not allowed; use distinct ints ≥ 1, e.g. 1 2 3")
    if figure == "ablation-value":
        per_task = [("D.Va", "dva", ()), ("D.Va without critic", "dva", (("use_critic", False),))]
    elif figure == "ablation-frames":
        per_task = [
            (f"D.Va, {k} frame{'s' * (k > 1)}", "dva", (("frame_stack", k),))
            for k in (FRAME_STACKS if frames is None else frames)
        ]
    else:
        algos = {
            "fig4": ("dva", "drqv2", "curl", "dreamerv3"),
            "fig6": ("dva", "dagger"),
            "fig7": ("dva", "shac-pixels"),
            "fig13": ("shac", "dpg-state"),
        }[figure]
        per_task = [(algo, algo, ()) for algo in algos]
    return [Setting(label, task, algo, overrides) for task in tasks for label, algo, overrides in per_task]


def is_complete(run_dir: Path, minutes: float) -> bool:
    """Whether the run in ``run_dir`` has already had ``minutes`` of training."""
    marker = run_dir / COMPLETE
    return marker.exists() and json.loads(marker.read_text())["minutes"] >= minutes


def run_setting(setting: Setting, seed: int, minutes: float, preset: str, run_dir: Path) -> str:
    """Train, resume or skip one run so that it has had ``minutes``; returns what it did."""
    from dva.training import checkpoint_manager, read_progress, train

    if is_complete(run_dir, minutes):
        return "skipped (complete)"
    if (run_dir / "run.json").exists() and checkpoint_manager(run_dir).latest_step() is not None:
        logged = read_progress(run_dir)  # the minutes it has, wall_time of its last row
        train(
            setting.task,
            setting.algo,
            run_dir=run_dir,
            resume=True,
            eval_every=None,
            eval_minutes=EVAL_MINUTES,
            minutes=max(minutes - float(logged[-1]["wall_time"]) / 60 if logged else minutes, 0.0),
        )
        action = "resumed"
    else:
        shutil.rmtree(run_dir, ignore_errors=True)  # a start that never reached its first checkpoint
        train(
            setting.task,
            setting.algo,
            preset=preset,
            seed=seed,
            minutes=minutes,
            run_dir=run_dir,
            eval_every=None,
            eval_minutes=EVAL_MINUTES,
            **dict(setting.overrides),
        )
        action = "trained"
    (run_dir / COMPLETE).write_text(json.dumps({"minutes": minutes}))
    return action


@dataclasses.dataclass(frozen=True)
class Job:
    """One run of a comparison, as a child process receives it (JSON on its command line)."""

    figure: str
    task: str
    slug: str  # which of the figure's settings on ``task``
    seed: int
    minutes: float
    preset: str
    run_dir: str
    frames: tuple[int, ...] | None = None  # ablation-frames' subset, if one was asked for

    def setting(self) -> Setting:
        frames = None if self.frames is None else tuple(self.frames)  # a list after its trip through JSON
        return next(s for s in figure_settings(self.figure, [self.task], frames) if s.slug == self.slug)

    def run(self) -> str:
        return run_setting(self.setting(), self.seed, self.minutes, self.preset, Path(self.run_dir))


def cpu_groups(cpus: Sequence[int], workers: int) -> list[tuple[int, ...]]:
    """``cpus`` split into ``workers`` disjoint groups of equal size (a remainder stays unused)."""
    if not isinstance(workers, int) or not 1 <= workers <= len(cpus):
        raise ValueError(
            f"workers = {workers!r} is not allowed; use an int from 1 to the {len(cpus)} CPUs this process may use"
        )
    ordered, size = sorted(cpus), len(cpus) // workers
    return [tuple(ordered[i * size : (i + 1) * size]) for i in range(workers)]


def available_cpus() -> list[int]:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def launch_pinned(job: Job, cpus: tuple[int, ...]) -> str:
    """Run ``job`` in a child process limited to ``cpus``; its output goes to ``<run_dir>.log``."""
    log = Path(job.run_dir).with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as output:
        child = subprocess.Popen(
            [sys.executable, "-m", "dva.analysis.compare", json.dumps(dataclasses.asdict(job))],
            stdout=output,
            stderr=subprocess.STDOUT,
        )
        # Pinned from here, not by a preexec_fn (unsafe to fork with JAX's threads running): Popen
        # returns once the child has exec'd, long before its interpreter starts any thread.
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(child.pid, cpus)
        returncode = child.wait()
    if returncode != 0:
        raise RuntimeError(f"run {job.run_dir} failed (exit {returncode}); its output is in {log}")
    return f"ran on CPUs {','.join(map(str, cpus))} (log: {log})"


def run_parallel(
    jobs: Sequence[Job],
    groups: Sequence[tuple[int, ...]],
    launch: Callable[[Job, tuple[int, ...]], str] = launch_pinned,
) -> list[str]:
    """Run ``jobs`` with one at a time on each CPU group, in order; returns what each did. Every
    job runs even when another fails; then the first failure is raised."""
    free: queue.Queue[tuple[int, ...]] = queue.Queue()
    for group in groups:
        free.put(group)

    def one(job: Job) -> str | Exception:
        cpus = free.get()
        try:
            return launch(job, cpus)
        except Exception as error:  # noqa: BLE001 - reported after the other runs finished
            return error
        finally:
            free.put(cpus)

    with ThreadPoolExecutor(len(groups)) as pool:
        results = list(pool.map(one, jobs))
    for result in results:
        if isinstance(result, Exception):
            raise result
    return results  # type: ignore[return-value]


def compare(
    figure: str,
    tasks: list[str],
    seeds: list[int],
    minutes: float,
    out: Path,
    preset: str = "cpu",
    threshold: float | None = None,
    workers: int = 1,
    frames: Sequence[int] | None = None,
) -> tuple[list[Path], str]:
    """Run (or complete) every run of ``figure`` and write its curves and table into ``out``;
    ``workers`` > 1 runs that many at once, each on its own share of the CPUs; ``frames`` picks
    ablation-frames' stack sizes."""
    from dva.analysis.plots import plot_runs, write_summary  # matplotlib: only when plotting

    groups = cpu_groups(available_cpus(), workers)
    labels: dict[Path, str] = {}
    jobs: list[Job] = []
    for setting in figure_settings(figure, tasks, frames):
        for seed in seeds:
            run_dir = out / "runs" / f"{setting.slug}_s{seed}"
            labels[run_dir] = f"{setting.label} on {setting.task}"
            jobs.append(
                Job(
                    figure,
                    setting.task,
                    setting.slug,
                    seed,
                    minutes,
                    preset,
                    str(run_dir),
                    None if frames is None else tuple(frames),
                )
            )

    def report(job: Job, action: str) -> None:
        print(f"{labels[Path(job.run_dir)]}, seed {job.seed}: {action}", flush=True)

    if workers == 1:
        for job in jobs:
            report(job, job.run())
    else:
        pending = [job for job in jobs if not is_complete(Path(job.run_dir), minutes)]
        print(f"{len(pending)} runs on {workers} workers of {len(groups[0])} CPUs each", flush=True)
        launched = dict(zip(pending, run_parallel(pending, groups, launch_pinned)))
        for job in jobs:
            report(job, launched.get(job, "skipped (complete)"))
    figures = plot_runs(list(labels), out, labels=labels)
    table, markdown = write_summary(list(labels), out, threshold=threshold, labels=labels)
    return [*figures, table, out / "summary.md"], markdown


if __name__ == "__main__":  # one run of a comparison in a child process (see launch_pinned)
    print(Job(**json.loads(sys.argv[1])).run())

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
to ``out/runs/<run>.log``. With ``backend="ray"`` each run is a Ray task with its share of CPUs
and GPUs, on the cluster at ``RAY_ADDRESS`` or on one that Ray starts on this machine; the same
rules skip and resume runs, so ``out`` must be a folder every node sees.

``dva sweep`` (:func:`grid_settings`) runs a grid of config values × tasks × seeds by the same
rules.
"""

from __future__ import annotations

import dataclasses
import itertools
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
from typing import Any, Literal

from dva.algorithms import check_algo, make_config
from dva.analysis.plots import plot_runs, write_summary
from dva.errors import DvaUsageError
from dva.runner.checkpoint import RunSpec, checkpoint_manager
from dva.runner.logs import read_progress
from dva.runner.runtime import configure
from dva.runner.training import train
from dva.tasks import TARGET_RETURNS

FigureName = Literal["fig4", "fig6", "fig7", "fig13", "ablation-value", "ablation-frames"]
FIGURES: tuple[str, ...] = typing.get_args(FigureName)
FRAME_STACKS: tuple[int, ...] = (1, 2, 3, 4, 5, 6)  # ablation-frames' settings, as the paper's
COMPLETE = "complete.json"  # written into a run directory when its budget is spent
# Every run is evaluated once per minute of its own clock by default, whatever its iteration time
# (D.Va ≈ 1 s, DAgger's student ≈ 12 s on the CPU preset), so times to a threshold have the same
# resolution; a slower interval is for methods whose evaluation costs minutes (TD-MPC2 plans each step).
EVAL_MINUTES = 1.0
# The algorithms each figure compares by default (the paper's), and those ``algos`` may add: the
# privileged variants, which learn from the simulator's state beside the pixels.
COMPARED: dict[str, tuple[str, ...]] = {
    "fig4": ("dva", "drqv2", "curl", "dreamerv3", "tdmpc2"),
    "fig6": ("dva", "dagger"),
    "fig7": ("dva", "shac-pixels"),
    "fig13": ("shac", "dpg-state"),
}
EXTENSIONS: dict[str, tuple[str, ...]] = {"fig4": ("dva-privileged", "drqv2-privileged"), "fig7": ("dva-privileged",)}
ABLATIONS = ("dva", "dva-privileged")  # the D.Va an ablation may vary (one, chosen by ``algos``)


@dataclasses.dataclass(frozen=True)
class Setting:
    """One curve of a comparison: ``algo`` on ``task`` with config ``overrides``."""

    label: str
    task: str
    algo: str
    overrides: tuple[tuple[str, Any], ...] = ()

    @property
    def slug(self) -> str:
        return re.sub(r"[^a-z0-9]+", "_", f"{self.task} {self.label}".lower()).strip("_")


def figure_settings(
    figure: str, tasks: list[str], frames: Sequence[int] | None = None, algos: Sequence[str] | None = None
) -> list[Setting]:
    """The settings a figure compares on each of ``tasks``.

    fig4: D.Va against the model-free (DrQ-v2, CURL) and model-based (DreamerV3, TD-MPC2) visual
    baselines; fig6: D.Va vs state-to-visual DAgger (its teacher's time included); fig7: D.Va vs
    visual SHAC; fig13: SHAC vs DPG on the state (the full gradient against the decoupled one, no pixels);
    ablation-value: D.Va with and without its critic; ablation-frames: D.Va with each number of
    stacked frames in ``frames`` (default 1–6; a subset makes a long per-run budget affordable);
    an ablation varies ``dva``, or the one D.Va variant in ``algos``.
    ``algos`` keeps only the settings of those algorithms (e.g. fig4's dva and drqv2 where the
    model-based baselines would not fit the budget) and may add the figure's :data:`EXTENSIONS`.
    """
    if figure not in FIGURES:
        raise DvaUsageError(f"figure {figure!r} is not allowed; use one of: {', '.join(FIGURES)}")
    if frames is not None and figure != "ablation-frames":
        raise DvaUsageError(f"frames = {list(frames)} is only allowed with ablation-frames, not with {figure!r}")
    if frames is not None and (
        not frames or len(set(frames)) != len(frames) or not all(isinstance(k, int) and k >= 1 for k in frames)
    ):
        raise DvaUsageError(f"frames = {list(frames)} is not allowed; use distinct ints ≥ 1, e.g. 1 2 3")
    per_task: list[tuple[str, str, tuple[tuple[str, Any], ...]]]  # (label, algo, config overrides)
    if figure in ("ablation-value", "ablation-frames"):  # ``algos``: which D.Va the ablation varies
        if algos is not None and (len(algos) != 1 or algos[0] not in ABLATIONS):
            raise DvaUsageError(
                f"algos = {list(algos)} is not allowed for {figure}; use one of: {', '.join(ABLATIONS)}"
            )
        dva, algos = (algos or ["dva"])[0], None
    if figure == "ablation-value":
        per_task = [(dva, dva, ()), (f"{dva} without critic", dva, (("use_critic", False),))]
    elif figure == "ablation-frames":
        per_task = [
            (f"{dva}, {k} frame{'s' * (k > 1)}", dva, (("frame_stack", k),))
            for k in (FRAME_STACKS if frames is None else frames)
        ]
    else:
        per_task = [(algo, algo, ()) for algo in COMPARED[figure]]
    if algos is not None:
        allowed = list(dict.fromkeys([*(algo for _, algo, _ in per_task), *EXTENSIONS.get(figure, ())]))
        if not algos or len(set(algos)) != len(algos) or not set(algos) <= set(allowed):
            raise DvaUsageError(
                f"algos = {list(algos)} is not allowed for {figure}; use distinct names from: {', '.join(allowed)}"
            )
        listed = [entry for entry in per_task if entry[1] in algos]
        per_task = listed + [(algo, algo, ()) for algo in algos if algo not in {entry[1] for entry in listed}]
    return [Setting(label, task, algo, overrides) for task in tasks for label, algo, overrides in per_task]


def is_complete(run_dir: Path, minutes: float) -> bool:
    """Whether the run in ``run_dir`` has already had ``minutes`` of training."""
    marker = run_dir / COMPLETE
    return marker.exists() and json.loads(marker.read_text())["minutes"] >= minutes


def saved_iteration(run_dir: Path) -> int | None:
    """The iteration of the last checkpoint of the run in ``run_dir`` (None: no run there, or none
    saved yet): where a resumed run continues from."""
    return checkpoint_manager(run_dir).latest_step() if (run_dir / "run.json").exists() else None


def minutes_trained(run_dir: Path, iteration: int) -> float:
    """The wall-clock minutes a run resumed from its checkpoint at ``iteration`` has had: that
    iteration's logged ``wall_time``, not the last row's (a resume drops the rows logged after the
    checkpoint, so their minutes are trained again)."""
    kept = [row for row in read_progress(run_dir) if int(row["iteration"]) <= iteration]
    return float(kept[-1]["wall_time"]) / 60 if kept else 0.0


def run_setting(
    setting: Setting, seed: int, minutes: float, preset: str, run_dir: Path, eval_minutes: float = EVAL_MINUTES
) -> str:
    """Train, resume or skip one run so that it has had ``minutes``, evaluated every ``eval_minutes``
    of its clock; returns what it did."""

    if (run_dir / "run.json").exists():
        check_same_setting(setting, preset, run_dir)
    if is_complete(run_dir, minutes):
        return "skipped (complete)"
    how: dict[str, Any] | None  # train()'s arguments, or None: nothing to train
    saved = saved_iteration(run_dir)
    if saved is not None:
        left = minutes - minutes_trained(run_dir, saved)
        # a run cut short after its budget was spent (before its completion mark) needs no training
        action, how = ("resumed", dict(resume=True, minutes=left)) if left > 0 else ("had its minutes", None)
    else:
        shutil.rmtree(run_dir, ignore_errors=True)  # a start that never reached its first checkpoint
        action, how = "trained", dict(preset=preset, seed=seed, minutes=minutes, **dict(setting.overrides))
    if how is not None:
        train(setting.task, setting.algo, run_dir=run_dir, eval_every=None, eval_minutes=eval_minutes, **how)
    (run_dir / COMPLETE).write_text(json.dumps({"minutes": minutes}))
    return action


def check_same_setting(setting: Setting, preset: str, run_dir: Path) -> None:
    """A run folder is reused only for the algorithm and config it was trained with: a clear error
    naming what differs where ``setting`` under ``preset`` asks for another (a changed preset, an
    old run of a renamed variant)."""

    spec = RunSpec.read(run_dir / "run.json")
    wanted = make_config(setting.task, setting.algo, preset, **dict(setting.overrides))
    if getattr(wanted, "teacher", "") is None:  # DAgger: the teacher it trained is part of the run
        wanted = dataclasses.replace(wanted, teacher=spec.config.teacher)
    differences = [f"algo {spec.algo} (wanted {setting.algo})"] if spec.algo != setting.algo else []
    if type(spec.config) is type(wanted):
        old, new = dataclasses.asdict(spec.config), dataclasses.asdict(wanted)
        differences += [f"{key} {old[key]!r} (wanted {new[key]!r})" for key in new if old.get(key) != new[key]]
    if differences:
        raise DvaUsageError(
            f"{run_dir} holds a run of another setting than {setting.label!r} under the {preset} preset: "
            f"{', '.join(differences)}; move it away or use another --out"
        )


@dataclasses.dataclass(frozen=True)
class Job:
    """One run of a comparison, as a child process or a Ray task receives it (JSON-able)."""

    setting: Setting
    seed: int
    minutes: float
    preset: str
    run_dir: str
    eval_minutes: float = EVAL_MINUTES

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, text: str) -> Job:
        values = json.loads(text)
        setting = values.pop("setting")
        # JSON turned the overrides' tuples into lists; configs need them hashable again.
        overrides = tuple((name, _tuples(value)) for name, value in setting.pop("overrides"))
        return cls(Setting(**setting, overrides=overrides), **values)

    def run(self) -> str:
        return run_setting(self.setting, self.seed, self.minutes, self.preset, Path(self.run_dir), self.eval_minutes)


def _tuples(value):
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def cpu_groups(cpus: Sequence[int], workers: int) -> list[tuple[int, ...]]:
    """``cpus`` split into ``workers`` disjoint groups of equal size (a remainder stays unused)."""
    if not isinstance(workers, int) or not 1 <= workers <= len(cpus):
        raise DvaUsageError(
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
            [sys.executable, "-m", "dva.analysis.compare", job.to_json()],
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


Backend = Literal["local", "ray"]
BACKENDS: tuple[str, ...] = typing.get_args(Backend)


def run_on_ray(jobs: Sequence[Job], cpus: float, gpus: float) -> list[str]:
    """Run ``jobs`` as Ray tasks of ``cpus`` CPUs and ``gpus`` GPUs each, on the cluster at
    ``RAY_ADDRESS`` or on a local one that Ray starts; returns what each did. Every job runs even
    when another fails; then the first failure is raised."""
    try:  # the 'ray' extra, imported only for --backend ray
        import ray
    except ImportError:
        raise ImportError("--backend ray needs the 'ray' extra: pip install 'dva[ray]'") from None
    if not ray.is_initialized():
        # A cluster started here runs its workers at normal priority, as the local backend's
        # processes (Ray's default niceness of 15 lets anything else on the machine starve them).
        os.environ.setdefault("RAY_worker_niceness", "0")
        ray.init(address=os.environ.get("RAY_ADDRESS"), log_to_driver=False)

    @ray.remote(num_cpus=cpus, num_gpus=gpus)
    def run(job_json: str) -> str:
        configure()  # a Ray worker is a fresh process
        return Job.from_json(job_json).run()

    futures = [run.remote(job.to_json()) for job in jobs]
    results: list[str | Exception] = []
    for future in futures:
        try:
            results.append(ray.get(future))
        except Exception as error:  # noqa: BLE001 - reported after the other runs finished
            results.append(RuntimeError(f"a run failed on Ray: {error}"))
    for result in results:
        if isinstance(result, Exception):
            raise result
    return results  # type: ignore[return-value]


def run_settings(
    settings: Sequence[Setting],
    out: Path,
    *,
    seeds: Sequence[int],
    minutes: float,
    preset: str = "cpu",
    threshold: float | None = None,
    eval_minutes: float = EVAL_MINUTES,
    workers: int = 1,
    backend: str = "local",
    cpus_per_run: float = 1.0,
    gpus_per_run: float = 0.0,
) -> tuple[list[Path], str]:
    """Run (or complete) every setting × seed under ``out/runs`` for ``minutes`` each, then write
    the curves and the table (time to ``threshold``, or else to each task's entry in
    :data:`~dva.tasks.TARGET_RETURNS`) into ``out``. Each run is evaluated every ``eval_minutes`` of
    its own clock. ``workers`` > 1 runs that many at
    once, each on its own share of the CPUs; ``backend="ray"`` runs them as Ray tasks of
    ``cpus_per_run`` CPUs and ``gpus_per_run`` GPUs. Settings come from :func:`figure_settings`
    (``dva compare``) or :func:`grid_settings` (``dva sweep``)."""

    if backend not in BACKENDS:
        raise DvaUsageError(f"backend {backend!r} is not allowed; use one of: {', '.join(BACKENDS)}")
    if not eval_minutes > 0:
        raise DvaUsageError(f"--eval-minutes {eval_minutes!r} is not allowed; use a number of minutes > 0")
    groups = cpu_groups(available_cpus(), workers) if backend == "local" else []
    labels: dict[Path, str] = {}
    thresholds: dict[str, float | None] = {}
    jobs: list[Job] = []
    for setting in settings:
        label = f"{setting.label} on {setting.task}"
        thresholds[label] = threshold if threshold is not None else TARGET_RETURNS.get(setting.task)
        for seed in seeds:
            run_dir = out / "runs" / f"{setting.slug}_s{seed}"
            labels[run_dir] = label
            jobs.append(Job(setting, seed, minutes, preset, str(run_dir), eval_minutes))

    def report(job: Job, action: str) -> None:
        print(f"{labels[Path(job.run_dir)]}, seed {job.seed}: {action}", flush=True)

    if backend == "local" and workers == 1:
        for job in jobs:
            report(job, job.run())
    else:
        pending = [job for job in jobs if not is_complete(Path(job.run_dir), minutes)]
        if backend == "ray":
            print(f"{len(pending)} runs on Ray, {cpus_per_run} CPUs and {gpus_per_run} GPUs each", flush=True)
            done = run_on_ray(pending, cpus_per_run, gpus_per_run) if pending else []
        else:
            print(f"{len(pending)} runs on {workers} workers of {len(groups[0])} CPUs each", flush=True)
            done = run_parallel(pending, groups, launch_pinned)
        launched = dict(zip(pending, done))
        for job in jobs:
            report(job, launched.get(job, "skipped (complete)"))
    figures = plot_runs(list(labels), out, labels=labels)
    table, markdown = write_summary(list(labels), out, threshold=thresholds, labels=labels)
    return [*figures, table, out / "summary.md"], markdown


def grid_settings(algo: str, tasks: Sequence[str], grid: Sequence[str]) -> list[Setting]:
    """One setting per task and combination of ``grid``'s values; each entry is ``FIELD=V1,V2,…``
    for a field of ``algo``'s config, values read as JSON where they parse (numbers, true/false,
    lists) and as strings otherwise."""

    fields = {field.name for field in dataclasses.fields(check_algo(algo).config_type)}
    axes: list[list[tuple[str, object]]] = []
    for entry in grid:
        name, _, values = entry.partition("=")
        name = name.strip().replace("-", "_")
        if not values or name not in fields:
            raise DvaUsageError(
                f"grid entry {entry!r} is not allowed; use FIELD=V1,V2 with a field of {algo}'s config "
                f"({', '.join(sorted(fields))})"
            )
        axes.append([(name, _tuples(value)) for value in _values(values)])
    combos = list(itertools.product(*axes)) if axes else [()]
    label = lambda combo: ", ".join(f"{name}={value}" for name, value in combo) or algo
    return [Setting(label(combo), task, algo, tuple(combo)) for task in tasks for combo in combos]


def _values(text: str) -> list:
    """``1e-3,2e-3`` → [0.001, 0.002]; ``[64,64],[128]`` → [[64, 64], [128]]; ``a,b`` → ["a", "b"]."""
    try:
        return json.loads(f"[{text}]")
    except json.JSONDecodeError:
        return text.split(",")


if __name__ == "__main__":  # one run of a comparison in a child process (see launch_pinned)
    configure()
    print(Job.from_json(sys.argv[1]).run())

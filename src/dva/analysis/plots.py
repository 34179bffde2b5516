"""Learning curves of one or more runs (``dva plot``): return vs wall-clock and vs env steps,
runs of the same task and algorithm (different seeds) drawn as mean ± std."""

from __future__ import annotations

import csv
import dataclasses
import json
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

from dva.analysis.statistics import bootstrap_interval, interval_text, mean_and_std_text, sample_std
from dva.errors import DvaUsageError

METRICS = ("eval_return", "train_return")
# A single evaluation swings by ±25 % on the legged tasks (a dive, a lucky episode), so the summary
# also gives each run's median over its last evaluations: 10 minutes in ``dva compare`` (once a minute).
LATE_POINTS = 10
AXES = {"env_steps": "environment steps", "wall_time": "wall-clock time (s)"}


def read_curve(run_dir: Path, metric: str) -> dict[str, np.ndarray]:
    """The logged ``metric`` of a run with its env steps and wall-clock, rows where it is finite."""
    path = Path(run_dir) / "progress.csv"
    if not path.exists():
        raise DvaUsageError(f"{run_dir} has no progress.csv (is it a run directory?)")
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if r[metric] not in ("", "nan")]
    return {key: np.array([float(r[key]) for r in rows]) for key in (metric, *AXES)}


def run_label(run_dir: Path) -> str:
    """``algo on task`` from the run's ``run.json`` (seeds of one label are averaged); a state
    gradient clip is part of the label, so clipped and exact runs are not averaged together."""
    spec = json.loads((Path(run_dir) / "run.json").read_text())
    clip = spec.get("config", {}).get("state_grad_clip")
    variant = f", state grad clip {clip:g}" if clip is not None else ""
    return f"{spec['algo']} on {spec['task']} ({spec['preset']} preset{variant})"


def mean_and_std(curves: list[dict[str, np.ndarray]], x_key: str, metric: str):
    """Seeds interpolated onto a shared grid up to the shortest run: (x, mean, std)."""
    curves = [c for c in curves if len(c[x_key]) > 0]
    end = min(c[x_key][-1] for c in curves)
    start = max(c[x_key][0] for c in curves)
    grid = np.linspace(start, end, 100) if len(curves) > 1 else curves[0][x_key]
    values = np.stack([np.interp(grid, c[x_key], c[metric]) for c in curves])
    return grid, values.mean(0), values.std(0)


def past_shortest(
    curves: list[dict[str, np.ndarray]], x_key: str, metric: str, end: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (x, y) of each seed that ran past ``end`` (where :func:`mean_and_std`'s grid stops), from
    its last point at or before it (so that it joins the mean there)."""
    parts = []
    for c in curves:
        start = max(int(np.searchsorted(c[x_key], end, side="right")) - 1, 0)
        if c[x_key][-1] > end:
            parts.append((c[x_key][start:], c[metric][start:]))
    return parts


def grouped_curves(
    run_dirs: list[Path], metric: str, labels: dict[Path, str] | None = None
) -> dict[str, list[dict[str, np.ndarray]]]:
    """The runs' curves of ``metric`` grouped by label (the seeds of one setting): ``labels[run_dir]``
    where given, else :func:`run_label`."""
    if metric not in METRICS:
        raise DvaUsageError(f"metric {metric!r} is not allowed; use one of: {', '.join(METRICS)}")
    groups: dict[str, list[dict[str, np.ndarray]]] = defaultdict(list)
    for run_dir in run_dirs:
        curve = read_curve(run_dir, metric)
        if len(curve[metric]) == 0:
            raise DvaUsageError(f"{run_dir} has no {metric} logged yet")
        groups[labels[run_dir] if labels and run_dir in labels else run_label(run_dir)].append(curve)
    return groups


def first_reach(curve: dict[str, np.ndarray], metric: str, threshold: float) -> tuple[float, float] | None:
    """``(wall_time, env_steps)`` of the first logged point with ``metric ≥ threshold``, or None."""
    reached = np.flatnonzero(curve[metric] >= threshold)
    if len(reached) == 0:
        return None
    return float(curve["wall_time"][reached[0]]), float(curve["env_steps"][reached[0]])


def summarize_runs(
    run_dirs: list[Path],
    metric: str = "eval_return",
    threshold: float | Mapping[str, float | None] | None = None,
    labels: dict[Path, str] | None = None,
) -> list[dict]:
    """One row per setting: seeds, final, late (each run's median over its last
    :data:`LATE_POINTS` logged values; mean ± sample std over seeds, and the mean's
    percentile-bootstrap 95 % interval) and best ``metric``, run length, and
    with a threshold how many seeds reached it and the median wall-clock and env steps they took
    (NaN when none did). ``threshold`` is one value for every setting or one per setting's label
    (a label it maps to None, or lacks, is not timed)."""
    rows = []
    for label, curves in grouped_curves(run_dirs, metric, labels).items():
        target = threshold.get(label) if isinstance(threshold, Mapping) else threshold
        final = np.array([c[metric][-1] for c in curves])
        late = np.array([np.median(c[metric][-LATE_POINTS:]) for c in curves])
        best = np.array([c[metric].max() for c in curves])
        late_low, late_high = bootstrap_interval(late)
        row = {
            "setting": label,
            "seeds": len(curves),
            "final_mean": final.mean(),
            "final_std": sample_std(final),
            "late_mean": late.mean(),
            "late_std": sample_std(late),
            "late_low": late_low,
            "late_high": late_high,
            "best_mean": best.mean(),
            "minutes": np.mean([c["wall_time"][-1] for c in curves]) / 60,
            "env_steps": np.mean([c["env_steps"][-1] for c in curves]),
        }
        if target is not None:
            reached = [r for r in (first_reach(c, metric, target) for c in curves) if r is not None]
            row.update(
                threshold=target,
                reached=len(reached),
                minutes_to_threshold=np.median([r[0] for r in reached]) / 60 if reached else np.nan,
                env_steps_to_threshold=np.median([r[1] for r in reached]) if reached else np.nan,
            )
        rows.append(row)
    return rows


def summary_markdown(rows: list[dict], metric: str) -> str:
    """:func:`summarize_runs`'s rows as a markdown table (the threshold columns where a row has one),
    and with several settings the one whose seeds' late medians have the highest mean."""
    timed = any("threshold" in row for row in rows)
    header = [
        "setting",
        "seeds",
        f"final {metric}",
        f"median of the last {LATE_POINTS}",
        "its 95 % interval (bootstrap over seeds)",
        f"best {metric}",
        "minutes",
        "env steps",
    ]
    if timed:
        header += ["threshold", "seeds reaching it", "minutes to it (median)", "env steps to it (median)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [
            row["setting"],
            str(row["seeds"]),
            mean_and_std_text(row["final_mean"], row["final_std"], row["seeds"]),
            mean_and_std_text(row["late_mean"], row["late_std"], row["seeds"]),
            interval_text(row["late_low"], row["late_high"], row["seeds"]),
            f"{row['best_mean']:.0f}",
            f"{row['minutes']:.1f}",
            f"{row['env_steps']:.0f}",
        ]
        if "threshold" in row:
            cells += [
                f"{row['threshold']:g}",
                f"{row['reached']} / {row['seeds']}",
                f"{row['minutes_to_threshold']:.1f}",
                f"{row['env_steps_to_threshold']:.0f}",
            ]
        elif timed:
            cells += ["–"] * 4
        lines.append("| " + " | ".join(cells) + " |")
    if len(rows) > 1:
        best = max(rows, key=lambda row: row["late_mean"])
        lines += ["", f"Highest median of the last {LATE_POINTS} (mean over seeds): {best['setting']}"]
    return "\n".join(lines) + "\n"


def write_summary(
    run_dirs: list[Path],
    out_dir: Path,
    metric: str = "eval_return",
    threshold: float | Mapping[str, float | None] | None = None,
    labels: dict[Path, str] | None = None,
) -> tuple[Path, str]:
    """Write ``summary.csv`` and ``summary.md`` (:func:`summarize_runs`); returns the CSV's path and
    the markdown."""
    rows = summarize_runs(run_dirs, metric, threshold, labels)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "summary.csv"
    with path.open("w", newline="") as f:
        # Every row's columns, in order: an untimed setting has no threshold columns (left empty).
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(key for row in rows for key in row)))
        writer.writeheader()
        writer.writerows(rows)
    markdown = summary_markdown(rows, metric)
    (out_dir / "summary.md").write_text(markdown)
    return path, markdown


def plot_runs(
    run_dirs: list[Path], out_dir: Path, metric: str = "eval_return", labels: dict[Path, str] | None = None
) -> list[Path]:
    """Write ``{metric}_vs_env_steps.png`` and ``{metric}_vs_wall_time.png`` (curves grouped as in
    :func:`grouped_curves`); returns their paths."""
    return plot_curves(grouped_curves(run_dirs, metric, labels), out_dir, metric)


@dataclasses.dataclass(frozen=True)
class PublishedCurve:
    """A curve its authors published, per env step: ``values`` (points × columns) holds either their
    seeds or their lowest, median and highest seed; it is drawn as the median of the columns
    (dashed) within their range."""

    label: str
    env_steps: np.ndarray
    values: np.ndarray


def plot_curves(
    groups: dict[str, list[dict[str, np.ndarray]]],
    out_dir: Path,
    metric: str,
    published: PublishedCurve | None = None,
) -> list[Path]:
    """Plot each group of curves (the seeds of a setting) as its mean ± std against env steps and
    against wall-clock (a seed that ran past the shortest one continues as a thin line), one PNG
    each, ``published`` beside them against env steps; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for x_key, x_label in AXES.items():
        fig = Figure(figsize=(6, 4), dpi=120)
        ax = fig.subplots()
        for label, curves in groups.items():
            x, mean, std = mean_and_std(curves, x_key, metric)
            (line,) = ax.plot(x, mean, label=f"{label}, {len(curves)} seed{'s' * (len(curves) > 1)}")
            if len(curves) > 1:
                ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.25)
                # A seed that ran longer than the others goes on alone, thin, past their mean.
                for seed_x, seed_y in past_shortest(curves, x_key, metric, x[-1]):
                    ax.plot(seed_x, seed_y, color=line.get_color(), linewidth=0.8, alpha=0.7)
        if published is not None and x_key == "env_steps":
            x, values = published.env_steps, published.values
            (line,) = ax.plot(x, np.median(values, axis=1), "--", color="0.3", label=published.label)
            ax.fill_between(x, values.min(axis=1), values.max(axis=1), color=line.get_color(), alpha=0.15)
        ax.set_xlabel(x_label)
        ax.set_ylabel(metric.replace("_", " "))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out_dir / f"{metric}_vs_{x_key}.png"
        fig.savefig(path)
        written.append(path)
    return written

"""What a run logs: ``progress.csv`` (one row per iteration, appended; rewritten atomically when
edited), TensorBoard and, with ``--track``, Weights & Biases; and the progress bar."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
from tensorboardX import SummaryWriter
from tqdm import tqdm

from dva.algorithms.base import Agent
from dva.runner.runtime import machine_line
from dva.runner.tracking import WandbTracker

MACHINES = "machines.txt"  # one line per start or resume of a run: its first iteration and the machine


def record_machine(run_dir: Path, iteration: int) -> None:
    """Append to the run's ``machines.txt`` the machine that trains it from ``iteration`` on: a
    run's wall-clock numbers depend on the CPU, and a resumed run may continue on another."""
    with open(Path(run_dir) / MACHINES, "a") as file:
        file.write(machine_line(iteration) + "\n")


def read_progress(run_dir) -> list[dict]:
    """The rows of a run's ``progress.csv``."""
    with (Path(run_dir) / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def csv_fields(agent: Agent) -> list[str]:
    """The columns of ``progress.csv``: the loop's, then the agent's own metrics."""
    return ["iteration", "env_steps", "wall_time", "train_return", "eval_return", *agent.metric_names, "iteration_time"]


class ProgressLog:
    """``progress.csv`` (appended row by row, rewritten atomically when edited) and TensorBoard."""

    def __init__(self, run_dir: Path, fields: list[str], tracker: WandbTracker | None = None) -> None:
        self.path, self.fields, self.tracker = run_dir / "progress.csv", fields, tracker
        self.rows: list[dict] = []
        if self.path.exists():
            with self.path.open() as f:
                self.rows = list(csv.DictReader(f))
        self.writer = SummaryWriter(str(run_dir / "tensorboard"))

    def append(self, row: dict) -> None:
        """Log one row (missing fields stay empty)."""
        self.rows.append(row)
        new = not self.path.exists()
        with self.path.open("a", newline="") as f:
            out = csv.DictWriter(f, fieldnames=self.fields, restval="")
            if new:
                out.writeheader()
            out.writerow(row)
        for key, value in row.items():
            if key != "iteration" and value != "" and np.isfinite(float(value)):
                self.writer.add_scalar(key, float(value), int(row["env_steps"]))
        if self.tracker is not None:
            self.tracker.log(row, int(row["env_steps"]))

    def set_last(self, key: str, value: float) -> None:
        """Fill in a field of the last row."""
        self.rows[-1][key] = value
        self._rewrite()
        self.writer.add_scalar(key, value, int(self.rows[-1]["env_steps"]))
        if self.tracker is not None:
            self.tracker.log({key: value}, int(self.rows[-1]["env_steps"]))

    def truncate(self, iteration: int) -> None:
        """Forget the rows logged after ``iteration``."""
        self.rows = [row for row in self.rows if int(row["iteration"]) <= iteration]
        self._rewrite()

    def close(self) -> None:
        self.writer.close()

    def _rewrite(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        with tmp.open("w", newline="") as f:
            out = csv.DictWriter(f, fieldnames=self.fields, restval="")
            out.writeheader()
            out.writerows(self.rows)
        tmp.replace(self.path)


def show_progress(bar: tqdm, row: dict, seconds_left: float | None) -> None:
    """Advance the progress bar by one iteration, showing ``row``'s numbers and, for a time budget
    (tqdm knows no ETA for it), the seconds left."""
    bar.update(1)
    postfix = dict(steps=row["env_steps"], ret=f"{row['train_return']:.1f}", s_it=f"{row['iteration_time']:.2f}")
    if seconds_left is not None:
        postfix["left"] = time.strftime("%H:%M:%S", time.gmtime(seconds_left))
    bar.set_postfix(postfix)

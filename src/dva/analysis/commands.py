"""The ``dva analyze`` commands, each beside the analysis it runs: the options tyro turns into
flags and a ``run()`` that calls the analysis and prints its table and files."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from dva.analysis.breakdown import measure_iteration, write_breakdown_report
from dva.analysis.cost import DVA_VARIANTS, measure_costs, write_cost_report
from dva.analysis.gradients import compare_gradients, write_gradient_report
from dva.analysis.gradnorm import gradient_norms, write_gradnorm_report
from dva.envs.rendering import check_image_size
from dva.errors import DvaUsageError
from dva.runner.runtime import machine_description
from dva.tasks import task_names


@dataclasses.dataclass
class SizeOverrides:
    """Options shared by the analyses that build trainers: the preset's sizes, overridden."""

    seed: int = 0
    out: Path = Path("analysis")
    num_envs: int | None = None
    """Override the preset's number of parallel envs."""
    horizon: int | None = None
    """Override the preset's short horizon h."""
    image_size: int | None = None
    """Override the preset's image side (pixels)."""

    def overrides(self) -> dict[str, Any]:
        return {"num_envs": self.num_envs, "horizon": self.horizon, "image_size": self.image_size}


def print_report(paths: list[Path], markdown: str = "") -> None:
    """An analysis's table, then the files it wrote."""
    if markdown:
        print(markdown)
    for path in paths:
        print(f"wrote {path}")


@dataclasses.dataclass
class GradientsAnalysis:
    """Paper Fig 3: along a SHAC run with state observations, cosine similarity and norms of the
    full gradient (APG) vs the decoupled one (DPG) at the same parameters. Writes
    OUT/gradients_TASK/apg_vs_dpg.{csv,png}."""

    task: str = "cartpole_swingup"
    """The paper uses hopper (use --iterations 200: our SHAC on Hopper diverges after ~220)."""
    iterations: int = 300
    """SHAC iterations to train (CPU preset)."""
    every: int = 10
    """Compare the two gradients every this many iterations."""
    seed: int = 0
    out: Path = Path("analysis")
    num_envs: int | None = None
    horizon: int | None = None

    def run(self) -> None:
        rows = compare_gradients(
            self.task, self.iterations, self.every, self.seed, num_envs=self.num_envs, horizon=self.horizon
        )
        title = f"SHAC on {self.task} (state observations, seed {self.seed}): APG vs DPG"
        print_report(write_gradient_report(rows, self.out / f"gradients_{self.task}", title))


@dataclasses.dataclass
class GradnormAnalysis(SizeOverrides):
    """Paper Fig 9: actor gradient norm over training, D.Va vs visual SHAC, per task (CPU preset
    unless overridden). Writes OUT/gradnorm/gradnorm.{csv,png,md} and the runs under it, which a
    second call resumes, extends or reuses."""

    tasks: list[str] = dataclasses.field(default_factory=lambda: ["cartpole_swingup", "hopper", "ant"])
    iterations: int = 100
    algo: str = "dva"
    """The D.Va variant compared with visual SHAC: dva (the paper's) | dva-privileged."""

    def run(self) -> None:
        if self.algo not in DVA_VARIANTS:
            raise DvaUsageError(f"--algo {self.algo} is not allowed; use one of: {', '.join(DVA_VARIANTS)}")
        out = self.out / "gradnorm"
        algos = (self.algo, "shac-pixels")
        rows, summary = gradient_norms(self.tasks, self.iterations, out, self.seed, algos=algos, **self.overrides())
        print_report(*write_gradnorm_report(rows, summary, out, f"actor gradient norm, seed {self.seed}"))


@dataclasses.dataclass
class CostAnalysis:
    """Paper Fig 10 and Table 1: backward time and peak memory of one actor gradient, D.Va vs
    visual SHAC, same envs/horizon/images on every task, printed as ratios. Writes
    OUT/cost/cost.{csv,png,md} and cost_ratios.csv."""

    tasks: list[str] = dataclasses.field(default_factory=task_names)
    num_envs: int = 32
    horizon: int = 32
    image_size: int = 84
    chunk: int = 1
    """D.Va's actor backward in chunks of this many steps (``--shac.actor-backward-chunk``; 1, the
    default, has the least memory)."""
    kept: bool = False
    """Also measure D.Va reusing the backward passes its rollout kept (chunk 0: no recomputed
    forward, every step's activations in memory)."""
    timing: bool = True
    """Time the forward and backward passes; --no-timing: memory only, from compiling."""
    seed: int = 0
    out: Path = Path("analysis")

    def run(self) -> None:
        check_image_size(self.image_size, self.image_size)  # fail before any compile
        rows = measure_costs(
            self.tasks, self.num_envs, self.horizon, self.image_size, self.seed, self.chunk, self.kept, self.timing
        )
        title = (
            f"one actor gradient, {self.num_envs} envs × {self.horizon} steps, {self.image_size}² pixels; "
            f"{machine_description()}"
        )
        print_report(*write_cost_report(rows, self.out / "cost", title))


@dataclasses.dataclass
class BreakdownAnalysis(SizeOverrides):
    """Paper Fig 5: D.Va's time per 1M env steps split into simulation (forward, backward),
    rendering, actor forward/backward and critic fitting. Writes OUT/breakdown_TASK/breakdown.{csv,png,md}."""

    task: str = "ant"
    preset: str = "cpu"
    """paper (the paper's hyperparameters) | cpu"""
    algo: str = "dva"

    def run(self) -> None:
        config, times = measure_iteration(self.task, self.algo, self.preset, self.seed, **self.overrides())
        title = (
            f"{self.algo} on {self.task}: {config.num_envs} envs × {config.horizon} steps"
            + (f", {config.image_size}² pixels" if config.observation == "pixels" else "")
            + f"; {machine_description()}"
        )
        print_report(*write_breakdown_report(config, times, self.out / f"breakdown_{self.task}", title))


ANALYSES = {
    "gradients": GradientsAnalysis,
    "gradnorm": GradnormAnalysis,
    "cost": CostAnalysis,
    "breakdown": BreakdownAnalysis,
}

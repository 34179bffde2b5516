"""The ``dva`` command line: ``dva tasks``, ``render``, ``train``, ``eval``, ``plot``, ``report``, ``compare``,
``analyze``."""

from __future__ import annotations

import dataclasses
import sys
import time
import typing
from pathlib import Path
from typing import Annotated, Any, Optional, Union

import jax
import numpy as np
import tyro

from dva.algorithms import ALGORITHMS, AlgoName
from dva.analysis import report
from dva.analysis.commands import ANALYSES
from dva.analysis.compare import EVAL_MINUTES, Backend, FigureName, figure_settings, grid_settings, run_settings
from dva.analysis.plots import plot_runs, write_summary
from dva.configs import PresetName
from dva.envs.factory import EVALUATION_EPISODES, check_env_name, simulated_task
from dva.envs.rendering import PixelRenderer
from dva.envs.visualize import (
    image_grid,
    policy_strip,
    policy_video,
    random_rollout,
    render_trajectory,
    save_png,
    write_video,
)
from dva.errors import DvaUsageError
from dva.runner.compiled import evaluate_run
from dva.runner.evaluation import random_policy_returns
from dva.runner.runtime import configure
from dva.runner.tracking import WandbTracker
from dva.runner.training import TrainingDiverged, check_budget, train
from dva.tasks import TARGET_RETURNS, make_task, task_names
from dva.tasks.physics import check_physics

DEFAULT_TASK = "cartpole_swingup"  # what a command works on when no task is given


@dataclasses.dataclass
class TasksCommand:
    """List the tasks with observation/action sizes, episode lengths and the target return that
    `dva compare` times each run to."""

    def run(self) -> None:
        print(
            f"{'task':<18}{'state obs':>10}{'actions':>9}{'episode':>9}{'target':>8}{'physics':>9}{'substeps':>10}  "
            f"{'contact ke / kd / kf / mu':<28}pixel camera"
        )
        for name in task_names():
            task = make_task(name)
            c = task.penalty_contact
            contact = f"{c.ke:g} / {c.kd:g} / {c.kf:g} / {c.mu:g}" if len(task.contact_points.body) else "none"
            target = f"{TARGET_RETURNS[name]:g}" if name in TARGET_RETURNS else "–"
            print(
                f"{name:<18}{task.obs_dim:>10}{task.action_dim:>9}{task.episode_length:>9}{target:>8}{task.physics:>9}"
                f"{task.substeps:>10}  {contact:<28}{task.camera}"
            )


@dataclasses.dataclass
class RenderCommand:
    """Write a PNG grid of the pixel observations and an mp4 of a random-action rollout."""

    task: str = DEFAULT_TASK
    num_envs: int = 16
    out: Path = Path("renders")
    image_size: int = 84
    """Side of the pixel observations (the PNG grid)."""
    video_size: int = 256
    """Side of each env's view in the video (larger than the observations)."""
    video_envs: int = 4
    steps: int = 120
    """Random-action steps in the video (60 per second of simulated time)."""
    seed: int = 0

    def run(self) -> None:
        task = make_task(self.task)
        observations = PixelRenderer(task, self.num_envs, self.image_size)
        _, qpos = random_rollout(task, jax.random.PRNGKey(self.seed), self.num_envs, self.steps)
        grid_path = self.out / f"{self.task}_observations.png"
        save_png(grid_path, image_grid(np.asarray(jax.jit(observations.__call__)(qpos[self.steps // 2]))))
        video_envs = min(self.video_envs, self.num_envs)
        big = PixelRenderer(task, video_envs, self.video_size, samples_per_pixel=2)
        frames = render_trajectory(big, qpos[:, :video_envs], columns=int(np.ceil(np.sqrt(video_envs))))
        video_path = self.out / f"{self.task}_random.mp4"
        write_video(video_path, frames)
        print(f"wrote {grid_path} and {video_path}")


def optional_fields(config_type: type, exclude: tuple[str, ...] = (), aliases: dict[str, str] | None = None) -> type:
    """A dataclass with every field of ``config_type`` (but ``exclude``) as an optional flag whose
    default, None, keeps the preset's value: ``dva train --shac.horizon 16``; ``aliases`` gives
    some a short flag too (e.g. ``--teacher`` for ``--dagger.teacher``)."""
    hints, aliases = typing.get_type_hints(config_type), aliases or {}

    def flag_type(name: str):
        optional = Optional[hints[name]]  # type: ignore[valid-type]  # a type found at runtime
        return Annotated[optional, tyro.conf.arg(aliases=(aliases[name],))] if name in aliases else optional

    fields = [
        (field.name, flag_type(field.name), dataclasses.field(default=None))
        for field in dataclasses.fields(config_type)
        if field.name not in exclude
    ]
    overrides = dataclasses.make_dataclass(f"{config_type.__name__}Overrides", fields, frozen=True)
    overrides.__doc__ = f"{(config_type.__doc__ or '').strip()} Unset: the preset's value."
    return overrides


# `dva train --GROUP.FIELD` flags, one group per config class of the registry: every field but
# those that define each of the group's algorithms (a field one of them fixes, another may set).
FLAG_GROUPS: dict[str, Any] = {}
for _entry in ALGORITHMS.values():
    FLAG_GROUPS.setdefault(_entry.flag_group, _entry)


def _defined_by_all(group: str) -> tuple[str, ...]:
    entries = [entry for entry in ALGORITHMS.values() if entry.flag_group == group]
    return tuple(name for name in entries[0].defining if all(name in entry.defining for entry in entries))


OVERRIDES = {
    group: optional_fields(entry.config_type, exclude=_defined_by_all(group), aliases=entry.flag_aliases)
    for group, entry in FLAG_GROUPS.items()
}


@dataclasses.dataclass
class TrainOptions:
    """Train a policy: D.Va (pixels, decoupled gradient), SHAC (state, full), DPG on state, visual
    SHAC (pixels from the differentiable renderer, full gradient), or a baseline (DrQ-v2, CURL,
    state-to-visual DAgger, DreamerV3 or TD-MPC2 from pixels or the state)."""

    task: str | None = None
    """The task (`dva tasks` lists them); default cartpole_swingup, on --resume the run's own."""
    algo: AlgoName | None = None
    """The algorithm (the docs' Algorithms page describes each); default dva, on --resume the run's own."""
    preset: PresetName = "cpu"
    """paper (the paper's hyperparameters) | cpu (fewer envs, smaller images)"""
    seed: int = 0
    iterations: int | None = None
    """Stop after this many iterations (default: the config's lr_decay_iterations); on --resume, this many more."""
    minutes: float | None = None
    """Stop after this much wall-clock time, compilation included, evaluations excluded; on --resume, this much more."""
    run_dir: Path | None = None
    """Where logs and checkpoints go (default: runs/TASK_ALGO_sSEED_TIME)."""
    resume: bool = False
    """Continue the run in --run-dir from its last checkpoint."""
    report: bool = True
    """At the end, write the return plots and a video of the policy into the run directory."""
    video_size: int = 256
    """Side of each env's view in that video (next to the actor's camera view)."""
    eval_every: int = 50
    eval_minutes: float | None = None
    """Also evaluate once this many minutes have passed since the last evaluation."""
    eval_episodes: int | None = EVALUATION_EPISODES
    """Episodes each evaluation averages, from fresh resets on envs of its own (every method in
    the docs' results: 16); None: one per training env, on the training envs."""
    checkpoint_every: int | None = None
    """Checkpoint every this many iterations (default: by time, --checkpoint-minutes)."""
    checkpoint_minutes: float = 2.0
    physics: str | None = None
    """Contact model: penalty | mujoco (default: the task's; see `dva tasks`)."""
    devices: int | None = None
    """Split the environments over this many devices (default: all JAX sees, for dva, shac,
    dpg-state and shac-pixels; the others run on one)."""
    track: bool = False
    """Also log to Weights & Biases: config, curves and the policy video (needs the wandb extra;
    WANDB_MODE=offline keeps it on disk)."""
    wandb_project: str | None = None
    """The W&B project (default: $WANDB_PROJECT, else dva)."""

    def resolved_task(self) -> str | None:
        """--task, else cartpole_swingup for a new run; None on --resume (the run's own)."""
        return self.task or (None if self.resume else DEFAULT_TASK)

    def resolved_algo(self) -> str | None:
        """--algo, else dva for a new run; None on --resume (the run's own, from its run.json)."""
        return self.algo or (None if self.resume else "dva")

    def config_overrides(self) -> dict:
        """The flags of this algorithm's group; a clear error for another group's."""
        overrides = {}
        algo = self.resolved_algo()
        for group in FLAG_GROUPS:
            values = {k: v for k, v in dataclasses.asdict(getattr(self, group)).items() if v is not None}
            if algo is not None and group == ALGORITHMS[algo].flag_group:
                overrides = values
            elif values and algo is None:
                raise DvaUsageError(f"--{group}.* flags ({', '.join(values)}): --resume keeps the run's own config")
            elif values:
                raise DvaUsageError(f"--{group}.* flags ({', '.join(values)}) do not apply to --algo {algo}")
        return overrides

    def run(self) -> None:
        if self.run_dir is None:
            if self.resume:
                raise DvaUsageError("--resume needs --run-dir: the run to continue")
            task = (self.task or DEFAULT_TASK).replace(":", "_")
            name = f"{task}_{self.resolved_algo()}_s{self.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
            self.run_dir = Path("runs") / name
        tracker = None
        if self.track:
            tracker = WandbTracker(self.wandb_project)
        run_dir = train(
            self.resolved_task(),
            self.algo,
            preset=self.preset,
            seed=self.seed,
            iterations=self.iterations,
            minutes=self.minutes,
            run_dir=self.run_dir,
            resume=self.resume,
            eval_every=self.eval_every,
            eval_minutes=self.eval_minutes,
            eval_episodes=self.eval_episodes,
            checkpoint_every=self.checkpoint_every,
            checkpoint_minutes=self.checkpoint_minutes,
            physics=self.physics,
            devices=self.devices,
            tracker=tracker,
            **self.config_overrides(),
        )
        print(f"run written to {run_dir}")
        if self.report:
            PlotCommand([run_dir], out=run_dir).run()
            EvalCommand(
                run_dir, self.eval_episodes, video=run_dir / "policy.mp4", video_size=self.video_size
            ).run()  # as many episodes as training's evaluations: the same compiled agent
            if tracker is not None:
                tracker.log_video(run_dir / "policy.mp4")
        if tracker is not None:
            tracker.finish()


def _group_help(group: str) -> str:
    algos = ", ".join(name for name, entry in ALGORITHMS.items() if entry.flag_group == group)
    return f"Hyperparameters of {algos} (unset: the preset's)."


TrainCommand = dataclasses.make_dataclass(
    "TrainCommand",
    [
        (
            group,
            Annotated[overrides, tyro.conf.arg(help=_group_help(group))],
            dataclasses.field(default_factory=overrides),
        )
        for group, overrides in OVERRIDES.items()
    ],
    bases=(TrainOptions,),
)
TrainCommand.__doc__ = TrainOptions.__doc__


@dataclasses.dataclass
class EvalCommand:
    """Replay a run's latest policy (deterministic, or with --sampled as in training), print the
    returns and optionally write a video (the actor's camera view next to a larger view) and a strip
    of frames."""

    run_dir: tyro.conf.Positional[Path]
    episodes: int | None = EVALUATION_EPISODES
    """Episodes to run (one per env, in parallel; None: as many as the run trains on); training's
    evaluations run --eval-episodes (16)."""
    video: Path | None = None
    """Where to write the mp4 (none: returns only)."""
    video_envs: int = 4
    video_size: int = 256
    strip: Path | None = None
    """Where to write a PNG strip of the best episode's view (none: no strip)."""
    strip_frames: int = 8
    """Frames in the strip, evenly spaced over the episode."""
    sampled: bool = False
    """Act as in training, sampling each action from the policy (D.Va and SHAC: tanh(μ + σε)), the
    rule behind every training-episode return and the D.Va authors' curves and videos; default: the
    deterministic action that training's evaluations use."""
    seed: int = 0

    def run(self) -> None:
        if self.strip is not None and self.strip_frames < 1:
            raise DvaUsageError(f"--strip-frames {self.strip_frames} is not allowed; use a number ≥ 1")
        if self.episodes is not None and self.episodes < 1:
            raise DvaUsageError(f"--episodes {self.episodes} is not allowed; use a number ≥ 1")
        spec, returns, qpos, camera = evaluate_run(self.run_dir, self.seed, self.episodes, self.sampled)
        task = simulated_task(spec.task, spec.physics)
        if task is None:  # dm_control's physics: no random reference or video from here
            print(f"{spec.algo} on {spec.task}: return {np.mean(returns):.1f} ± {np.std(returns):.1f}")
            return
        random = random_policy_returns(task, jax.random.PRNGKey(self.seed), len(returns))
        rule = " (sampled actions)" if self.sampled else ""
        print(
            f"{spec.algo} on {spec.task}: return {np.mean(returns):.1f} ± {np.std(returns):.1f} "
            f"over {len(returns)} episodes{rule} (min {np.min(returns):.1f}, max {np.max(returns):.1f}); "
            f"random actions: {np.mean(random):.1f} ± {np.std(random):.1f}"
        )
        if self.video is not None:
            policy_video(
                self.video,
                task,
                qpos,
                camera,
                self.video_envs,
                self.video_size,
                action_repeat=getattr(spec.config, "action_repeat", 1),
            )
            print(f"wrote {self.video}")
        if self.strip is not None:
            best = int(np.argmax(returns))
            policy_strip(self.strip, task, qpos, best, self.strip_frames, self.video_size)
            print(f"wrote {self.strip} (env {best}, return {returns[best]:.1f})")


@dataclasses.dataclass
class PlotCommand:
    """Plot return vs wall-clock and vs env steps (runs of one task and algo averaged: mean ± std) and
    write a table of each setting's final, late (median of each run's last 10 evaluations) and best
    return and, with ``--threshold``, time to reach it."""

    run_dirs: tyro.conf.Positional[list[Path]]
    out: Path = Path("plots")
    metric: str = "eval_return"
    """eval_return (deterministic, full episodes) | train_return (episodes finished in training)"""
    threshold: float | None = None
    """Also report, per setting, when its seeds first reached this return (e.g. 2× random)."""

    def run(self) -> None:
        for path in plot_runs(self.run_dirs, self.out, self.metric):
            print(f"wrote {path}")
        path, markdown = write_summary(self.run_dirs, self.out, self.metric, self.threshold)
        print(markdown + f"wrote {path} and summary.md")


@dataclasses.dataclass
class ReportCommand:
    """Regenerate the tables of a report's documents from the data in its folder of sections (each
    section's section.toml says which; a summary.toml there gives summary rows): by default this
    repository's docs/results.md, README.md and docs/index.md from docs/results/."""

    check: bool = False
    """Change nothing: print how the documents differ from their regenerated selves; exit 1 if they do."""
    plots: bool = False
    """Also redraw each section's learning curves from its CSV files."""
    stamp: str | None = None
    """A section just measured: record the hash of the code and configs it measures, and --commit."""
    commit: str | None = None
    """With --stamp: the commit of the code that made the data."""
    setting: str | None = None
    """With --stamp: only this setting was measured (its section.toml table [settings."NAME"])."""
    root: Path = Path(".")
    """The folder the sections, documents and sections' sources are relative to."""
    sections: Path = report.RESULTS
    """The folder of sections, one subfolder each with its section.toml."""
    documents: list[str] = dataclasses.field(default_factory=lambda: list(report.DOCUMENTS))
    """The markdown documents whose <!-- generated: NAME --> blocks are filled."""

    def run(self) -> None:
        layout = report.Layout(self.root, self.sections, tuple(self.documents))
        if not layout.folder.is_dir():
            raise DvaUsageError(f"--sections {self.sections} is not a folder under {self.root.resolve()}")
        missing = [document for document in layout.documents if not (layout.root / document).is_file()]
        if missing:
            raise DvaUsageError(f"--documents {' '.join(missing)} do not exist under {self.root.resolve()}")
        if self.stamp is not None:
            if self.commit is None:
                raise DvaUsageError("--stamp needs --commit: the commit of the code that made the data")
            report.stamp(layout, self.stamp, self.commit, self.setting)
        if self.check:
            diff = report.differences(layout)
            print(diff or "the documents agree with their data")
            raise SystemExit(1 if diff else 0)
        for path in report.write(layout, self.plots):
            print(f"wrote {path}")


@dataclasses.dataclass(kw_only=True)
class ManyRuns:
    """What compare and sweep share: seeds, budget, where the runs go and what runs them."""

    seeds: list[int] = dataclasses.field(default_factory=lambda: [0, 1])
    minutes: float = 30.0
    """Wall-clock budget of every run (compilation included)."""
    preset: PresetName = "cpu"
    threshold: float | None = None
    """Report when each setting first reached this eval return (default: its task's target
    return, as `dva tasks` lists them)."""
    eval_minutes: float = EVAL_MINUTES
    """Evaluate every run after this many minutes of its own clock (the median of the last 10 then
    spans 10 of them); more for a method whose evaluation takes minutes (TD-MPC2 plans every step)."""
    out: Path = Path("comparisons")
    workers: int = 1
    """local backend: runs at once, each in its own process pinned to an equal share of the CPUs
    (e.g. 2 on a 2-core machine: one core per run). CPU only: on a GPU they would share the one
    device."""
    backend: Backend = "local"
    """local (this machine's processes) | ray (Ray tasks on the cluster at $RAY_ADDRESS, or on one
    Ray starts here; needs the ray extra, and an --out every node sees)."""
    cpus_per_run: float = 1.0
    """ray backend: the CPUs Ray reserves for each run."""
    gpus_per_run: float = 0.0
    """ray backend: the GPUs Ray reserves for each run (fractions share one)."""

    def run_options(self) -> dict:
        """The options :func:`~dva.analysis.compare.run_settings` takes: all of these but ``out``."""
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(ManyRuns) if field.name != "out"}


@dataclasses.dataclass(kw_only=True)
class CompareCommand(ManyRuns):
    """One of the paper's comparisons: every setting × task × seed for the same wall-clock budget,
    then return vs wall-clock and vs env steps (PNG) and final return / time to ``--threshold``
    (CSV + markdown) in OUT. Finished runs are skipped and interrupted ones resumed, so re-running
    after a crash, or with more seeds or minutes, only trains what is missing."""

    figure: tyro.conf.Positional[FigureName]
    """fig4: D.Va vs DrQ-v2, CURL, DreamerV3 and TD-MPC2; fig6: D.Va vs state-to-visual DAgger
    (teacher's time included); fig7: D.Va vs visual SHAC; fig13: SHAC vs DPG on the state;
    ablation-value: D.Va without its critic; ablation-frames: D.Va with 1–6 stacked frames."""
    tasks: list[str] = dataclasses.field(default_factory=lambda: [DEFAULT_TASK])
    frames: list[int] | None = None
    """ablation-frames only: the stack sizes to compare (default 1 2 3 4 5 6)."""
    algos: list[str] | None = None
    """Run only these of the figure's algorithms (e.g. dva drqv2; default: all of them)."""

    def run(self) -> None:
        settings = figure_settings(self.figure, self.tasks, self.frames, self.algos)
        paths, markdown = run_settings(settings, self.out / self.figure, **self.run_options())
        print(markdown + "".join(f"wrote {path}\n" for path in paths), end="")


@dataclasses.dataclass(kw_only=True)
class SweepCommand(ManyRuns):
    """A grid of one algorithm's hyperparameters: every combination of the --grid values × task ×
    seed for the same wall-clock budget, by the rules of compare (finished runs skipped,
    interrupted ones resumed), with its curves and table in OUT."""

    algo: AlgoName = "dva"
    tasks: list[str] = dataclasses.field(default_factory=lambda: [DEFAULT_TASK])
    grid: list[str] = dataclasses.field(default_factory=list)
    """FIELD=V1,V2 per config field of the algorithm (e.g. actor_lr=1e-3,2e-3 horizon=16,32);
    values are read as JSON where they parse."""
    out: Path = Path("sweeps")

    def run(self) -> None:
        settings = grid_settings(self.algo, self.tasks, self.grid)
        paths, markdown = run_settings(settings, self.out, **self.run_options())
        print(markdown + "".join(f"wrote {path}\n" for path in paths), end="")


# One subcommand per analysis, built from the registry (a type checker cannot evaluate it).
if typing.TYPE_CHECKING:
    AnalyzeCommand = Any
else:
    AnalyzeCommand = Union[tuple(Annotated[cls, tyro.conf.subcommand(name)] for name, cls in ANALYSES.items())]
# A Union has no docstring of its own: without this, ``dva --help`` would print typing.Union's.
ANALYZE_HELP = "The analyses behind the method (gradients, gradnorm, cost, breakdown), each writing a PNG and a table."


COMMANDS = {
    "tasks": TasksCommand,
    "render": RenderCommand,
    "train": TrainCommand,
    "eval": EvalCommand,
    "plot": PlotCommand,
    "report": ReportCommand,
    "compare": CompareCommand,
    "sweep": SweepCommand,
    "analyze": AnalyzeCommand,
}


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``dva`` console script."""
    configure()  # before anything computes: JAX reads XLA_FLAGS once
    # As tyro.extras.subcommand_cli_from_dict, but with the analyze group's description set.
    subcommands: Any = Union[
        tuple(
            Annotated[
                Any,
                tyro.conf.subcommand(
                    name=name, constructor=cls, description=ANALYZE_HELP if name == "analyze" else None
                ),
            ]
            for name, cls in COMMANDS.items()
        )
    ]
    command = tyro.cli(subcommands, args=argv, prog="dva")
    try:
        for task in [getattr(command, "task", None), *getattr(command, "tasks", [])]:
            if task is not None:
                check_env_name(task)  # fail before any heavy set-up
        if getattr(command, "physics", None) is not None:
            check_physics(command.physics)
        check_budget(getattr(command, "iterations", None), getattr(command, "minutes", None))
        command.run()
    except DvaUsageError as error:  # bad input: one line naming the value and the choices
        print(f"dva: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    except TrainingDiverged as error:  # not a bug in dva: say what happened and what to try
        algo = command.resolved_algo() if isinstance(command, TrainOptions) else getattr(command, "algo", None)
        hint = ALGORITHMS[algo].divergence_hint if algo in ALGORITHMS else "lower learning rates"
        print(f"dva: training stopped: {error}. Resume from that checkpoint (--resume) with {hint}.", file=sys.stderr)
        raise SystemExit(3) from None


if __name__ == "__main__":
    main()

"""The one training loop behind ``dva train``, for every :class:`~dva.algorithms.base.Agent`:
time or iteration budget, progress bar, CSV + TensorBoard logs of whatever metrics the agent
returns, periodic deterministic evaluation, atomic Orbax checkpoints, resume and the divergence
guard."""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp
from jax.sharding import Mesh
from tqdm import tqdm

from dva.algorithms import check_algo, make_config
from dva.algorithms.base import Agent, Metrics
from dva.envs.factory import EVALUATION_EPISODES, check_evaluation_episodes, env_physics
from dva.errors import DvaUsageError
from dva.runner.checkpoint import (
    Checkpoints,
    RunSpec,
    check_new_run_dir,
    checkpoint_manager,
    restore,
    resumed_run,
    write_spec,
)
from dva.runner.compiled import abstract_state, build, committed, compiled
from dva.runner.logs import ProgressLog, csv_fields, record_machine, show_progress
from dva.runner.schedule import Every, RunClock
from dva.runner.sharding import device_mesh, place
from dva.runner.tracking import WandbTracker


class TrainingDiverged(RuntimeError):
    """An iteration was unhealthy (e.g. the actor gradient NaN or above its limit); the last good
    checkpoint is kept."""

    def __init__(self, message: str, iteration: int, logged: dict) -> None:
        super().__init__(message)
        self.iteration, self.logged = iteration, logged


def run_mesh(spec: RunSpec, devices: int | None) -> Mesh | None:
    """The devices a run's environments split over (None: one device). ``devices`` None means
    every device JAX sees for an agent that splits, one for the others."""
    if not getattr(check_algo(spec.algo).make_agent, "batch_fields", ()):
        if devices not in (None, 1):
            raise DvaUsageError(f"devices = {devices!r} is not allowed for {spec.algo}: it runs on one device; use 1")
        return None
    mesh = device_mesh(devices, spec.config.num_envs)
    return mesh if mesh.size > 1 else None


def train(
    task: str | None,
    algo: str | None = None,
    *,
    preset: str = "cpu",
    seed: int = 0,
    iterations: int | None = None,
    minutes: float | None = None,
    run_dir: Path = Path("runs/latest"),
    resume: bool = False,
    eval_every: int | None = 50,
    eval_minutes: float | None = None,
    eval_episodes: int | None = EVALUATION_EPISODES,
    checkpoint_every: int | None = None,
    checkpoint_minutes: float = 2.0,
    physics: str | None = None,
    devices: int | None = None,
    tracker: WandbTracker | None = None,
    **config_overrides,
) -> Path:
    """Train ``algo`` on ``task`` and return the run directory (logs, checkpoints, ``run.json``).

    ``algo`` defaults to ``"dva"`` for a new run; on ``resume``, ``task`` and ``algo`` default to
    the run's own (given, they must be the run's). ``config_overrides`` replace fields of the
    preset's config (None: keep). Stops after ``iterations``, or ``minutes`` (the whole call,
    set-up and compilation included, and what the agent builds on — DAgger's teacher —,
    evaluations excluded; so does the logged wall-clock, a
    fair clock for comparing methods whatever their tasks' evaluations cost; on ``resume``,
    minutes more, counted from the first iteration: a resume's set-up and compilation are off the
    clock), or else the agent's ``default_iterations``. Evaluates at iteration 0, every
    ``eval_every`` iterations, after any iteration that ends ``eval_minutes`` or more after the
    last evaluation (the same resolution in wall-clock for fast and slow iterations: what a
    time-to-threshold comparison needs) and at the end (never when both are None); each evaluation
    averages ``eval_episodes`` episodes from fresh resets on envs of its own (None: one per
    training env, on the training envs themselves — no second batch to build). Checkpoints every
    ``checkpoint_every`` iterations if given, else every
    ``checkpoint_minutes`` (an off-policy agent's replay makes a checkpoint hundreds of MB), and at
    the end. ``resume`` continues the run in ``run_dir`` from its last checkpoint. ``devices``:
    how many devices the environments split over (:mod:`dva.runner.sharding`; None: all JAX sees, for
    the algorithms that split). ``tracker``: also log to Weights & Biases (the caller finishes it).
    """
    clock = RunClock()
    run_dir = Path(run_dir)
    check_budget(iterations, minutes)
    check_evaluation_episodes(eval_episodes, "--eval-episodes")  # before the run's folder is written
    if resume:
        spec = resumed_run(run_dir, task, algo)
    elif task is None:
        raise DvaUsageError("a new run needs a task (dva tasks lists them)")
    else:
        algo = algo or "dva"
        check_new_run_dir(run_dir)
        config = make_config(task, algo, preset, **config_overrides)
        began = time.perf_counter()
        # DAgger's teacher, if it has none
        config = train_teacher(algo, config, task, preset, seed, run_dir, physics, eval_episodes)
        clock.exclude(time.perf_counter() - began)  # the teacher's time counts through agent.prior_cost
        physics = env_physics(task, physics)
        spec = write_spec(run_dir, RunSpec(task, algo, preset, seed, config, physics))
    mesh = run_mesh(spec, devices)
    agent = build(spec, mesh, eval_episodes)
    checkpoints = Checkpoints(checkpoint_manager(run_dir), checkpoint_every, checkpoint_minutes)
    if tracker is not None:
        tracker.start(run_dir, spec.to_dict())
    log = ProgressLog(run_dir, csv_fields(agent), tracker)
    state = starting_state(agent, spec, mesh, checkpoints.manager, log, resume)
    record_machine(run_dir, int(state.iteration))
    if resume:  # the curve continues from the checkpoint: set-up and compiling are not training
        compiled(agent).iteration.lower(state).compile()
        clock.exclude(clock.seconds())
    # Where the curve starts: the end of the last run, or the cost of what the agent builds on
    # (DAgger's teacher), so that comparisons count it.
    curve = CurveOrigin.of(agent, log)
    budget = Budget.of(agent, iterations, minutes, curve, first=int(state.iteration))
    evaluations = Evaluations(agent, clock, eval_every, eval_minutes)
    if not log.rows:
        log.append(untrained_row(agent, state, curve, evaluations))
    bar = tqdm(total=budget.iterations, unit="it", dynamic_ncols=True, desc=f"{spec.algo} {spec.task}")
    try:
        # A resumed run restores its envs mid-episode: its last logged return stands until one ends.
        train_return = float(log.rows[-1].get("train_return") or "nan")
        while not budget.spent(state, clock):
            state, metrics, seconds = run_iteration(agent, state)
            raise_if_diverged(agent, metrics, int(state.iteration), checkpoints.manager)
            train_return = latest_train_return(metrics, train_return)
            row = progress_row(agent, state, metrics, seconds, train_return, curve, clock, evaluations)
            log.append(row)
            checkpoints.save_if_due(state)
            show_progress(bar, row, budget.seconds_left(clock))
            if metrics.stop:  # the agent's own stopping rule (DAgger: BC loss low enough)
                break
        evaluations.end_on_one(log, state)
    finally:
        bar.close()
        log.close()
    checkpoints.save_final(state)
    return run_dir


def check_budget(iterations: int | None, minutes: float | None) -> None:
    """A budget must be positive (a run of no iterations or minutes would train nothing)."""
    if iterations is not None and iterations <= 0:
        raise DvaUsageError(f"--iterations {iterations} is not allowed; use a whole number > 0")
    if minutes is not None and not minutes > 0:
        raise DvaUsageError(f"--minutes {minutes} is not allowed; use a number > 0")


def train_teacher(algo: str, config, task: str, preset: str, seed: int, run_dir: Path, physics, eval_episodes):
    """For an algorithm that learns from a teacher run (DAgger) and has none: train one with the
    teacher's algorithm for ``config.teacher_minutes`` into ``run_dir/teacher``; the config then
    names it."""
    teacher_algo = check_algo(algo).teacher_algo
    if teacher_algo is None or config.teacher is not None:
        return config
    teacher_dir = train(
        task,
        teacher_algo,
        preset=preset,
        seed=seed,
        minutes=config.teacher_minutes,
        run_dir=run_dir / "teacher",
        physics=physics,
        eval_episodes=eval_episodes,
    )
    return dataclasses.replace(config, teacher=str(teacher_dir))


def starting_state(agent: Agent, spec: RunSpec, mesh: Mesh | None, manager, log: ProgressLog, resume: bool):
    """The latest checkpoint on resume (rows logged after it are dropped), else a fresh state;
    split over ``mesh``'s devices where there is one."""
    placement = committed if mesh is None else functools.partial(place, mesh=mesh, batch_fields=agent.batch_fields)
    if resume and manager.latest_step() is not None:
        state = restore(manager, abstract_state(agent, spec.seed), placement)
        log.truncate(int(state.iteration))
        return state
    return placement(compiled(agent).init(jax.random.PRNGKey(spec.seed)))


class CurveOrigin(NamedTuple):
    """The wall-clock seconds and env steps the logged curve continues from, and the minutes of
    the budget already spent (a fresh run pays its teacher's; a resumed run's budget is more)."""

    seconds: float
    env_steps: int
    spent_minutes: float

    @classmethod
    def of(cls, agent: Agent, log: ProgressLog) -> CurveOrigin:
        if log.rows:
            return cls(float(log.rows[-1]["wall_time"]), agent.prior_cost[1], 0.0)
        return cls(agent.prior_cost[0], agent.prior_cost[1], agent.prior_cost[0] / 60)


@dataclasses.dataclass
class Budget:
    """When :func:`train` stops: after ``iterations`` more, or ``minutes`` on the clock."""

    iterations: int | None
    minutes: float | None
    first: int
    spent_minutes: float

    @classmethod
    def of(cls, agent: Agent, iterations, minutes, curve: CurveOrigin, first: int) -> Budget:
        if iterations is None and minutes is None:
            iterations = agent.default_iterations
        return cls(iterations, minutes, first, curve.spent_minutes)

    def elapsed_minutes(self, clock: RunClock) -> float:
        return self.spent_minutes + clock.seconds() / 60

    def seconds_left(self, clock: RunClock) -> float | None:
        """What is left of a time budget (None for an iteration budget: the progress bar's ETA)."""
        if self.iterations is not None or self.minutes is None:
            return None
        return max(0.0, 60 * (self.minutes - self.elapsed_minutes(clock)))

    def spent(self, state, clock: RunClock) -> bool:
        done = int(state.iteration) - self.first
        return (self.iterations is not None and done >= self.iterations) or (
            self.minutes is not None and self.elapsed_minutes(clock) >= self.minutes
        )


class Evaluations:
    """When to evaluate (every ``every`` iterations or ``minutes`` since the last), and the
    evaluation itself (kept off the clock)."""

    def __init__(self, agent: Agent, clock: RunClock, every: int | None, minutes: float | None) -> None:
        self.agent, self.clock, self.schedule = agent, clock, Every(every, minutes)
        self.on = self.schedule.on

    def due(self, iteration: int) -> bool:
        return self.schedule.due(iteration)

    def __call__(self, state) -> float:
        """Mean deterministic return, one full episode per env, with a key per iteration."""
        began = time.perf_counter()
        key = jax.random.PRNGKey(10_000 + int(state.iteration))
        value = float(np.mean(compiled(self.agent).evaluate(self.agent.policy(state), key)))
        self.schedule.done()
        self.clock.exclude(time.perf_counter() - began)
        return value

    def end_on_one(self, log: ProgressLog, state) -> None:
        """Evaluate the final state if its row has no evaluation yet."""
        last = log.rows[-1]
        if self.on and last["eval_return"] == "" and int(last["iteration"]) == int(state.iteration):
            log.set_last("eval_return", self(state))


def untrained_row(agent: Agent, state, curve: CurveOrigin, evaluations: Evaluations) -> dict:
    """The first row: the untrained policy's return, where the curve starts (no evaluation: nan)."""
    return {
        "iteration": 0,
        "env_steps": curve.env_steps,
        "wall_time": curve.seconds,
        "train_return": float("nan"),
        "eval_return": evaluations(state) if evaluations.on else float("nan"),
    }


def run_iteration(agent: Agent, state):
    """One jitted iteration: the new state, its metrics on the host (one small transfer) and its
    seconds."""
    began = time.perf_counter()
    state, metrics = compiled(agent).iteration(state)
    metrics = jax.device_get(metrics)
    return state, metrics, time.perf_counter() - began


def raise_if_diverged(agent: Agent, metrics: Metrics, iteration: int, manager: ocp.CheckpointManager) -> None:
    if not metrics.healthy:
        raise TrainingDiverged(
            f"{agent.abort_reason(metrics.logged)} at iteration {iteration}; the last good "
            f"checkpoint is in {manager.directory}",
            iteration,
            metrics.logged,
        )


def latest_train_return(metrics: Metrics, previous: float) -> float:
    """The mean return of the episodes that ended in this iteration, else ``previous``."""
    if metrics.finished_episodes > 0:
        return float(metrics.finished_return_sum / metrics.finished_episodes)
    return previous


def progress_row(agent, state, metrics, seconds, train_return, curve, clock, evaluations) -> dict:
    """The iteration's row of ``progress.csv`` (evaluated when due)."""
    n = int(state.iteration)
    return {
        "iteration": n,
        "env_steps": curve.env_steps + n * agent.env_steps_per_iteration,
        "wall_time": round(curve.seconds + clock.seconds(), 3),
        "train_return": train_return,
        "eval_return": evaluations(state) if evaluations.due(n) else "",
        **{name: float(metrics.logged[name]) for name in agent.metric_names},
        "iteration_time": round(seconds, 4),
    }

"""The one training loop behind ``dva train``, for every :class:`~dva.algorithms.base.Agent`:
time or iteration budget, progress bar, CSV + TensorBoard logs of whatever metrics the agent
returns, periodic deterministic evaluation, atomic Orbax checkpoints, resume and the divergence
guard."""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from jax.sharding import Mesh
from tqdm import tqdm

from dva.algorithms import build_agent, check_algo, config_from_dict, make_config, saved_algo
from dva.algorithms.base import Agent, RecurrentAgent, TeacherRun
from dva.envs.dmc import make_dmc_task
from dva.envs.registry import is_dmc
from dva.errors import DvaUsageError
from dva.runner.evaluation import evaluate_policy
from dva.runner.sharding import device_mesh, place
from dva.runner.tracking import WandbTracker
from dva.tasks import make_task


class TrainingDiverged(RuntimeError):
    """An iteration was unhealthy (e.g. the actor gradient NaN or above its limit); the last good
    checkpoint is kept."""

    def __init__(self, message: str, iteration: int, metrics: dict) -> None:
        super().__init__(message)
        self.iteration, self.metrics = iteration, metrics


@dataclasses.dataclass
class RunSpec:
    """What ``dva train`` was asked for (saved as ``run.json`` so ``--resume`` can rebuild it)."""

    task: str
    algo: str
    preset: str
    seed: int
    config: Any  # the algorithm's typed config (a dict only in run.json)
    physics: str | None = None  # the task's contact model (None: the task's default)

    @classmethod
    def read(cls, path: Path) -> RunSpec:
        """The spec saved in ``path`` (``run.json``), its config typed again (under the registry
        entry it belongs to now: :func:`~dva.algorithms.saved_algo`)."""
        values = json.loads(path.read_text())
        config = config_from_dict(values["algo"], values["config"])
        return cls(**dict(values, algo=saved_algo(values["algo"], config), config=config))

    def to_dict(self) -> dict:
        """As ``run.json`` holds it."""
        return dict(self.__dict__, config=dataclasses.asdict(self.config))


def read_progress(run_dir) -> list[dict]:
    """The rows of a run's ``progress.csv``."""
    with (Path(run_dir) / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def build(spec: RunSpec, mesh: Mesh | None = None) -> Agent:
    """The agent of a run (its renderer, which must stay alive, lives in ``agent.env``); one per
    task, algorithm, config, physics and device mesh in a process (see :func:`_agent`)."""
    return _agent(spec.task, spec.algo, spec.config, spec.physics, mesh)


@functools.lru_cache(maxsize=4)
def _agent(task: str, algo: str, config, physics: str | None, mesh: Mesh | None) -> Agent:
    """Agents are stateless, so the runs of one process that share a configuration — a resume, the
    next seed of ``dva compare``, ``dva eval`` after ``dva train`` — share one agent, its renderer and,
    through :func:`compiled`, its traced and compiled functions (tracing the reverse pass through
    MJX alone takes tens of seconds on a CPU). The seed is not part of the config."""
    teacher = load_teacher(config.teacher) if check_algo(algo).teacher_algo else None
    return build_agent(task, algo, config, physics, mesh, teacher)


def load_teacher(run_dir: str | None) -> TeacherRun:
    """The finished run an agent learns from (see :class:`~dva.algorithms.base.TeacherRun`)."""
    if run_dir is None:
        raise DvaUsageError("teacher = None: this algorithm needs a teacher run directory (--teacher)")
    spec, agent, state = load_run(Path(run_dir))
    last = read_progress(Path(run_dir))[-1]
    return TeacherRun(spec.algo, agent, agent.policy(state), (float(last["wall_time"]), int(last["env_steps"])))


def run_mesh(spec: RunSpec, devices: int | None) -> Mesh | None:
    """The devices a run's environments split over (None: one device). ``devices`` None means
    every device JAX sees for an agent that splits, one for the others."""
    if not getattr(check_algo(spec.algo).make_agent, "batch_fields", ()):
        if devices not in (None, 1):
            raise DvaUsageError(f"devices = {devices!r} is not allowed for {spec.algo}: it runs on one device; use 1")
        return None
    mesh = device_mesh(devices, spec.config.num_envs)
    return mesh if mesh.size > 1 else None


class Compiled(NamedTuple):
    """An agent's jitted functions: initial state, iteration (its state donated), evaluation, and
    evaluation that also records each step's ``qpos`` and camera frame (for ``dva eval`` and videos)."""

    init: jax.stages.Wrapped
    iteration: jax.stages.Wrapped
    evaluate: jax.stages.Wrapped
    evaluate_recorded: jax.stages.Wrapped


@functools.lru_cache(maxsize=4)
def compiled(agent: Agent) -> Compiled:
    """``agent``'s jitted functions, traced once per agent."""
    return Compiled(
        jax.jit(functools.partial(initial_state, agent)),
        jax.jit(agent.iteration, donate_argnums=0),
        jax.jit(functools.partial(evaluate_agent, agent)),
        jax.jit(functools.partial(evaluate_agent, agent, record=True)),
    )


def initial_state(agent: Agent, key: jax.Array):
    """``agent.init(key)`` with its weak-typed leaves (arrays made from Python scalars) made strong,
    as a checkpoint restores them (see :func:`committed`)."""
    return jax.tree.map(lambda x: jnp.asarray(x, x.dtype) if jax.typeof(x).weak_type else x, agent.init(key))


def committed(state):
    """``state`` committed to the default device. A fresh state (strongly typed: :func:`initial_state`),
    a restored one and the iteration's outputs then have one signature: the iteration compiles
    once per run, and a resumed run loads it from the persistent cache (measured before: a resume
    compiled Cart-pole SHAC's iteration twice more, 65 s and 95 s on one core)."""
    return jax.device_put(state, jax.devices()[0])


def load_run(run_dir: Path) -> tuple[RunSpec, Agent, object]:
    """A finished or running run: its spec, agent and latest checkpointed state."""
    run_dir = Path(run_dir)
    spec_path = run_dir / "run.json"
    if not spec_path.exists():
        raise DvaUsageError(f"{run_dir} is not a run directory (missing run.json)")
    spec = RunSpec.read(spec_path)
    agent = build(spec)
    manager = checkpoint_manager(run_dir)
    if manager.latest_step() is None:
        raise DvaUsageError(f"{run_dir} has no checkpoint yet")
    return spec, agent, restore(manager, agent, spec.seed)


def evaluate_agent(agent: Agent, policy, key: jax.Array, record: bool = False):
    """:func:`~dva.runner.evaluation.evaluate_policy` with the agent's deterministic policy (its memory
    carried from step to step where it is a :class:`~dva.algorithms.base.RecurrentAgent`)."""
    if isinstance(agent, RecurrentAgent):
        return evaluate_policy(
            agent.env,
            lambda observation, memory, key: agent.act_recurrent(policy, observation, memory, key),
            key,
            record,
            agent.initial_memory(agent.env.num_envs),
        )
    return evaluate_policy(
        agent.env, lambda observation, memory, _key: (agent.act(policy, observation), memory), key, record
    )


def evaluate_run(run_dir: Path, seed: int = 0) -> tuple[RunSpec, np.ndarray, np.ndarray, np.ndarray]:
    """Replay a run's latest policy deterministically for one episode per env.

    Returns the spec, the episode returns (N,), and per step the ``qpos`` (T, N, nq) and the
    newest camera frame the actor saw (T, N, H, W, 3; empty for state observations).
    """
    spec, agent, state = load_run(run_dir)
    returns, qpos, camera = jax.device_get(
        compiled(agent).evaluate_recorded(agent.policy(state), jax.random.PRNGKey(seed))
    )
    return spec, returns, qpos, camera


def checkpoint_manager(run_dir: Path) -> ocp.CheckpointManager:
    """Orbax manager writing to ``run_dir/checkpoints`` (atomic: written aside, then renamed)."""
    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp.CheckpointManager(run_dir.resolve() / "checkpoints", options=options)


def _saved_leaves(state) -> dict[str, jax.Array]:
    """The non-empty leaves of ``state`` by path (Orbax cannot store MJX's zero-size arrays)."""
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    return {jax.tree_util.keystr(path): leaf for path, leaf in leaves if leaf.size > 0}


def save(manager: ocp.CheckpointManager, state) -> None:
    """Checkpoint ``state`` under its iteration number."""
    manager.save(int(state.iteration), args=ocp.args.StandardSave(_saved_leaves(state)))


def restore(manager: ocp.CheckpointManager, agent: Agent, seed: int, placement=None):
    """The latest checkpoint, shaped like the agent's initial state (from ``jax.eval_shape``: no
    need to run the initialisation) and committed like it (or placed by ``placement``); a clear
    error when it cannot be read."""
    like = jax.eval_shape(compiled(agent).init, jax.random.PRNGKey(seed))
    step = manager.latest_step()
    try:
        saved = manager.restore(step, args=ocp.args.StandardRestore(_saved_leaves(like)))
    except Exception as error:  # orbax raises many types for damaged files
        raise DvaUsageError(f"checkpoint {manager.directory}/{step} is corrupt or incompatible: {error}") from None
    paths_and_leaves, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = [
        saved.get(jax.tree_util.keystr(path), jnp.zeros(leaf.shape, leaf.dtype))  # zero-size leaves
        for path, leaf in paths_and_leaves
    ]
    return (placement or committed)(jax.tree_util.tree_unflatten(treedef, leaves))


def csv_fields(agent: Agent) -> list[str]:
    """The columns of ``progress.csv``: the loop's, then the agent's own metrics."""
    return ["iteration", "env_steps", "wall_time", "train_return", "eval_return", *agent.metric_names, "iteration_time"]


def train(
    task: str,
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
    checkpoint_every: int | None = None,
    checkpoint_minutes: float = 2.0,
    physics: str | None = None,
    devices: int | None = None,
    tracker: WandbTracker | None = None,
    **config_overrides,
) -> Path:
    """Train ``algo`` on ``task`` and return the run directory (logs, checkpoints, ``run.json``).

    ``algo`` defaults to ``"dva"`` for a new run and to the run's own on ``resume`` (given, it
    must be the run's). ``config_overrides`` replace fields of the preset's config (None: keep). Stops after
    ``iterations``, or ``minutes`` (the whole call, set-up and compilation included, and what the
    agent builds on — DAgger's teacher —, evaluations excluded; so does the logged wall-clock, a
    fair clock for comparing methods whatever their tasks' evaluations cost; on ``resume``,
    minutes more, counted from the first iteration: a resume's set-up and compilation are off the
    clock), or else the agent's ``default_iterations``. Evaluates at iteration 0, every
    ``eval_every`` iterations, after any iteration that ends ``eval_minutes`` or more after the
    last evaluation (the same resolution in wall-clock for fast and slow iterations: what a
    time-to-threshold comparison needs) and at the end (never when both are None). Checkpoints every
    ``checkpoint_every`` iterations if given, else every
    ``checkpoint_minutes`` (an off-policy agent's replay makes a checkpoint hundreds of MB), and at
    the end. ``resume`` continues the run in ``run_dir`` from its last checkpoint. ``devices``:
    how many devices the environments split over (:mod:`dva.runner.sharding`; None: all JAX sees, for
    the algorithms that split). ``tracker``: also log to Weights & Biases (the caller finishes it).
    """
    clock = RunClock()
    run_dir = Path(run_dir)
    check_budget(iterations, minutes)
    if resume:
        spec = resumed_run(run_dir, task, algo)
    else:
        algo = algo or "dva"
        check_new_run_dir(run_dir)
        config = make_config(task, algo, preset, **config_overrides)
        began = time.perf_counter()
        config = train_teacher(algo, config, task, preset, seed, run_dir, physics)  # DAgger's, if it has none
        clock.exclude(time.perf_counter() - began)  # the teacher's time counts through agent.prior_cost
        physics = make_dmc_task(task).physics if is_dmc(task) else make_task(task, physics).physics
        spec = write_spec(run_dir, RunSpec(task, algo, preset, seed, config, physics))
    mesh = run_mesh(spec, devices)
    agent = build(spec, mesh)
    checkpoints = Checkpoints(checkpoint_manager(run_dir), checkpoint_every, checkpoint_minutes)
    if tracker is not None:
        tracker.start(run_dir, spec.to_dict())
    log = ProgressLog(run_dir, csv_fields(agent), tracker)
    state = starting_state(agent, spec, mesh, checkpoints.manager, log, resume)
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
        train_return = float("nan")
        while not budget.spent(state, clock):
            state, metrics, seconds = run_iteration(agent, state)
            raise_if_diverged(agent, metrics, int(state.iteration), checkpoints.manager)
            train_return = latest_train_return(metrics, train_return)
            row = progress_row(agent, state, metrics, seconds, train_return, curve, clock, evaluations)
            log.append(row)
            checkpoints.save_if_due(state)
            show_progress(bar, row, budget, clock)
            if metrics.get("stop", False):  # the agent's own stopping rule (DAgger: BC loss low enough)
                break
        evaluations.end_on_one(log, state)
    finally:
        bar.close()
        log.close()
    checkpoints.save_final(state)
    return run_dir


class RunClock:
    """Seconds of a :func:`train` call on the run's clock: everything but evaluations and what was
    paid for elsewhere (a teacher, counted through the agent's ``prior_cost``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def seconds(self) -> float:
        return time.perf_counter() - self.start

    def exclude(self, seconds: float) -> None:
        """Take ``seconds`` off the clock."""
        self.start += seconds


def check_budget(iterations: int | None, minutes: float | None) -> None:
    """A budget must be positive (a run of no iterations or minutes would train nothing)."""
    if iterations is not None and iterations <= 0:
        raise DvaUsageError(f"--iterations {iterations} is not allowed; use a whole number > 0")
    if minutes is not None and not minutes > 0:
        raise DvaUsageError(f"--minutes {minutes} is not allowed; use a number > 0")


def check_run_dir(run_dir: Path) -> None:
    """The run directory must be a directory this process can create and write."""
    if run_dir.exists() and not run_dir.is_dir():
        raise DvaUsageError(f"--run-dir {run_dir} is a file, not a directory; use a new or existing directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise DvaUsageError(
            f"--run-dir {run_dir} cannot be written ({error.strerror}); use a writable directory"
        ) from None


def resumed_run(run_dir: Path, task: str, algo: str | None) -> RunSpec:
    """The spec of the run in ``run_dir`` (``run.json``), which must be a run on ``task`` (and of
    ``algo`` where given)."""
    spec_path = run_dir / "run.json"
    if not spec_path.exists():
        raise DvaUsageError(f"--resume: no run to resume in {run_dir} (missing run.json)")
    spec = RunSpec.read(spec_path)
    if spec.task != task or algo not in (None, spec.algo):
        raise DvaUsageError(
            f"--resume: {run_dir} holds a {spec.algo} run on {spec.task}, not {algo or spec.algo} on {task}; "
            f"pass --task {spec.task} --algo {spec.algo}"
        )
    return spec


def check_new_run_dir(run_dir: Path) -> None:
    """A new run needs a directory that holds no run and can be written."""
    if (run_dir / "run.json").exists():
        raise DvaUsageError(f"run directory {run_dir} already holds a run; pass --resume or another --run-dir")
    check_run_dir(run_dir)


def write_spec(run_dir: Path, spec: RunSpec) -> RunSpec:
    """Save a new run's spec as ``run.json`` (what ``--resume`` rebuilds it from)."""
    (run_dir / "run.json").write_text(json.dumps(spec.to_dict(), indent=2))
    return spec


def train_teacher(algo: str, config, task: str, preset: str, seed: int, run_dir: Path, physics):
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
    )
    return dataclasses.replace(config, teacher=str(teacher_dir))


def starting_state(agent: Agent, spec: RunSpec, mesh: Mesh | None, manager, log: ProgressLog, resume: bool):
    """The latest checkpoint on resume (rows logged after it are dropped), else a fresh state;
    split over ``mesh``'s devices where there is one."""
    placement = committed if mesh is None else functools.partial(place, mesh=mesh, batch_fields=agent.batch_fields)
    if resume and manager.latest_step() is not None:
        state = restore(manager, agent, spec.seed, placement)
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

    def spent(self, state, clock: RunClock) -> bool:
        done = int(state.iteration) - self.first
        return (self.iterations is not None and done >= self.iterations) or (
            self.minutes is not None and self.elapsed_minutes(clock) >= self.minutes
        )


class Evaluations:
    """When to evaluate, and the evaluation itself (kept off the clock)."""

    def __init__(self, agent: Agent, clock: RunClock, every: int | None, minutes: float | None) -> None:
        self.agent, self.clock, self.every, self.minutes = agent, clock, every, minutes
        self.on = bool(every or minutes)
        self.last = time.perf_counter()

    def due(self, iteration: int) -> bool:
        return bool(self.every and iteration % self.every == 0) or bool(
            self.minutes and time.perf_counter() - self.last >= 60 * self.minutes
        )

    def __call__(self, state) -> float:
        """Mean deterministic return, one full episode per env, with a key per iteration."""
        began = time.perf_counter()
        key = jax.random.PRNGKey(10_000 + int(state.iteration))
        value = float(np.mean(compiled(self.agent).evaluate(self.agent.policy(state), key)))
        self.last = time.perf_counter()
        self.clock.exclude(self.last - began)
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


def raise_if_diverged(agent: Agent, metrics: dict, iteration: int, manager: ocp.CheckpointManager) -> None:
    if not metrics["healthy"]:
        raise TrainingDiverged(
            f"{agent.abort_reason(metrics)} at iteration {iteration}; the last good "
            f"checkpoint is in {manager.directory}",
            iteration,
            metrics,
        )


def latest_train_return(metrics: dict, previous: float) -> float:
    """The mean return of the episodes that ended in this iteration, else ``previous``."""
    if metrics["finished_episodes"] > 0:
        return float(metrics["finished_return_sum"] / metrics["finished_episodes"])
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
        **{name: float(metrics[name]) for name in agent.metric_names},
        "iteration_time": round(seconds, 4),
    }


class Checkpoints:
    """Saves every ``every`` iterations if given, else every ``minutes``, and at the end."""

    def __init__(self, manager: ocp.CheckpointManager, every: int | None, minutes: float) -> None:
        self.manager, self.every, self.minutes = manager, every, minutes
        self.last = time.perf_counter()

    def save_if_due(self, state) -> None:
        if (
            int(state.iteration) % self.every == 0
            if self.every
            else time.perf_counter() - self.last >= 60 * self.minutes
        ):
            save(self.manager, state)
            self.last = time.perf_counter()

    def save_final(self, state) -> None:
        if self.manager.latest_step() != int(state.iteration):
            save(self.manager, state)
        self.manager.wait_until_finished()


def show_progress(bar: tqdm, row: dict, budget: Budget, clock: RunClock) -> None:
    bar.update(1)
    postfix = dict(steps=row["env_steps"], ret=f"{row['train_return']:.1f}", s_it=f"{row['iteration_time']:.2f}")
    if budget.iterations is None and budget.minutes is not None:  # tqdm knows no ETA: show what is left
        left = max(0.0, 60 * (budget.minutes - budget.elapsed_minutes(clock)))
        postfix["left"] = time.strftime("%H:%M:%S", time.gmtime(left))
    bar.set_postfix(postfix)


class ProgressLog:
    """``progress.csv`` (appended row by row, rewritten atomically when edited) and TensorBoard."""

    def __init__(self, run_dir: Path, fields: list[str], tracker: WandbTracker | None = None) -> None:
        from tensorboardX import SummaryWriter

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

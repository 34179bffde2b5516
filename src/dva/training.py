"""The training loop behind ``dva train``: presets, progress bar, CSV + TensorBoard logs,
periodic deterministic evaluation, atomic Orbax checkpoints and resume."""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import time
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
from tqdm import tqdm

from dva.algorithms.shac import SHAC, SHACConfig, TrainState
from dva.rendering import PixelRenderer
from dva.soft_rendering import SoftRenderer
from dva.tasks import check_task_name, make_task

ALGORITHMS = {  # algorithm → (actor observation, gradient)
    "dva": ("pixels", "decoupled"),
    "shac": ("state", "full"),
    "dpg-state": ("state", "decoupled"),
    "shac-pixels": ("pixels", "full"),  # visual SHAC through the differentiable renderer
}
# Visual SHAC's own horizons and env counts (spec §3: 32/32/8/32 steps, 64/64/32/32 envs).
VISUAL_SHAC_PAPER = {"ant": dict(horizon=8, num_envs=32), "humanoid": dict(num_envs=32)}

# Spec §1, Table 7 (+ epochs from the ref. code). Half-Cheetah uses the Hopper/Ant row.
PAPER_PRESETS: dict[str, dict] = {
    "cartpole_swingup": dict(trunk=64, actor_hidden=(64, 64), critic_hidden=(64, 64), critic_lr=2e-4,
                             target_alpha=0.2, iterations=4000),
    "hopper": dict(trunk=128, actor_hidden=(128, 64, 32), critic_hidden=(64, 64), critic_lr=2e-4,
                   target_alpha=0.2, iterations=30000),
    "cheetah": dict(trunk=128, actor_hidden=(128, 64, 32), critic_hidden=(64, 64), critic_lr=2e-4,
                    target_alpha=0.2, iterations=30000),
    "ant": dict(trunk=128, actor_hidden=(128, 64, 32), critic_hidden=(64, 64), critic_lr=2e-3,
                target_alpha=0.2, iterations=30000),
    "quadruped": dict(trunk=128, actor_hidden=(128, 64, 32), critic_hidden=(64, 64), critic_lr=2e-3,
                      target_alpha=0.2, iterations=30000),  # the paper gives none: Ant's row
    "humanoid": dict(trunk=256, actor_hidden=(256, 128), critic_hidden=(128, 128), critic_lr=5e-4,
                     target_alpha=0.995, iterations=60000),
}
# What a 2-core CPU can afford: the same method and networks, fewer envs, smaller images (the
# conv encoder dominates an iteration on CPU, spec §6) and a 16-step horizon: half the cost per
# iteration and twice the updates per env step (Cart-pole from pixels: return 600-900 after
# 100k steps, where h = 32 was still at the collapsed ~110; benchmarks/RESULTS.md).
CPU_OVERRIDES = dict(num_envs=16, image_size=48, horizon=16, iterations=1000)
# The legged robots learn for longer: a 1000-iteration decay left SHAC on Hopper (state) at the
# final learning rate after 4 of its 30 minutes, its evaluations stuck at 1000–1500 after a 3052
# peak; 4000 iterations ≈ 17 minutes of SHAC on state, ≈ 2 hours of D.Va from pixels.
CPU_TASK_OVERRIDES = {task: dict(iterations=4000) for task in ("hopper", "cheetah", "ant", "humanoid", "quadruped")}
PRESETS = ("paper", "cpu")


def make_config(task: str, algo: str, preset: str, **overrides) -> SHACConfig:
    """The configuration of ``algo`` on ``task`` under ``preset`` ('paper' or 'cpu')."""
    check_task_name(task)
    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algo {algo!r}; choose one of: {', '.join(ALGORITHMS)}")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    observation, gradient = ALGORITHMS[algo]
    values = dict(PAPER_PRESETS[task], observation=observation, gradient=gradient)
    if algo == "shac-pixels":
        values.update(VISUAL_SHAC_PAPER.get(task, {}))
    if preset == "cpu":
        values.update(CPU_OVERRIDES, **CPU_TASK_OVERRIDES.get(task, {}))
    values.update({k: v for k, v in overrides.items() if v is not None})
    return SHACConfig(**values)


class TrainingDiverged(RuntimeError):
    """The actor gradient was NaN or above the limit; the last good checkpoint is kept."""

    def __init__(self, message: str, iteration: int, grad_norm: float) -> None:
        super().__init__(message)
        self.iteration, self.grad_norm = iteration, grad_norm


@dataclasses.dataclass
class RunSpec:
    """What ``dva train`` was asked for (saved as ``run.json`` so ``--resume`` can rebuild it)."""

    task: str
    algo: str
    preset: str
    seed: int
    config: dict
    physics: str | None = None  # the task's contact model (None: the task's default)


def build(spec: RunSpec) -> tuple[SHAC, PixelRenderer | SoftRenderer | None]:
    """The trainer (and its renderer, which must stay alive) for a run: pixels come from the
    Warp renderer, or from the differentiable one when the gradient goes through them."""
    task = make_task(spec.task, spec.physics)
    config = SHACConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec.config.items()})
    renderer = None
    if config.observation == "pixels":
        kind = SoftRenderer if config.gradient == "full" else PixelRenderer
        renderer = kind(task, config.num_envs, config.image_size)
    return SHAC(task, config, renderer), renderer


def load_run(run_dir: Path) -> tuple[RunSpec, SHAC, PixelRenderer | SoftRenderer | None, TrainState]:
    """A finished or running run: its spec, trainer, renderer and latest checkpointed state."""
    run_dir = Path(run_dir)
    spec_path = run_dir / "run.json"
    if not spec_path.exists():
        raise ValueError(f"{run_dir} is not a run directory (missing run.json)")
    spec = RunSpec(**json.loads(spec_path.read_text()))
    agent, renderer = build(spec)
    manager = checkpoint_manager(run_dir)
    if manager.latest_step() is None:
        raise ValueError(f"{run_dir} has no checkpoint yet")
    state = restore(manager, jax.jit(agent.init)(jax.random.PRNGKey(spec.seed)))
    return spec, agent, renderer, state


def evaluate_run(run_dir: Path, seed: int = 0) -> tuple[RunSpec, np.ndarray, np.ndarray, np.ndarray]:
    """Replay a run's latest policy deterministically for one episode per env.

    Returns the spec, the episode returns (N,), and per step the ``qpos`` (T, N, nq) and the
    newest camera frame the actor saw (T, N, H, W, 3; empty for state observations).
    """
    spec, agent, _renderer, state = load_run(run_dir)
    evaluate = jax.jit(functools.partial(agent.evaluate, record=True))
    returns, qpos, camera = jax.device_get(evaluate(state.actor_params, state.obs_stats, jax.random.PRNGKey(seed)))
    return spec, returns, qpos, camera


def checkpoint_manager(run_dir: Path) -> ocp.CheckpointManager:
    """Orbax manager writing to ``run_dir/checkpoints`` (atomic: written aside, then renamed)."""
    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp.CheckpointManager(run_dir.resolve() / "checkpoints", options=options)


def _saved_leaves(state: TrainState) -> dict[str, jax.Array]:
    """The non-empty leaves of ``state`` by path (Orbax cannot store MJX's zero-size arrays)."""
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    return {jax.tree_util.keystr(path): leaf for path, leaf in leaves if leaf.size > 0}


def save(manager: ocp.CheckpointManager, state: TrainState) -> None:
    """Checkpoint ``state`` under its iteration number."""
    manager.save(int(state.iteration), args=ocp.args.StandardSave(_saved_leaves(state)))


def restore(manager: ocp.CheckpointManager, like: TrainState) -> TrainState:
    """The latest checkpoint, shaped like ``like``; a clear error when it cannot be read."""
    step = manager.latest_step()
    try:
        saved = manager.restore(step, args=ocp.args.StandardRestore(_saved_leaves(like)))
    except Exception as error:  # orbax raises many types for damaged files
        raise ValueError(f"checkpoint {manager.directory}/{step} is corrupt or incompatible: {error}") from None
    paths_and_leaves, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = [saved.get(jax.tree_util.keystr(path), leaf) for path, leaf in paths_and_leaves]
    return jax.tree_util.tree_unflatten(treedef, leaves)


CSV_FIELDS = ["iteration", "env_steps", "wall_time", "train_return", "eval_return", "actor_loss",
              "actor_grad_norm", "critic_loss", "iteration_time"]


def train(task: str, algo: str = "dva", preset: str = "cpu", seed: int = 0, iterations: int | None = None,
          minutes: float | None = None, run_dir: Path = Path("runs/latest"), resume: bool = False,
          eval_every: int | None = 50, checkpoint_every: int = 25, physics: str | None = None,
          **overrides) -> Path:
    """Train and return the run directory (logs, checkpoints, ``run.json``).

    Evaluates at iteration 0, every ``eval_every`` iterations and at the end (never when None).

    ``minutes`` bounds the whole call, set-up and compilation included; so does the logged
    wall-clock (a fair clock for comparing methods).
    """
    start = time.perf_counter()
    run_dir = Path(run_dir)
    spec_path = run_dir / "run.json"
    if resume:
        if not spec_path.exists():
            raise ValueError(f"--resume: no run to resume in {run_dir} (missing run.json)")
        spec = RunSpec(**json.loads(spec_path.read_text()))
    else:
        if spec_path.exists():
            raise ValueError(f"run directory {run_dir} already holds a run; pass --resume or another --run-dir")
        config = make_config(task, algo, preset, **overrides)
        spec = RunSpec(task, algo, preset, seed, dataclasses.asdict(config), make_task(task, physics).physics)
        run_dir.mkdir(parents=True, exist_ok=True)
        spec_path.write_text(json.dumps(spec.__dict__, indent=2))
    agent, _renderer = build(spec)
    cfg = agent.config
    total = iterations if iterations is not None else (None if minutes is not None else cfg.iterations)

    manager = checkpoint_manager(run_dir)
    state = jax.jit(agent.init)(jax.random.PRNGKey(spec.seed))
    rows = _read_log(run_dir / "progress.csv")
    if resume and manager.latest_step() is not None:
        state = restore(manager, state)
        done_iterations = int(state.iteration)
        rows = [row for row in rows if int(row["iteration"]) <= done_iterations]
        _rewrite_log(run_dir / "progress.csv", rows)  # drop rows logged after the checkpoint
    offset_time = float(rows[-1]["wall_time"]) if rows else 0.0

    step_fn = jax.jit(agent.iteration, donate_argnums=0)
    evaluate = jax.jit(agent.evaluate)

    def eval_return(state: TrainState) -> float:
        """Mean deterministic return, one full episode per env, with a key per iteration."""
        key = jax.random.PRNGKey(10_000 + int(state.iteration))
        return float(np.mean(evaluate(state.actor_params, state.obs_stats, key)))

    writer = _tensorboard(run_dir)
    first = int(state.iteration)
    last_train_return = float("nan")
    if not rows:  # the untrained policy's return: where the curve starts (no evaluation: nan)
        row = {"iteration": 0, "env_steps": 0, "wall_time": 0.0, "train_return": float("nan"),
               "eval_return": eval_return(state) if eval_every else float("nan"),
               "actor_loss": "", "actor_grad_norm": "", "critic_loss": "", "iteration_time": ""}
        rows.append(row)
        _log(run_dir, writer, row)
    bar = tqdm(total=total, initial=0, unit="it", dynamic_ncols=True, desc=f"{spec.algo} {spec.task}")
    try:
        while True:
            elapsed_min = (time.perf_counter() - start) / 60
            done = int(state.iteration) - first
            if (total is not None and done >= total) or (minutes is not None and elapsed_min >= minutes):
                break
            tick = time.perf_counter()
            state, metrics = step_fn(state)
            metrics = jax.device_get(metrics)  # one small transfer per iteration, for the log
            iteration_time = time.perf_counter() - tick
            n = int(state.iteration)
            if not metrics["healthy"]:
                norm = float(metrics["actor_grad_norm"])
                raise TrainingDiverged(
                    f"actor gradient norm {norm:.3g} at iteration {n} is NaN or above {cfg.max_grad_norm:.3g}; "
                    f"the last good checkpoint is in {manager.directory}", n, norm)
            if metrics["finished_episodes"] > 0:
                last_train_return = float(metrics["finished_return_sum"] / metrics["finished_episodes"])
            evaluation = eval_return(state) if eval_every and n % eval_every == 0 else ""
            row = {"iteration": n, "env_steps": n * cfg.num_envs * cfg.horizon,
                   "wall_time": round(offset_time + time.perf_counter() - start, 3),
                   "train_return": last_train_return, "eval_return": evaluation,
                   "actor_loss": float(metrics["actor_loss"]), "actor_grad_norm": float(metrics["actor_grad_norm"]),
                   "critic_loss": float(metrics["critic_loss"]), "iteration_time": round(iteration_time, 4)}
            rows.append(row)
            _log(run_dir, writer, row)
            if n % checkpoint_every == 0:
                save(manager, state)
            bar.update(1)
            postfix = dict(steps=row["env_steps"], ret=f"{last_train_return:.1f}", s_it=f"{iteration_time:.2f}")
            if total is None:  # a time budget: tqdm cannot know the ETA, so show what is left
                postfix["left"] = time.strftime("%H:%M:%S", time.gmtime(max(0.0, minutes * 60 - (time.perf_counter() - start))))
            bar.set_postfix(postfix)
        last = rows[-1]
        if eval_every and last["eval_return"] == "" and int(last["iteration"]) == int(state.iteration):  # end on an evaluation
            last["eval_return"] = eval_return(state)
            _rewrite_log(run_dir / "progress.csv", rows)
            writer.add_scalar("eval_return", last["eval_return"], int(last["env_steps"]))
    finally:
        bar.close()
        writer.close()
    if manager.latest_step() != int(state.iteration):
        save(manager, state)
    manager.wait_until_finished()
    return run_dir


def _read_log(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def _rewrite_log(path: Path, rows: list[dict]) -> None:
    tmp = path.with_suffix(".tmp")
    with tmp.open("w", newline="") as f:
        out = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        out.writeheader()
        out.writerows(rows)
    tmp.replace(path)


def _log(run_dir: Path, writer, row: dict) -> None:
    path = run_dir / "progress.csv"
    new = not path.exists()
    with path.open("a", newline="") as f:
        out = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        if new:
            out.writeheader()
        out.writerow(row)
    for key, value in row.items():
        if key != "iteration" and value != "" and np.isfinite(float(value)):
            writer.add_scalar(key, float(value), row["env_steps"])


def _tensorboard(run_dir: Path):
    from tensorboardX import SummaryWriter

    return SummaryWriter(str(run_dir / "tensorboard"))

"""Agents and their compiled functions, built once per configuration in a process (the compile
cache), and a saved run loaded back: its agent and its latest checkpoint."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from dva.algorithms import build_agent, check_algo, sampling_algorithms
from dva.algorithms.base import Agent, SamplingAgent, TeacherRun
from dva.envs.factory import EVALUATION_EPISODES
from dva.errors import DvaUsageError
from dva.runner.checkpoint import RunSpec, checkpoint_manager, restore
from dva.runner.evaluation import evaluate_agent
from dva.runner.logs import read_progress


def build(spec: RunSpec, mesh: Mesh | None = None, evaluation_episodes: int | None = EVALUATION_EPISODES) -> Agent:
    """The agent of a run (its renderer, which must stay alive, lives in ``agent.env``); one per
    task, algorithm, config, physics, device mesh and evaluation size in a process (see :func:`_agent`)."""
    return _agent(spec.task, spec.algo, spec.config, spec.physics, mesh, evaluation_episodes)


@functools.lru_cache(maxsize=4)
def _agent(
    task: str, algo: str, config, physics: str | None, mesh: Mesh | None, evaluation_episodes: int | None
) -> Agent:
    """Agents are stateless, so the runs of one process that share a configuration — a resume, the
    next seed of ``dva compare``, ``dva eval`` after ``dva train`` — share one agent, its renderer and,
    through :func:`compiled`, its traced and compiled functions (tracing the reverse pass through
    MJX alone takes tens of seconds on a CPU). The seed is not part of the config."""
    teacher = load_teacher(config.teacher) if check_algo(algo).teacher_algo else None
    return build_agent(task, algo, config, physics, mesh, teacher, evaluation_episodes)


def load_teacher(run_dir: str | None) -> TeacherRun:
    """The finished run an agent learns from (see :class:`~dva.algorithms.base.TeacherRun`)."""
    if run_dir is None:
        raise DvaUsageError("teacher = None: this algorithm needs a teacher run directory (--teacher)")
    spec, agent, state = load_run(Path(run_dir))
    last = read_progress(Path(run_dir))[-1]
    return TeacherRun(spec.algo, agent, agent.policy(state), (float(last["wall_time"]), int(last["env_steps"])))


class Compiled(NamedTuple):
    """An agent's jitted functions: initial state, iteration (its state donated), evaluation,
    evaluation that also records each step's ``qpos`` and camera frame (for ``dva eval`` and videos),
    and that recorded evaluation under the training action rule (``dva eval --sampled``; each
    compiles on its first call)."""

    init: jax.stages.Wrapped
    iteration: jax.stages.Wrapped
    evaluate: jax.stages.Wrapped
    evaluate_recorded: jax.stages.Wrapped
    evaluate_sampled_recorded: jax.stages.Wrapped


@functools.lru_cache(maxsize=4)
def compiled(agent: Agent) -> Compiled:
    """``agent``'s jitted functions, traced once per agent."""
    return Compiled(
        jax.jit(functools.partial(initial_state, agent)),
        jax.jit(agent.iteration, donate_argnums=0),
        jax.jit(functools.partial(evaluate_agent, agent)),
        jax.jit(functools.partial(evaluate_agent, agent, record=True)),
        jax.jit(functools.partial(evaluate_agent, agent, record=True, sampled=True)),
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


def abstract_state(agent: Agent, seed: int):
    """The shapes and types of ``agent``'s initial state (``jax.eval_shape``: nothing runs): what a
    checkpoint restores into."""
    return jax.eval_shape(compiled(agent).init, jax.random.PRNGKey(seed))


def load_run(run_dir: Path, evaluation_episodes: int | None = EVALUATION_EPISODES) -> tuple[RunSpec, Agent, object]:
    """A finished or running run: its spec, agent (evaluating ``evaluation_episodes`` episodes)
    and latest checkpointed state."""
    run_dir = Path(run_dir)
    spec_path = run_dir / "run.json"
    if not spec_path.exists():
        raise DvaUsageError(f"{run_dir} is not a run directory (missing run.json)")
    spec = RunSpec.read(spec_path)
    agent = build(spec, evaluation_episodes=evaluation_episodes)
    manager = checkpoint_manager(run_dir)
    if manager.latest_step() is None:
        raise DvaUsageError(f"{run_dir} has no checkpoint yet")
    return spec, agent, restore(manager, abstract_state(agent, spec.seed), committed)


def evaluate_run(
    run_dir: Path, seed: int = 0, episodes: int | None = EVALUATION_EPISODES, sampled: bool = False
) -> tuple[RunSpec, np.ndarray, np.ndarray, np.ndarray]:
    """Replay a run's latest policy deterministically (``sampled``: under its training action
    rule) for ``episodes`` episodes, one per env of an evaluation batch.

    Returns the spec, the episode returns (N,), and per step the ``qpos`` (T, N, nq) and the
    newest camera frame the actor saw (T, N, H, W, 3; empty for state observations).
    """
    spec, agent, state = load_run(run_dir, episodes)
    if sampled and not isinstance(agent, SamplingAgent):
        raise DvaUsageError(
            f"--sampled: {spec.algo} acts without a sampled action rule; the algorithms with one: "
            + ", ".join(sampling_algorithms())
        )
    functions = compiled(agent)
    evaluate = functions.evaluate_sampled_recorded if sampled else functions.evaluate_recorded
    returns, qpos, camera = jax.device_get(evaluate(agent.policy(state), jax.random.PRNGKey(seed)))
    return spec, returns, qpos, camera

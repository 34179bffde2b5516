"""One evaluation for every algorithm and for the random-policy reference: full episodes, one
per env, from fresh resets."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from dva.algorithms.base import Agent, RecurrentAgent, SamplingAgent
from dva.envs.observations import Env, Observation, PixelObservations
from dva.tasks.base import Task

# (observation, memory, key) → (action in [−1, 1], memory): the memory is what a recurrent policy
# carries between steps (DreamerV3's latent state), ``()`` for the others.
Policy = Callable[[Observation, Any, jax.Array], tuple[jax.Array, Any]]


def evaluate_policy(env: Env, policy: Policy, key: jax.Array, record: bool = False, memory: Any = ()):
    """Undiscounted return of one full episode per env under ``policy``, starting from ``memory``: (N,).

    Episodes that end early stop counting (the auto-reset continues them unseen). With
    ``record=True`` also returns, per step, ``qpos`` (T, N, nq) and the newest frame the policy saw
    (T, N, H, W, 3; (T, N, 0) without pixels) — what a video needs.
    """
    env = env.evaluation_env()
    reset_key, policy_key = jax.random.split(key)
    state = env.reset(reset_key)

    def step(carry, step_key):
        state, memory, total, running = carry
        action, memory = policy(env.observe(state), memory, step_key)
        state = env.step(state, action)
        total = total + running * state.reward
        shown = (state.data.qpos, state.frames[..., -3:]) if record else None
        return (state, memory, total, running * (1.0 - state.done)), shown

    ones = jnp.ones(env.num_envs)
    keys = jax.random.split(policy_key, env.episode_steps)
    (_, _, total, _), shown = jax.lax.scan(step, (state, memory, 0.0 * ones, ones), keys)
    return (total, *shown) if record else total


@functools.partial(jax.jit, static_argnums=(0, 2))
def random_policy_returns(task: Task, key: jax.Array, num_envs: int) -> jax.Array:
    """The reference a trained policy is judged against: uniform random actions in [−1, 1], (N,)."""

    def uniform(_observation: Observation, memory: tuple, step_key: jax.Array) -> tuple[jax.Array, tuple]:
        return jax.random.uniform(step_key, (num_envs, task.action_dim), minval=-1.0, maxval=1.0), memory

    return evaluate_policy(PixelObservations(task, num_envs), uniform, key)


def evaluate_agent(agent: Agent, policy, key: jax.Array, record: bool = False, sampled: bool = False):
    """:func:`~dva.runner.evaluation.evaluate_policy` with the agent's deterministic policy (its memory
    carried from step to step where it is a :class:`~dva.algorithms.base.RecurrentAgent`), or with
    ``sampled`` its training action rule (a :class:`~dva.algorithms.base.SamplingAgent`)."""
    if sampled:
        assert isinstance(agent, SamplingAgent), f"{type(agent).__name__} has no sampled action rule"
        return evaluate_policy(
            agent.env, lambda observation, memory, key: (agent.sample(policy, observation, key), memory), key, record
        )
    if isinstance(agent, RecurrentAgent):
        return evaluate_policy(
            agent.env,
            lambda observation, memory, key: agent.act_recurrent(policy, observation, memory, key),
            key,
            record,
            agent.initial_memory(agent.env.evaluation_env().num_envs),
        )
    return evaluate_policy(
        agent.env, lambda observation, memory, _key: (agent.act(policy, observation), memory), key, record
    )

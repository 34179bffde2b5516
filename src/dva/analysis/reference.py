"""Reference returns to judge a trained policy against."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from dva.tasks import Task


@functools.partial(jax.jit, static_argnums=(0, 2))
def random_policy_returns(task: Task, key: jax.Array, num_envs: int) -> jax.Array:
    """Undiscounted return of one full episode per env under uniform random actions in [−1, 1]: (N,)."""
    reset_key, action_key = jax.random.split(key)
    env = task.reset(reset_key, num_envs)

    def step(carry, step_key):
        env, total, running = carry
        action = jax.random.uniform(step_key, (num_envs, task.action_dim), minval=-1.0, maxval=1.0)
        env = task.step(env, action)
        return (env, total + running * env.reward, running * (1.0 - env.done)), None

    ones = jnp.ones(num_envs)
    (_, total, _), _ = jax.lax.scan(step, (env, 0.0 * ones, ones), jax.random.split(action_key, task.episode_length))
    return total

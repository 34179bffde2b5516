"""Test doubles shared by the tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dva.algorithms import ALGORITHMS, make_config
from dva.envs.observations import PixelObservations
from dva.tasks import make_task


class StripeRenderer:
    """A cheap stand-in for the Warp renderer (the env wrapper only needs the Renderer protocol):
    a grey image whose brightness follows the cart position."""

    differentiable = False

    def __init__(self, num_envs: int, size: int = 16) -> None:
        self.num_envs, self.size = num_envs, size

    def __call__(self, qpos: jax.Array) -> jax.Array:
        value = jnp.clip(128.0 + 50.0 * qpos[:, 0], 0, 255).astype(jnp.uint8)
        return jnp.broadcast_to(value[:, None, None, None], (self.num_envs, self.size, self.size, 3))


def small_off_policy_agent(algo: str, iterations: int, **overrides):
    """A tiny ``algo`` (drqv2 or curl) on cartpole_balance with 4 envs and the stripe renderer,
    trained for ``iterations``: returns the agent, its state before and after the last iteration
    and that iteration's metrics (the last update is then checked on what the iteration did,
    without compiling the update on its own)."""
    config = make_config(
        "cartpole_balance",
        algo,
        "cpu",
        num_envs=4,
        image_size=16,
        batch_size=8,
        hidden=(16, 16),
        feature_dim=8,
        replay_size=400,
        **overrides,
    )
    env = PixelObservations(
        make_task("cartpole_balance"), 4, StripeRenderer(4), config.frame_stack, config.action_repeat
    )
    agent = ALGORITHMS[algo].make_agent(env, config)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    iteration = jax.jit(agent.iteration)
    for _ in range(iterations):
        previous = state
        state, metrics = iteration(state)
    return agent, previous, state, jax.device_get(metrics)


def output_layer(params: dict) -> str:
    """The name of a flax MLP's last Dense layer in ``params`` (``Dense_k`` with the largest k)."""
    return max((name for name in params if name.startswith("Dense")), key=lambda name: int(name.split("_")[-1]))

"""Test doubles shared by the tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp


class StripeRenderer:
    """A cheap stand-in for the Warp renderer (the env wrapper only needs the Renderer protocol):
    a grey image whose brightness follows the cart position."""

    differentiable = False

    def __init__(self, num_envs: int, size: int = 16) -> None:
        self.num_envs, self.size = num_envs, size

    def __call__(self, qpos: jax.Array) -> jax.Array:
        value = jnp.clip(128.0 + 50.0 * qpos[:, 0], 0, 255).astype(jnp.uint8)
        return jnp.broadcast_to(value[:, None, None, None], (self.num_envs, self.size, self.size, 3))

"""D.Va / SHAC's networks: ELU + LayerNorm MLPs, the Gaussian actor with a state-independent
log-std, the state critic, and running mean / std statistics of the observations."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from dva.networks.conv import PixelEncoder


class MLP(nn.Module):
    """Hidden layers Dense → LayerNorm → ELU, then a linear output layer."""

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.elu(nn.LayerNorm()(nn.Dense(width)(x)))
        return nn.Dense(self.out)(x)


class Actor(nn.Module):
    """Gaussian policy head: mean from an MLP, state-independent log-std initialised to −1.

    With ``pixels=True`` the input goes through :class:`PixelEncoder` and a Linear → LayerNorm →
    Tanh trunk of width ``trunk`` first. Returns ``(mean, log_std)`` of the pre-tanh action; with
    ``state_dim > 0`` also a linear prediction of the (normalised) simulator state from the trunk's
    features, for the auxiliary state-prediction loss (``predict_state=True``; init with it).
    """

    action_dim: int
    hidden: Sequence[int]
    pixels: bool
    trunk: int = 64
    init_log_std: float = -1.0
    state_dim: int = 0

    @nn.compact
    def __call__(self, observation: jax.Array, predict_state: bool = False):
        x = observation
        if self.pixels:
            x = PixelEncoder()(x)
            x = jnp.tanh(nn.LayerNorm()(nn.Dense(self.trunk)(x)))
        mean = MLP(self.hidden, self.action_dim)(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,))
        log_std = jnp.broadcast_to(log_std, mean.shape)
        if predict_state:
            return mean, log_std, nn.Dense(self.state_dim, name="state_head")(x)
        return mean, log_std


class Critic(nn.Module):
    """State-value MLP (ELU + LayerNorm) on the normalised low-dimensional state."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, state: jax.Array) -> jax.Array:
        return MLP(self.hidden, 1)(state)[..., 0]


class RunningStats(struct.PyTreeNode):
    """Running mean and variance (parallel Welford), for normalising critic/actor states."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def create(cls, dim: int) -> RunningStats:
        return cls(mean=jnp.zeros(dim), var=jnp.ones(dim), count=jnp.asarray(1e-4))

    def update(self, batch: jax.Array) -> RunningStats:
        """Fold in ``batch`` (..., dim)."""
        batch = batch.reshape(-1, batch.shape[-1])
        batch_mean, batch_var, n = batch.mean(0), batch.var(0), batch.shape[0]
        total = self.count + n
        delta = batch_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        return RunningStats(mean=mean, var=m2 / total, count=total)

    def normalize(self, x: jax.Array, clip: float = 5.0) -> jax.Array:
        return jnp.clip((x - self.mean) / jnp.sqrt(self.var + 1e-5), -clip, clip)

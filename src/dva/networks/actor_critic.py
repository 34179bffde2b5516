"""D.Va / SHAC's networks: ELU + LayerNorm MLPs, the Gaussian actor with a state-independent
log-std, the state critic, and running mean / std statistics of the observations.

Two styles, the same shapes and parameters: ``"flax"`` (Dense → LayerNorm → ELU, Flax's default
initialisers) and ``"authors"`` (as the paper's authors' PyTorch code: Linear → ELU → LayerNorm;
orthogonal weights with gain √2 for the convolutions and every critic layer, gain 1 for the
encoder's trunk; PyTorch's default ``U(±1/√fan_in)`` weights and biases for the actor's MLP)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, get_args

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from dva.networks.conv import PixelEncoder

NetworkStyle = Literal["flax", "authors"]
NETWORK_STYLES: tuple[str, ...] = get_args(NetworkStyle)
LayerInit = Literal["lecun", "orthogonal", "pytorch"]


def dense(width: int, fan_in: int, init: LayerInit, gain: float = 1.0) -> nn.Dense:
    """A Dense layer initialised as ``init`` says: Flax's LeCun normal (zero bias), orthogonal
    weights scaled by ``gain`` (zero bias), or PyTorch's ``nn.Linear`` default (weights and bias
    uniform in ±1/√fan_in)."""
    if init == "lecun":
        return nn.Dense(width)
    if init == "orthogonal":
        return nn.Dense(width, kernel_init=nn.initializers.orthogonal(gain))
    bound = fan_in**-0.5
    uniform = nn.initializers.uniform(2 * bound)  # [0, 2·bound), shifted below

    def shifted(key, shape, dtype=jnp.float32):
        return uniform(key, shape, dtype) - bound

    return nn.Dense(width, kernel_init=shifted, bias_init=shifted)


class MLP(nn.Module):
    """Hidden layers Dense → LayerNorm → ELU (``norm_last``: Dense → ELU → LayerNorm, the authors'
    order), then a linear output layer; every Dense initialised by ``initializer`` (see :func:`dense`)."""

    hidden: Sequence[int]
    out: int
    norm_last: bool = False
    initializer: LayerInit = "lecun"
    gain: float = 1.0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = dense(width, x.shape[-1], self.initializer, self.gain)(x)
            x = nn.LayerNorm()(nn.elu(x)) if self.norm_last else nn.elu(nn.LayerNorm()(x))
        return dense(self.out, x.shape[-1], self.initializer, self.gain)(x)


class Actor(nn.Module):
    """Gaussian policy head: mean from an MLP, state-independent log-std initialised to −1.

    With ``pixels=True`` the input goes through :class:`PixelEncoder` and a Linear → LayerNorm →
    Tanh trunk of width ``trunk`` first. Returns ``(mean, log_std)`` of the pre-tanh action; with
    ``state_dim > 0`` also a linear prediction of the (normalised) simulator state from the trunk's
    features, for the auxiliary state-prediction loss (``predict_state=True``; init with it).
    ``style``: see the module's docstring.
    """

    action_dim: int
    hidden: Sequence[int]
    pixels: bool
    trunk: int = 64
    init_log_std: float = -1.0
    state_dim: int = 0
    style: NetworkStyle = "flax"

    @nn.compact
    def __call__(self, observation: jax.Array, predict_state: bool = False):
        x = observation
        authors = self.style == "authors"
        if self.pixels:
            x = PixelEncoder(orthogonal=authors)(x)
            x = jnp.tanh(nn.LayerNorm()(dense(self.trunk, x.shape[-1], "orthogonal" if authors else "lecun")(x)))
        mean = MLP(self.hidden, self.action_dim, norm_last=authors, initializer="pytorch" if authors else "lecun")(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,))
        log_std = jnp.broadcast_to(log_std, mean.shape)
        if predict_state:
            return mean, log_std, nn.Dense(self.state_dim, name="state_head")(x)
        return mean, log_std


class Critic(nn.Module):
    """State-value MLP (ELU + LayerNorm) on the normalised low-dimensional state; ``style``: see
    the module's docstring."""

    hidden: Sequence[int]
    style: NetworkStyle = "flax"

    @nn.compact
    def __call__(self, state: jax.Array) -> jax.Array:
        if self.style == "authors":
            return MLP(self.hidden, 1, norm_last=True, initializer="orthogonal", gain=2**0.5)(state)[..., 0]
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

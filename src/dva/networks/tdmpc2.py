"""TD-MPC2's networks: MLPs of Dense → LayerNorm → Mish layers, SimNorm latents, the pixel encoder
(four strided convolutions) and an ensemble of Q-functions kept as stacked parameters, so that a
caller evaluates only the members it draws."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from dva.errors import DvaUsageError
from dva.networks.conv import Conv, scale_pixels

# TD-MPC2 initialises every linear layer's weights from a normal of std 0.02 truncated at ±2 std
# (PyTorch's trunc_normal_ with its default ±2 bounds), biases at 0.
dense_init = nn.initializers.truncated_normal(0.02)


def simnorm(x: jax.Array, group: int) -> jax.Array:
    """Simplicial normalisation: the last axis cut into groups of ``group`` entries, each
    group a softmax — the latent is a point on a product of simplices (bounded, and sparse where a
    group's logits differ)."""
    groups = x.reshape(x.shape[:-1] + (-1, group))
    return jax.nn.softmax(groups, -1).reshape(x.shape)


class NormedMLP(nn.Module):
    """TD-MPC2's MLP: ``hidden`` × (Dense → LayerNorm → Mish), dropout after the first Dense,
    then an output layer: Dense → LayerNorm → SimNorm for a latent (``simnorm_group`` > 0), else a
    plain Dense (zero-initialised for the reward and Q heads, which then start predicting 0)."""

    hidden: Sequence[int]
    out: int
    simnorm_group: int = 0
    zero_output: bool = False
    dropout: float = 0.0

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        for i, width in enumerate(self.hidden):
            x = nn.Dense(width, kernel_init=dense_init)(x)
            if i == 0 and self.dropout > 0:
                x = nn.Dropout(self.dropout, deterministic=deterministic)(x)
            x = jax.nn.mish(nn.LayerNorm()(x))
        if self.simnorm_group:
            return simnorm(nn.LayerNorm()(nn.Dense(self.out, kernel_init=dense_init)(x)), self.simnorm_group)
        return nn.Dense(self.out, kernel_init=nn.initializers.zeros if self.zero_output else dense_init)(x)


class TDMPC2PixelEncoder(nn.Module):
    """TD-MPC2's pixel encoder: convolutions 7×7 /2, 5×5 /2, 3×3 /2, 3×3 /1 of ``channels`` each,
    ReLU between them, flattened and SimNorm-ed (64² frames give 4·4·32 = 512 latent entries, 48²
    give 2·2·32 = 128). uint8 in, scaled ``x/255 − 0.5``."""

    channels: int = 32
    simnorm_group: int = 8

    @nn.compact
    def __call__(self, pixels: jax.Array) -> jax.Array:
        batch_shape = pixels.shape[:-3]
        x = scale_pixels(pixels.reshape((-1,) + pixels.shape[-3:]))
        layers = ((7, 2), (5, 2), (3, 2), (3, 1))
        for i, (size, stride) in enumerate(layers):
            x = Conv(self.channels, stride, size)(x)
            if i < len(layers) - 1:
                x = nn.relu(x)
        return simnorm(x.reshape(batch_shape + (-1,)), self.simnorm_group)


def pixel_latent_dim(image_size: int, channels: int) -> int:
    """The width of :class:`TDMPC2PixelEncoder`'s output for ``image_size``² frames."""
    size = image_size
    for kernel, stride in ((7, 2), (5, 2), (3, 2), (3, 1)):
        size = (size - kernel) // stride + 1
    if size < 1:
        raise DvaUsageError(f"image_size = {image_size} is too small for TD-MPC2's encoder; use ≥ 39")
    return size * size * channels


class QEnsemble:
    """``members`` Q-functions of one :class:`NormedMLP` shape, their parameters stacked on a
    leading axis: :meth:`apply` evaluates the members ``index`` names (all by default)."""

    def __init__(self, members: int, hidden: Sequence[int], num_bins: int, dropout: float) -> None:
        self.members = members
        self.net = NormedMLP(hidden, num_bins, zero_output=True, dropout=dropout)

    def init(self, key: jax.Array, x: jax.Array) -> dict:
        return jax.vmap(lambda k: self.net.init(k, x))(jax.random.split(key, self.members))

    def apply(
        self, params: dict, x: jax.Array, index: jax.Array | None = None, dropout_key: jax.Array | None = None
    ) -> jax.Array:
        """The logits (members, …, num_bins) of the members ``index`` (an int array) on ``x``;
        with ``dropout_key``, with dropout (training)."""
        if index is not None:
            params = jax.tree.map(lambda p: p[index], params)
        count = jax.tree.leaves(params)[0].shape[0]
        if dropout_key is None:
            return jax.vmap(lambda p: self.net.apply(p, x))(params)
        keys = jax.random.split(dropout_key, count)
        return jax.vmap(lambda p, k: self.net.apply(p, x, deterministic=False, rngs={"dropout": k}))(params, keys)


def concat_action(z: jax.Array, action: jax.Array) -> jax.Array:
    return jnp.concatenate([z, action], axis=-1)

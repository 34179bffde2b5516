"""DreamerV3's networks: the state vector's MLP encoder, the conv encoder and decoder (strided
4×4 convolutions as 2×2 ones over 2×2 pixel blocks), the RSSM and the MLP heads."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from dva.errors import DvaUsageError
from dva.networks.conv import conv_valid, scale_pixels


def norm_silu(x: jax.Array, width: int) -> jax.Array:
    """DreamerV3's layer: Dense → LayerNorm → SiLU (call inside a compact module)."""
    return nn.silu(nn.LayerNorm()(nn.Dense(width)(x)))


class DreamerMLP(nn.Module):
    """``layers`` × (Dense → LayerNorm → SiLU), then a linear output (zero-initialised for the
    reward and critic heads, so that they start predicting 0, and for the actor, whose mean
    action then starts at 0)."""

    units: int
    layers: int
    out: int
    zero_output: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.layers):
            x = norm_silu(x, self.units)
        init = nn.initializers.zeros if self.zero_output else nn.initializers.lecun_normal()
        return nn.Dense(self.out, kernel_init=init)(x)


class MLPEncoder(nn.Module):
    """DreamerV3's encoder of a state vector (which the agent has ``symlog``-squashed):
    ``layers`` × (Dense → LayerNorm → SiLU)."""

    units: int
    layers: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.layers):
            x = norm_silu(x, self.units)
        return x


def _space_to_depth(x: jax.Array) -> jax.Array:
    """(N, 2H, 2W, C) → (N, H, W, 4C), each 2×2 block's pixels as channels in (row, column, C) order."""
    n, height, width, channels = x.shape
    blocks = x.reshape(n, height // 2, 2, width // 2, 2, channels).transpose(0, 1, 3, 2, 4, 5)
    return blocks.reshape(n, height // 2, width // 2, 4 * channels)


def _pad_one(x: jax.Array) -> jax.Array:
    return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))


def strided_conv4(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """``nn.Conv(…, (4, 4), (2, 2), "SAME")`` without its bias, for even sizes: the padded input's
    2×2 blocks become channels, so the 4×4 stride-2 convolution is a 2×2 stride-1 one with the
    same multiply-adds, whose gradients XLA computes faster on the CPU than its strided
    convolution's (``benchmarks/dreamer_update.py``)."""
    channels, features = kernel.shape[2:]
    # kernel[2a + b, 2a' + b'] multiplies block (y + a, y' + a')'s pixel (b, b')
    blocked = kernel.reshape(2, 2, 2, 2, channels, features).transpose(0, 2, 1, 3, 4, 5)
    return conv_valid(_space_to_depth(_pad_one(x)), blocked.reshape(2, 2, 4 * channels, features), 1)


def strided_conv4_transpose(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """``nn.ConvTranspose(…, (4, 4), (2, 2), "SAME")`` without its bias: each of the output's four
    pixel phases (row and column parity r, c) is a 2×2 stride-1 convolution of the padded input
    with the kernel taps ``kernel[r::2, c::2]``: no multiply-add touches the zeros of XLA's
    input-dilated convolution, three quarters of its input.

    With few output features (≤ 16: the CPU preset decoder's last two layers) the four phases are one 3×3
    convolution with 4 × features outputs (each phase's taps in its 2×2 corner of the 3×3 window),
    whose pixels are then put in place: 2.25× the multiply-adds, but half the time forward and
    backward on the CPU, where interleaving four thin outputs costs more than the convolutions
    (``benchmarks/dreamer_update.py``)."""
    padded, (n, height, width), features = _pad_one(x), x.shape[:3], kernel.shape[-1]
    if features <= 16:
        windows = jnp.zeros((3, 3) + kernel.shape[2:3] + (2, 2, features), kernel.dtype)
        for r in (0, 1):
            for c in (0, 1):  # output pixel (2m + r, 2m' + c) reads padded rows m + r + (0, 1)
                windows = windows.at[r : r + 2, c : c + 2, :, r, c].set(kernel[r::2, c::2])
        out = conv_valid(padded, windows.reshape(3, 3, -1, 4 * features), 1)  # (N, H, W, (r, c, F))
        return (
            out.reshape(n, height, width, 2, 2, features)
            .transpose(0, 1, 3, 2, 4, 5)
            .reshape(n, 2 * height, 2 * width, features)
        )
    phases = [
        [conv_valid(padded[:, r : r + height + 1, c : c + width + 1], kernel[r::2, c::2], 1) for c in (0, 1)]
        for r in (0, 1)
    ]  # output pixel (2m + r, 2m' + c) reads input rows m + r − 1 + (0, 1)
    interleaved = jnp.stack([jnp.stack(row, axis=3) for row in phases], axis=2)  # (N, H, r, W, c, F)
    return interleaved.reshape(n, 2 * height, 2 * width, features)


class StridedConv4(nn.Module):
    """A 4×4, stride-2, SAME convolution (or its transpose, ``transpose=True``) with bias: the
    parameters, names and initialisation of ``nn.Conv`` / ``nn.ConvTranspose``, computed by
    :func:`strided_conv4` / :func:`strided_conv4_transpose`."""

    features: int
    transpose: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        if not self.transpose and (x.shape[1] % 2 or x.shape[2] % 2):
            raise DvaUsageError(
                f"image size {x.shape[1:3]} is not allowed for a stride-2 4×4 convolution; use even sizes"
            )
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (4, 4, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return (strided_conv4_transpose if self.transpose else strided_conv4)(x, kernel) + bias


class ConvEncoder(nn.Module):
    """4 × (4×4 conv, stride 2, LayerNorm, SiLU) with ``depth`` × (1, 2, 4, 8) channels: a uint8
    (…, S, S, 3) image becomes (S/16)² × 8·depth features."""

    depth: int = 32

    @nn.compact
    def __call__(self, pixels: jax.Array) -> jax.Array:
        batch_shape = pixels.shape[:-3]
        x = scale_pixels(pixels.reshape((-1,) + pixels.shape[-3:]))
        for index, multiplier in enumerate((1, 2, 4, 8)):  # nn.Conv's names: older checkpoints load
            x = nn.silu(nn.LayerNorm()(StridedConv4(self.depth * multiplier, name=f"Conv_{index}")(x)))
        return x.reshape(batch_shape + (-1,))


class ConvDecoder(nn.Module):
    """The encoder mirrored with transposed convolutions: features → (…, S, S, 3) images in the
    encoder's ``x/255 − 0.5`` scale."""

    depth: int = 32
    image_size: int = 64

    @nn.compact
    def __call__(self, features: jax.Array) -> jax.Array:
        batch_shape, side = features.shape[:-1], self.image_size // 16
        x = nn.Dense(side * side * 8 * self.depth)(features.reshape(-1, features.shape[-1]))
        x = x.reshape(-1, side, side, 8 * self.depth)
        for index, multiplier in enumerate((4, 2, 1)):
            x = StridedConv4(self.depth * multiplier, transpose=True, name=f"ConvTranspose_{index}")(x)
            x = nn.silu(nn.LayerNorm()(x))
        x = StridedConv4(3, transpose=True, name="ConvTranspose_3")(x)
        return x.reshape(batch_shape + x.shape[1:])


class LayerNormGRU(nn.Module):
    """The 2023 DreamerV3 reference's GRU: one bias-free Dense over ``[h, x]`` to the three gates'
    pre-activations, LayerNorm over all of them, the reset gate applied to the candidate's
    pre-activation, and the update gate's pre-activation shifted by −1 (the state starts by
    keeping most of itself). Returns the next ``h``."""

    features: int

    @nn.compact
    def __call__(self, deter: jax.Array, x: jax.Array) -> jax.Array:
        gates = nn.LayerNorm()(nn.Dense(3 * self.features, use_bias=False)(jnp.concatenate([deter, x], -1)))
        reset, candidate, update = jnp.split(gates, 3, axis=-1)
        candidate = jnp.tanh(jax.nn.sigmoid(reset) * candidate)
        update = jax.nn.sigmoid(update - 1.0)
        return update * candidate + (1.0 - update) * deter


class RSSM(nn.Module):
    """DreamerV3's recurrent state-space model: a deterministic GRU state ``h`` and a stochastic
    state ``z`` of ``stoch`` categoricals with ``classes`` classes each (one-hot, (…, stoch, classes)).

    ``transition(h, z, a)`` is the next ``h``; ``prior(h)`` predicts ``z``'s logits from ``h`` alone
    (imagination), ``posterior(h, embedding)`` from ``h`` and the image (observation); the agent
    mixes them with the uniform distribution (``model_based_math.unimix_logits``)."""

    deter: int = 512
    stoch: int = 32
    classes: int = 32
    units: int = 512

    def setup(self) -> None:
        self.input_layer = nn.Dense(self.units)
        self.input_norm = nn.LayerNorm()
        self.cell = LayerNormGRU(self.deter)
        self.prior_net = DreamerMLP(self.units, 1, self.stoch * self.classes)
        self.posterior_net = DreamerMLP(self.units, 1, self.stoch * self.classes)

    def transition(self, deter: jax.Array, stoch: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([stoch.reshape(stoch.shape[:-2] + (-1,)), action], axis=-1)
        return self.cell(deter, nn.silu(self.input_norm(self.input_layer(x))))

    def _logits(self, net: nn.Module, x: jax.Array) -> jax.Array:
        return net(x).reshape(x.shape[:-1] + (self.stoch, self.classes))

    def prior(self, deter: jax.Array) -> jax.Array:
        return self._logits(self.prior_net, deter)

    def posterior(self, deter: jax.Array, embedding: jax.Array) -> jax.Array:
        return self._logits(self.posterior_net, jnp.concatenate([deter, embedding], axis=-1))

    def __call__(self, deter: jax.Array, stoch: jax.Array, action: jax.Array, embedding: jax.Array):
        """Every sub-network once (what ``init`` needs)."""
        deter = self.transition(deter, stoch, action)
        return self.prior(deter), self.posterior(deter, embedding)

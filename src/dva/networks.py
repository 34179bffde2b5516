"""Networks (docs/algorithms.md): the DrQ-v2 pixel encoder every pixel algorithm shares; D.Va / SHAC's
ELU+LayerNorm MLPs, Gaussian actor with a state-independent log-std and state critic; DrQ-v2's
deterministic actor and twin Q critic; CURL's squashed-Gaussian actor and projection; DreamerV3's conv encoder
and decoder, RSSM
and heads; running mean/std statistics."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

CONV_DIMENSIONS = ("NHWC", "HWIO", "NHWC")


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv_valid(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    """A VALID, NHWC × HWIO convolution: XLA's own forward, its gradients as NHWC × HWIO
    convolutions too. On the CPU XLA's forward runs at ≈ 110 GFLOP/s only with YNNPACK's fusions
    off, which :mod:`dva.runtime` sees to (≈ 18 with them on). XLA's own gradients use other
    dimension orders, which its CPU backend runs 20× (input) to 185× (kernel) slower inside a
    loop body — a ``lax.scan`` over chunks, a reverse scan through the rollout, a scan of updates
    — than at the top level (jax-ml/jax#12868); written as NHWC × HWIO forward convolutions they
    run at full speed in both (docs/development.md, "CPU speed notes").
    A ``custom_vjp``: reverse mode only (``jax.jvp`` through it raises)."""
    return _conv(x, kernel, stride)


def _conv(
    x: jax.Array,
    kernel: jax.Array,
    stride: int,
    lhs_dilation: int = 1,
    rhs_dilation: int = 1,
    padding: str | Sequence[tuple[int, int]] = "VALID",
) -> jax.Array:
    return jax.lax.conv_general_dilated(
        x,
        kernel,
        (stride, stride),
        padding,
        (lhs_dilation,) * 2,
        (rhs_dilation,) * 2,
        dimension_numbers=CONV_DIMENSIONS,
    )


def _conv_valid_forward(x, kernel, stride):
    return _conv(x, kernel, stride), (x, kernel)


def _conv_valid_backward(stride, residuals, out_grad):
    x, kernel = residuals
    size_h, size_w = kernel.shape[:2]
    out_h, out_w = out_grad.shape[1:3]
    used_h, used_w = (out_h - 1) * stride + size_h, (out_w - 1) * stride + size_w  # rows a stride skips at the end
    # dK[i, j, c, o] = Σ_{n,y,x} x[n, s·y + i, s·x + j, c] · g[n, y, x, o]: images as channels,
    # channels as images, the output gradient as a kernel dilated by the stride.
    kernel_grad = _conv(
        x[:, :used_h, :used_w].transpose(3, 1, 2, 0), out_grad.transpose(1, 2, 0, 3), 1, rhs_dilation=stride
    ).transpose(1, 2, 0, 3)
    # dx: the output gradient dilated by the stride, fully padded, against the flipped kernel.
    flipped = jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2)
    padding = [(size_h - 1, size_h - 1 + x.shape[1] - used_h), (size_w - 1, size_w - 1 + x.shape[2] - used_w)]
    input_grad = _conv(out_grad, flipped, 1, lhs_dilation=stride, padding=padding)
    return input_grad, kernel_grad


conv_valid.defvjp(_conv_valid_forward, _conv_valid_backward)


def scale_pixels(pixels: jax.Array) -> jax.Array:
    """uint8 pixels as the networks see them: ``x/255 − 0.5`` in [−0.5, 0.5] (also DreamerV3's
    reconstruction target)."""
    return pixels.astype(jnp.float32) / 255.0 - 0.5


class Conv(nn.Module):
    """3×3 VALID convolution + bias (the parameters of ``nn.Conv``; older checkpoints load)."""

    features: int
    stride: int = 1
    size: int = 3

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (self.size, self.size, x.shape[-1], self.features)
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return conv_valid(x, kernel, self.stride) + bias


class PixelEncoder(nn.Module):
    """DrQ-v2's conv stack: 4 × (3×3, 32 channels, ReLU), first stride 2; uint8 in, features out.

    Pixels are scaled ``x/255 − 0.5``. An 84×84×9 input gives 35×35×32 = 39200 features.
    """

    channels: int = 32

    @nn.compact
    def __call__(self, pixels: jax.Array) -> jax.Array:
        batch_shape = pixels.shape[:-3]
        x = scale_pixels(pixels.reshape((-1,) + pixels.shape[-3:]))
        for stride in (2, 1, 1, 1):
            x = nn.relu(Conv(self.channels, stride)(x))
        return x.reshape(batch_shape + (-1,))


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
    Tanh trunk of width ``trunk`` first. Returns ``(mean, log_std)`` of the pre-tanh action.
    """

    action_dim: int
    hidden: Sequence[int]
    pixels: bool
    trunk: int = 64
    init_log_std: float = -1.0

    @nn.compact
    def __call__(self, observation: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = observation
        if self.pixels:
            x = PixelEncoder()(x)
            x = jnp.tanh(nn.LayerNorm()(nn.Dense(self.trunk)(x)))
        mean = MLP(self.hidden, self.action_dim)(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,))
        return mean, jnp.broadcast_to(log_std, mean.shape)


class Critic(nn.Module):
    """State-value MLP (ELU + LayerNorm) on the normalised low-dimensional state."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, state: jax.Array) -> jax.Array:
        return MLP(self.hidden, 1)(state)[..., 0]


class ReluMLP(nn.Module):
    """DrQ-v2's MLP: Dense → ReLU hidden layers, then a linear output layer."""

    hidden: Sequence[int]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.out)(x)


def feature_trunk(x: jax.Array, features: int) -> jax.Array:
    """DrQ-v2's trunk on encoder features: Dense → LayerNorm → Tanh (call inside a compact module)."""
    return jnp.tanh(nn.LayerNorm()(nn.Dense(features)(x)))


class DeterministicActor(nn.Module):
    """DrQ-v2's actor on encoder features: trunk, ReLU MLP, ``tanh`` mean action in [−1, 1]."""

    action_dim: int
    feature_dim: int = 50
    hidden: Sequence[int] = (1024, 1024)

    @nn.compact
    def __call__(self, features: jax.Array) -> jax.Array:
        return jnp.tanh(ReluMLP(self.hidden, self.action_dim)(feature_trunk(features, self.feature_dim)))


class TwinQ(nn.Module):
    """Clipped double Q (DrQ-v2, CURL): one trunk on encoder features, two Q heads on
    ``[trunk(features), action]``. Returns ``(q1, q2)``, each (batch,)."""

    feature_dim: int = 50
    hidden: Sequence[int] = (1024, 1024)

    @nn.compact
    def __call__(self, features: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = jnp.concatenate([feature_trunk(features, self.feature_dim), action], axis=-1)
        return ReluMLP(self.hidden, 1)(x)[..., 0], ReluMLP(self.hidden, 1)(x)[..., 0]


class SquashedGaussianActor(nn.Module):
    """SAC's actor on encoder features (CURL): trunk, ReLU MLP, ``(mean, log_std)`` of the pre-tanh
    action with ``log_std`` squashed into [−10, 2]."""

    action_dim: int
    feature_dim: int = 50
    hidden: Sequence[int] = (1024, 1024)
    log_std_range: tuple[float, float] = (-10.0, 2.0)

    @nn.compact
    def __call__(self, features: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = ReluMLP(self.hidden, 2 * self.action_dim)(feature_trunk(features, self.feature_dim))
        mean, log_std = jnp.split(out, 2, axis=-1)
        low, high = self.log_std_range
        return mean, low + 0.5 * (high - low) * (jnp.tanh(log_std) + 1.0)


class Projection(nn.Module):
    """CURL's projection of encoder features for the contrastive loss: Dense → LayerNorm."""

    features: int = 50

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        return nn.LayerNorm()(nn.Dense(self.features)(x))


# ---- DreamerV3 --------------------------------------------------------------------------------
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
    input-dilated convolution, three quarters of its input."""
    padded, (n, height, width), features = _pad_one(x), x.shape[:3], kernel.shape[-1]
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
            raise ValueError(f"image size {x.shape[1:3]} is not allowed for a stride-2 4×4 convolution; use even sizes")
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


class RSSM(nn.Module):
    """DreamerV3's recurrent state-space model: a deterministic GRU state ``h`` and a stochastic
    state ``z`` of ``stoch`` categoricals with ``classes`` classes each (one-hot, (…, stoch, classes)).

    ``transition(h, z, a)`` is the next ``h``; ``prior(h)`` predicts ``z``'s logits from ``h`` alone
    (imagination), ``posterior(h, embedding)`` from ``h`` and the image (observation); the agent
    mixes them with the uniform distribution (``dreamer_math.unimix_logits``)."""

    deter: int = 512
    stoch: int = 32
    classes: int = 32
    units: int = 512

    def setup(self) -> None:
        self.input_layer = nn.Dense(self.units)
        self.input_norm = nn.LayerNorm()
        self.cell = nn.GRUCell(features=self.deter)
        self.prior_net = DreamerMLP(self.units, 1, self.stoch * self.classes)
        self.posterior_net = DreamerMLP(self.units, 1, self.stoch * self.classes)

    def transition(self, deter: jax.Array, stoch: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([stoch.reshape(stoch.shape[:-2] + (-1,)), action], axis=-1)
        return self.cell(deter, nn.silu(self.input_norm(self.input_layer(x))))[0]

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

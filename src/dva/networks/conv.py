"""The convolutions and the pixel encoder every pixel algorithm shares (DrQ-v2's), with a
backward pass that runs at full speed inside loops (docs/development.md, "CPU speed notes")."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

CONV_DIMENSIONS = ("NHWC", "HWIO", "NHWC")


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv_valid(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    """A VALID, NHWC × HWIO convolution: XLA's own forward, its gradients as NHWC × HWIO
    convolutions too. On the CPU XLA's forward runs at ≈ 110 GFLOP/s only with YNNPACK's fusions
    off, which :mod:`dva.runner.runtime` sees to (≈ 18 with them on). XLA's own gradients use other
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
    """3×3 VALID convolution + bias (the parameters of ``nn.Conv``; older checkpoints load);
    kernels LeCun normal, or ``orthogonal`` with gain √2 (each filter a scaled orthonormal vector:
    PyTorch's ``orthogonal_`` on its (out, in·3·3) weight)."""

    features: int
    stride: int = 1
    size: int = 3
    orthogonal: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        init = nn.initializers.orthogonal(2**0.5) if self.orthogonal else nn.initializers.lecun_normal()
        kernel = self.param("kernel", init, (self.size, self.size, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return conv_valid(x, kernel, self.stride) + bias


class PixelEncoder(nn.Module):
    """DrQ-v2's conv stack: 4 × (3×3, 32 channels, ReLU), first stride 2; uint8 in, features out.

    Pixels are scaled ``x/255 − 0.5``. An 84×84×9 input gives 35×35×32 = 39200 features.
    ``orthogonal``: the kernels' initialisation (see :class:`Conv`).
    """

    channels: int = 32
    orthogonal: bool = False

    @nn.compact
    def __call__(self, pixels: jax.Array) -> jax.Array:
        batch_shape = pixels.shape[:-3]
        x = scale_pixels(pixels.reshape((-1,) + pixels.shape[-3:]))
        for stride in (2, 1, 1, 1):
            x = nn.relu(Conv(self.channels, stride, orthogonal=self.orthogonal)(x))
        return x.reshape(batch_shape + (-1,))

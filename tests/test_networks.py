"""The pixel encoder's convolution: our patch-matmul forward and custom gradient against XLA's
convolution and its autodiff gradient."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.networks import PixelEncoder, conv_valid


def xla_conv(x, kernel, stride):
    return jax.lax.conv_general_dilated(x, kernel, (stride, stride), "VALID",
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("batch", [2, 12])  # the kernel gradient sums over every image
def test_conv_valid_and_its_gradients_match_xla(stride, batch):
    kx, kk, kg = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(kx, (batch, 11, 9, 5))  # odd, non-square sizes: a wrong stride or tap order shows
    kernel = jax.random.normal(kk, (3, 3, 5, 4))
    ours, ours_vjp = jax.vjp(lambda x, k: conv_valid(x, k, stride), x, kernel)
    reference, reference_vjp = jax.vjp(lambda x, k: xla_conv(x, k, stride), x, kernel)
    assert ours.shape == reference.shape == (batch, (11 - 3) // stride + 1, (9 - 3) // stride + 1, 4)
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-5)
    grad_out = jax.random.normal(kg, ours.shape)
    for got, expected in zip(ours_vjp(grad_out), reference_vjp(grad_out)):
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-4)


def test_pixel_encoder_feature_size():
    """DrQ-v2's stack on 84×84: stride 2 then three stride-1 layers give 35×35×32 features."""
    encoder = PixelEncoder()
    pixels = jnp.zeros((1, 84, 84, 9), jnp.uint8)
    features = encoder.apply(encoder.init(jax.random.PRNGKey(0), pixels), pixels)
    assert features.shape == (1, 35 * 35 * 32)

"""The pixel encoders' convolutions: our patch-matmul forms and custom gradient against XLA's
convolution (and Flax's strided and transposed layers) and their autodiff gradients."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.networks import ConvDecoder, ConvEncoder, PixelEncoder, StridedConv4, conv_valid


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


@pytest.mark.parametrize("transpose", [False, True])
def test_strided_conv4_and_its_gradients_match_flax(transpose):
    """DreamerV3's 4×4 stride-2 SAME layers (blocks as channels; the transpose as four output
    phases) against ``nn.Conv`` / ``nn.ConvTranspose`` with the same parameters."""
    kx, kp, kg = jax.random.split(jax.random.PRNGKey(1), 3)
    x = jax.random.normal(kx, (3, 8, 6, 5))  # non-square: a swapped row / column tap shows
    ours = StridedConv4(7, transpose=transpose)
    flax_layer = (nn.ConvTranspose if transpose else nn.Conv)(7, (4, 4), (2, 2), "SAME")
    params = ours.init(kp, x)
    params = jax.tree.map(lambda p: p + 0.1 * jax.random.normal(kg, p.shape), params)  # a non-zero bias
    assert jax.tree.structure(params) == jax.tree.structure(flax_layer.init(kp, x))
    got, got_vjp = jax.vjp(ours.apply, params, x)
    expected, expected_vjp = jax.vjp(flax_layer.apply, params, x)
    assert got.shape == expected.shape == ((3, 16, 12, 7) if transpose else (3, 4, 3, 7))
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-4)
    grad_out = jax.random.normal(kg, got.shape)
    for a, b in zip(jax.tree.leaves(got_vjp(grad_out)), jax.tree.leaves(expected_vjp(grad_out))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)


def test_dreamer_conv_stacks_keep_flax_layer_names_and_reject_odd_images():
    """Checkpoints written with ``nn.Conv`` / ``nn.ConvTranspose`` layers still load; an odd image
    size is refused by name."""
    encoder, decoder = ConvEncoder(4), ConvDecoder(4, 32)
    pixels = jnp.zeros((1, 32, 32, 3), jnp.uint8)
    assert set(encoder.init(jax.random.PRNGKey(0), pixels)["params"]) >= {f"Conv_{i}" for i in range(4)}
    decoder_params = decoder.init(jax.random.PRNGKey(0), jnp.zeros((1, 10)))["params"]
    assert set(decoder_params) >= {f"ConvTranspose_{i}" for i in range(4)}
    with pytest.raises(ValueError, match=r"\(5, 4\).*even"):
        StridedConv4(2).init(jax.random.PRNGKey(0), jnp.zeros((1, 5, 4, 3)))

"""The pixel encoders' convolutions against Flax's layers (DrQ-v2's stack; DreamerV3's strided and
transposed ones as 2×2 block convolutions), values and gradients."""

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.algorithms.shac import SHACConfig
from dva.errors import DvaUsageError
from dva.networks import MLP, Actor, ConvDecoder, ConvEncoder, Critic, PixelEncoder, StridedConv4, conv_valid
from dva.runner.runtime import CPU_FLAGS, YNN_FUSION_FLAG, configure_xla


class FlaxPixelEncoder(nn.Module):
    """DrQ-v2's stack written with Flax's own layers: the reference for :class:`PixelEncoder`."""

    @nn.compact
    def __call__(self, pixels):
        x = pixels.astype(jnp.float32) / 255.0 - 0.5
        for stride in (2, 1, 1, 1):
            x = nn.relu(nn.Conv(32, (3, 3), (stride, stride), padding="VALID")(x))
        return x.reshape(x.shape[0], -1)


def test_pixel_encoder_matches_flax_layers_with_the_same_parameters():
    """Same parameter tree as Flax's ``nn.Conv`` stack (older checkpoints load), same outputs and
    gradients, on an odd, non-square image (a wrong stride or tap order shows)."""
    pixels = jax.random.randint(jax.random.PRNGKey(0), (3, 19, 17, 9), 0, 256).astype(jnp.uint8)
    params = PixelEncoder().init(jax.random.PRNGKey(1), pixels)
    assert jax.tree.structure(params) == jax.tree.structure(FlaxPixelEncoder().init(jax.random.PRNGKey(1), pixels))
    loss = lambda module: lambda p: jnp.sum(jnp.sin(module.apply(p, pixels)))  # noqa: E731
    ours, ours_grad = jax.value_and_grad(loss(PixelEncoder()))(params)
    reference, reference_grad = jax.value_and_grad(loss(FlaxPixelEncoder()))(params)
    np.testing.assert_allclose(ours, reference, rtol=1e-5)
    for got, expected in zip(jax.tree.leaves(ours_grad), jax.tree.leaves(reference_grad)):
        np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("in_loop", [False, True])
def test_conv_valid_gradients_match_xla_at_top_level_and_inside_a_scan(stride, in_loop):
    """``conv_valid``'s own backward (NHWC × HWIO convolutions, fast inside loops) gives XLA's
    input and kernel gradients: stride 2 over 20 rows leaves the last row unused (its gradient 0),
    non-square images and channels catch a swapped axis; inside a ``lax.scan`` as the chunked D.Va
    gradient and visual SHAC's reverse scan run it."""
    kx, kk, kg = jax.random.split(jax.random.PRNGKey(3), 3)
    x = jax.random.normal(kx, (2, 3, 20, 17, 5))  # (loop steps, images, H, W, C)
    kernel = jax.random.normal(kk, (3, 3, 5, 4))
    reference = lambda x, k: jax.lax.conv_general_dilated(  # noqa: E731
        x, k, (stride, stride), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC")
    )
    weights = jax.random.normal(kg, (2,) + reference(x[0], kernel).shape)

    def loss(conv):
        def total(x, k):
            if in_loop:
                return jax.lax.scan(lambda acc, xw: (acc + jnp.sum(xw[1] * conv(xw[0], k)), None), 0.0, (x, weights))[0]
            return sum(jnp.sum(weights[i] * conv(x[i], k)) for i in range(2))

        return total

    ours = jax.jit(jax.value_and_grad(loss(lambda x, k: conv_valid(x, k, stride)), argnums=(0, 1)))(x, kernel)
    expected = jax.value_and_grad(loss(reference), argnums=(0, 1))(x, kernel)
    for got, want in zip(jax.tree.leaves(ours), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    if stride == 2:
        assert not np.any(ours[1][0][:, :, -1])  # the row no output reads gets no gradient


def test_runtime_turns_off_ynnpack_convolutions_unless_the_user_chose(monkeypatch):
    """XLA's CPU convolutions are fast only with YNNPACK's fusions off (dva.runner.runtime); a user's own
    XLA_FLAGS are kept, and their own YNN setting wins."""
    assert YNN_FUSION_FLAG in os.environ["XLA_FLAGS"]  # importing dva set it here
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    configure_xla()
    assert os.environ["XLA_FLAGS"] == f"--xla_backend_optimization_level=0 {CPU_FLAGS}"
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=dot")
    configure_xla()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_experimental_ynn_fusion_type=dot"


def test_pixel_encoder_feature_size():
    """DrQ-v2's stack on 84×84: stride 2 then three stride-1 layers give 35×35×32 features."""
    encoder = PixelEncoder()
    pixels = jnp.zeros((1, 84, 84, 9), jnp.uint8)
    features = encoder.apply(encoder.init(jax.random.PRNGKey(0), pixels), pixels)
    assert features.shape == (1, 35 * 35 * 32)


@pytest.mark.parametrize("transpose, features", [(False, 7), (True, 7), (True, 20)])
def test_strided_conv4_and_its_gradients_match_flax(transpose, features):
    """DreamerV3's 4×4 stride-2 SAME layers (blocks as channels; the transpose as four output
    phases, as one 3×3 convolution for ≤ 16 features) against ``nn.Conv`` / ``nn.ConvTranspose``
    with the same parameters."""
    kx, kp, kg = jax.random.split(jax.random.PRNGKey(1), 3)
    x = jax.random.normal(kx, (3, 8, 6, 5))  # non-square: a swapped row / column tap shows
    ours = StridedConv4(features, transpose=transpose)
    flax_layer = (nn.ConvTranspose if transpose else nn.Conv)(features, (4, 4), (2, 2), "SAME")
    params = ours.init(kp, x)
    params = jax.tree.map(lambda p: p + 0.1 * jax.random.normal(kg, p.shape), params)  # a non-zero bias
    assert jax.tree.structure(params) == jax.tree.structure(flax_layer.init(kp, x))
    got, got_vjp = jax.vjp(ours.apply, params, x)
    expected, expected_vjp = jax.vjp(flax_layer.apply, params, x)
    assert got.shape == expected.shape == ((3, 16, 12, features) if transpose else (3, 4, 3, features))
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


def _layer_norm(x: np.ndarray) -> np.ndarray:
    return (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-6)


def _elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


@pytest.mark.parametrize("norm_last", [False, True])
def test_mlp_orders_its_hidden_layers_as_asked(norm_last):
    mlp = MLP((8, 5), 2, norm_last=norm_last)
    x = jax.random.normal(jax.random.PRNGKey(0), (4, 3))
    params = mlp.init(jax.random.PRNGKey(1), x)["params"]
    h = np.asarray(x, np.float64)
    for i in range(2):
        h = h @ np.asarray(params[f"Dense_{i}"]["kernel"]) + np.asarray(params[f"Dense_{i}"]["bias"])
        h = _layer_norm(_elu(h)) if norm_last else _elu(_layer_norm(h))  # LayerNorm's scale 1, bias 0 at init
    expected = h @ np.asarray(params["Dense_2"]["kernel"]) + np.asarray(params["Dense_2"]["bias"])
    np.testing.assert_allclose(mlp.apply({"params": params}, x), expected, rtol=1e-4, atol=1e-5)


def test_authors_networks_keep_the_parameters_and_take_the_authors_initialisation():
    pixels = jnp.zeros((2, 24, 24, 9), jnp.uint8)  # 5 × 5 × 32 = 800 features
    key = jax.random.PRNGKey(0)
    authors = Actor(3, (32, 16), pixels=True, trunk=32, style="authors").init(key, pixels)["params"]
    flax_style = Actor(3, (32, 16), pixels=True, trunk=32).init(key, pixels)["params"]
    assert jax.tree.map(jnp.shape, authors) == jax.tree.map(jnp.shape, flax_style)  # checkpoints interchange
    for name, conv in authors["PixelEncoder_0"].items():  # each filter a √2-scaled orthonormal vector
        filters = np.asarray(conv["kernel"]).reshape(-1, 32)
        np.testing.assert_allclose(filters.T @ filters, 2 * np.eye(32), atol=1e-4, err_msg=name)
        assert not np.any(conv["bias"])
    trunk = np.asarray(authors["Dense_0"]["kernel"])
    np.testing.assert_allclose(trunk.T @ trunk, np.eye(32), atol=1e-4)
    biases = []
    for name, layer in authors["MLP_0"].items():  # PyTorch's nn.Linear default: U(±1/√fan_in)
        if name.startswith("Dense"):
            bound, kernel = layer["kernel"].shape[0] ** -0.5, np.asarray(layer["kernel"])
            assert 0.8 * bound < np.abs(kernel).max() <= bound and np.abs(layer["bias"]).max() <= bound
            assert abs(kernel.mean()) < 0.3 * bound  # centred, not [0, 2·bound)
            biases.append(np.asarray(layer["bias"]) / bound)
    assert abs(np.concatenate(biases).mean()) < 0.3
    critic = Critic((64, 64), style="authors").init(key, jnp.zeros((1, 11)))["params"]["MLP_0"]
    first = np.asarray(critic["Dense_0"]["kernel"])  # 11 × 64: orthonormal rows, gain √2
    np.testing.assert_allclose(first @ first.T, 2 * np.eye(11), atol=1e-4)
    last = np.asarray(critic["Dense_2"]["kernel"])  # 64 × 1: a column of norm √2
    np.testing.assert_allclose(np.linalg.norm(last), 2**0.5, rtol=1e-5)


def test_shac_config_refuses_an_unknown_network_style():
    with pytest.raises(DvaUsageError, match="networks 'torch' is not allowed; use one of flax, authors"):
        SHACConfig(networks="torch")  # type: ignore[arg-type]

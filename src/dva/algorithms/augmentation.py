"""Image augmentation for the off-policy pixel baselines (DrQ-v2, CURL)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def shift_images(images: jax.Array, shifts: jax.Array, pad: int) -> jax.Array:
    """Each image (B, H, W, C) padded by ``pad`` (edge pixels repeated) and cropped back to H × W
    at offset ``shifts`` (B, 2) in [0, 2·pad]: offset (pad, pad) is the identity."""
    height, width, channels = images.shape[1:]
    padded = jnp.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    crop = lambda image, shift: jax.lax.dynamic_slice(image, (shift[0], shift[1], 0), (height, width, channels))
    return jax.vmap(crop)(padded, shifts)


def random_shift(images: jax.Array, pad: int, key: jax.Array) -> jax.Array:
    """DrQ's augmentation: every image shifted by its own random offset of up to ±``pad`` pixels."""
    return shift_images(images, jax.random.randint(key, (images.shape[0], 2), 0, 2 * pad + 1), pad)

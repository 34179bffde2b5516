"""DrQ-v2's deterministic actor and twin Q critic; CURL's squashed-Gaussian actor and projection."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


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

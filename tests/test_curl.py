"""CURL: InfoNCE logits and loss, the SAC temperature loss and the squashed-Gaussian density
against hand-computed values; an agent whose every part learns and whose key encoder follows by
momentum."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from fakes import small_off_policy_agent

from dva.algorithms.curl import info_nce_logits, squashed_gaussian_sample, temperature_loss


def test_info_nce_logits_and_loss_by_hand():
    query = jnp.array([[1.0, 0.0], [0.0, 1.0]])
    key = jnp.array([[1.0, 0.0], [0.0, 2.0]])
    bilinear = jnp.array([[1.0, 0.5], [0.0, 1.0]])
    # q W kᵀ = [[1, 1], [0, 2]]; each row minus its maximum.
    logits = info_nce_logits(query, key, bilinear)
    np.testing.assert_allclose(logits, [[0.0, 0.0], [-2.0, 0.0]])
    loss = optax.softmax_cross_entropy_with_integer_labels(logits, jnp.arange(2)).mean()
    assert float(loss) == pytest.approx((math.log(2.0) + math.log(1.0 + math.exp(-2.0))) / 2, rel=1e-6)


def test_temperature_loss_by_hand():
    log_alpha = jnp.log(0.1)
    log_prob = jnp.array([-1.0, 0.0])  # entropy estimates 1 and 0, target entropy −1
    assert float(temperature_loss(log_alpha, log_prob, -1.0)) == pytest.approx(0.1 * (2.0 + 1.0) / 2, rel=1e-6)
    # ∂/∂ log α of α·c is α·c: positive here, so gradient descent lowers α (entropy above target).
    assert float(jax.grad(temperature_loss)(log_alpha, log_prob, -1.0)) == pytest.approx(0.15, rel=1e-6)


def test_squashed_gaussian_density_by_hand():
    mean, log_std = jnp.array([[0.3, -0.2]]), jnp.array([[-0.5, 0.1]])
    key = jax.random.PRNGKey(4)
    action, log_prob = squashed_gaussian_sample(mean, log_std, key)
    noise = np.asarray(jax.random.normal(key, mean.shape))
    u = np.asarray(mean) + np.exp(np.asarray(log_std)) * noise
    np.testing.assert_allclose(action, np.tanh(u), rtol=1e-6)
    gaussian = -0.5 * noise**2 - np.asarray(log_std) - 0.5 * np.log(2 * np.pi)
    np.testing.assert_allclose(log_prob, (gaussian - np.log(1 - np.tanh(u) ** 2 + 1e-6)).sum(-1), rtol=1e-5)


def test_curl_update_trains_every_part_and_moves_the_key_encoder_by_momentum():
    # 5 × 4 envs × 2 repeats = 40 env steps: past the seed phase, a full sequence in every env.
    agent, previous, state, metrics = small_off_policy_agent("curl", 5, seed_steps=16, updates_per_iteration=1)
    config = agent.config
    assert metrics.healthy and all(np.isfinite(metrics.logged[name]) for name in agent.loss_names)
    learner, updated = previous.learner, state.learner  # one update apart
    for name in ("encoder", "critic", "actor", "projection", "bilinear", "log_alpha"):
        change = max(
            np.abs(a - b).max()
            for a, b in zip(jax.tree.leaves(updated.params[name]), jax.tree.leaves(learner.params[name]))
        )
        assert change > 0, name
    for name, tau in (
        ("encoder", config.encoder_tau),
        ("projection", config.encoder_tau),
        ("critic", config.critic_tau),
    ):
        expected = jax.tree.map(
            lambda online, old: tau * online + (1 - tau) * old, updated.params[name], learner.target[name]
        )
        for got, want in zip(jax.tree.leaves(updated.target[name]), jax.tree.leaves(expected)):
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    action = agent.act(agent.policy(state), agent.env.observe(state.env))
    assert action.shape == (4, 1) and np.all(np.abs(np.asarray(action)) < 1.0)

"""The model-based agents' numerical pieces against hand-computed values."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.algorithms.model_based_math import (
    categorical_cross_entropy,
    categorical_kl,
    kl_balance_losses,
    lambda_returns,
    normalized_advantage,
    symexp,
    symlog,
    symlog_bins,
    twohot,
    twohot_decode,
    unimix_logits,
    update_return_scale,
)


def test_symlog_and_symexp_by_hand():
    x = jnp.array([-10.0, -1.0, 0.0, 0.5, 100.0])
    np.testing.assert_allclose(symlog(x), [-math.log(11), -math.log(2), 0.0, math.log(1.5), math.log(101)], rtol=1e-6)
    np.testing.assert_allclose(symexp(symlog(x)), x, rtol=1e-5)


def test_twohot_splits_between_neighbours_and_decodes_back():
    bins = jnp.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    x = symexp(jnp.array([0.25, -1.0, 5.0]))  # between 0 and 1; on a bin; beyond the last bin
    encoded = np.asarray(twohot(x, bins))
    np.testing.assert_allclose(encoded[0], [0, 0, 0.75, 0.25, 0], atol=1e-6)
    np.testing.assert_allclose(encoded[1], [0, 1, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(encoded[2], [0, 0, 0, 0, 1], atol=1e-6)
    # logits whose softmax is the two-hot decode to the value (up to the clip at the end bin)
    decoded = twohot_decode(jnp.log(jnp.asarray(encoded[:2]) + 1e-12), bins)
    np.testing.assert_allclose(decoded, x[:2], rtol=1e-5)
    assert symlog_bins().shape == (255,) and float(symlog_bins()[127]) == pytest.approx(0.0, abs=1e-6)


def test_lambda_returns_with_a_terminal_by_hand():
    gamma, lam = 0.9, 0.5
    reward = jnp.array([1.0, 2.0, 3.0])
    value = jnp.array([0.0, 10.0, 20.0, 30.0])
    continuation = jnp.array([1.0, 0.0, 1.0])  # the episode ends after the second step
    r3 = 3.0 + gamma * (0.5 * 30.0 + 0.5 * 30.0)  # R_T = v_T
    r2 = 2.0  # c = 0: nothing after the terminal
    r1 = 1.0 + gamma * (0.5 * 10.0 + 0.5 * r2)  # v of the state step 1 reaches
    np.testing.assert_allclose(lambda_returns(reward, value, continuation, gamma, lam), [r1, r2, r3], rtol=1e-6)


def test_return_normalisation_by_hand():
    returns = jnp.arange(101.0)  # 5th percentile 5, 95th 95
    scale = update_return_scale(jnp.asarray(10.0), returns, decay=0.99)
    assert float(scale) == pytest.approx(0.99 * 10.0 + 0.01 * 90.0)
    np.testing.assert_allclose(normalized_advantage(jnp.array([5.0]), jnp.array([1.0]), jnp.asarray(0.5)), [4.0])
    np.testing.assert_allclose(normalized_advantage(jnp.array([5.0]), jnp.array([1.0]), jnp.asarray(8.0)), [0.5])


def test_kl_balancing_with_free_bits_by_hand():
    posterior = jnp.log(jnp.array([[[0.9, 0.1]]]))  # one group, two classes
    prior = jnp.log(jnp.array([[[0.5, 0.5]]]))
    kl = 0.9 * math.log(0.9 / 0.5) + 0.1 * math.log(0.1 / 0.5)
    assert float(categorical_kl(posterior, prior)[0]) == pytest.approx(kl, rel=1e-5)
    dynamics, representation = kl_balance_losses(posterior, prior, free_nats=0.1)
    assert float(dynamics[0]) == pytest.approx(kl, rel=1e-5) and float(representation[0]) == pytest.approx(kl, rel=1e-5)
    # the dynamics loss trains only the prior, the representation loss only the posterior
    d_post, d_prior = jax.grad(lambda a, b: kl_balance_losses(a, b, 0.1)[0].sum(), argnums=(0, 1))(posterior, prior)
    r_post, r_prior = jax.grad(lambda a, b: kl_balance_losses(a, b, 0.1)[1].sum(), argnums=(0, 1))(posterior, prior)
    assert np.abs(d_post).max() == 0 and np.abs(d_prior).max() > 0
    assert np.abs(r_prior).max() == 0 and np.abs(r_post).max() > 0
    # below the free nats: the constant, and no gradient at all
    dynamics, _ = kl_balance_losses(posterior, prior, free_nats=1.0)
    assert float(dynamics[0]) == 1.0
    assert np.abs(jax.grad(lambda b: kl_balance_losses(posterior, b, 1.0)[0].sum())(prior)).max() == 0


def test_unimix_keeps_every_class_likely():
    probs = jnp.exp(unimix_logits(jnp.array([100.0, 0.0, 0.0, 0.0]), mix=0.01))
    np.testing.assert_allclose(probs, [0.99 + 0.0025, 0.0025, 0.0025, 0.0025], rtol=1e-5)


def test_categorical_cross_entropy_against_hand_computed_values():
    # uniform over 4 classes against a one-hot target: log 4; against a two-hot 0.25/0.75 split
    # of logits (0, log 3): −(0.25 log 0.25 + 0.75 log 0.75)
    np.testing.assert_allclose(categorical_cross_entropy(jnp.zeros(4), jnp.eye(4)[2]), np.log(4.0), rtol=1e-6)
    logits, target = jnp.log(jnp.array([1.0, 3.0])), jnp.array([0.25, 0.75])
    expected = -(0.25 * np.log(0.25) + 0.75 * np.log(0.75))
    np.testing.assert_allclose(categorical_cross_entropy(logits, target), expected, rtol=1e-6)

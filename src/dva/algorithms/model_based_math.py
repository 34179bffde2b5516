"""The numerical pieces of the model-based agents, as pure functions: symlog squashing and
two-hot regression targets (DreamerV3's reward and critic heads, TD-MPC2's reward and Q heads),
λ-returns with continuation flags, percentile return normalisation, KL balancing with free bits
and unimix categoricals (DreamerV3's). Each is tested against hand-computed values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def symlog(x: jax.Array) -> jax.Array:
    """``sign(x) log(1 + |x|)``: compresses large magnitudes, the identity near 0."""
    return jnp.sign(x) * jnp.log1p(jnp.abs(x))


def symexp(x: jax.Array) -> jax.Array:
    """The inverse of :func:`symlog`: ``sign(x) (exp|x| − 1)``."""
    return jnp.sign(x) * jnp.expm1(jnp.abs(x))


def symlog_bins(num_bins: int = 255, low: float = -20.0, high: float = 20.0) -> jax.Array:
    """The bin centres of the reward and critic heads, evenly spaced in symlog space."""
    return jnp.linspace(low, high, num_bins)


def twohot(x: jax.Array, bins: jax.Array) -> jax.Array:
    """Two-hot encoding of ``symlog(x)`` over ``bins`` (…, K): the weight splits between the two
    neighbouring bins in proportion to closeness, so ``Σ w_k bins_k = symlog(x)``; values beyond
    the ends go wholly to the end bin."""
    y = jnp.clip(symlog(x), bins[0], bins[-1])
    upper = jnp.clip(jnp.searchsorted(bins, y, side="right"), 1, len(bins) - 1)
    lower = upper - 1
    weight_upper = (y - bins[lower]) / (bins[upper] - bins[lower])
    return (
        jax.nn.one_hot(lower, len(bins)) * (1.0 - weight_upper)[..., None]
        + jax.nn.one_hot(upper, len(bins)) * weight_upper[..., None]
    )


def categorical_cross_entropy(logits: jax.Array, target: jax.Array) -> jax.Array:
    """The cross-entropy of ``softmax(logits)`` against a (soft) ``target`` distribution, such as a
    :func:`twohot` encoding."""
    return -jnp.sum(target * jax.nn.log_softmax(logits, -1), axis=-1)


def twohot_decode(logits: jax.Array, bins: jax.Array) -> jax.Array:
    """The prediction of a two-hot head: ``symexp(Σ softmax(logits)_k bins_k)``."""
    return symexp(jnp.sum(jax.nn.softmax(logits, axis=-1) * bins, axis=-1))


def lambda_returns(reward: jax.Array, value: jax.Array, continuation: jax.Array, gamma: float, lam: float) -> jax.Array:
    """λ-returns of an imagined trajectory (time-major).

    ``reward``, ``continuation`` (the probability the episode goes on after the step, 0 at a
    terminal) are (T, …) for steps 1…T; ``value`` is (T + 1, …) for states 0…T. Returns (T, …):
    ``R_t = r_t + γ c_t ((1 − λ) v_{t+1} + λ R_{t+1})`` with ``R_T = v_T`` bootstrapping the end.
    """

    def back(next_return, inputs):
        r, c, v_next = inputs
        ret = r + gamma * c * ((1.0 - lam) * v_next + lam * next_return)
        return ret, ret

    _, returns = jax.lax.scan(back, value[-1], (reward, continuation, value[1:]), reverse=True)
    return returns


def update_return_scale(scale: jax.Array, returns: jax.Array, decay: float = 0.99) -> jax.Array:
    """The EMA of the returns' 5th-to-95th percentile range (DreamerV3's return normaliser)."""
    spread = jnp.percentile(returns, 95) - jnp.percentile(returns, 5)
    return decay * scale + (1.0 - decay) * spread


def normalized_advantage(returns: jax.Array, value: jax.Array, scale: jax.Array) -> jax.Array:
    """``(R − v) / max(1, S)``: large returns are scaled down, small ones never scaled up."""
    return (returns - value) / jnp.maximum(1.0, scale)


def categorical_kl(p_logits: jax.Array, q_logits: jax.Array) -> jax.Array:
    """``KL(p ‖ q)`` of independent categoricals (…, groups, classes), summed over the groups."""
    p_log, q_log = jax.nn.log_softmax(p_logits, -1), jax.nn.log_softmax(q_logits, -1)
    return jnp.sum(jnp.exp(p_log) * (p_log - q_log), axis=(-2, -1))


def kl_balance_losses(
    posterior_logits: jax.Array, prior_logits: jax.Array, free_nats: float = 1.0
) -> tuple[jax.Array, jax.Array]:
    """DreamerV3's dynamics and representation losses with free bits:
    ``max(free, KL(sg(post) ‖ prior))`` trains the prior, ``max(free, KL(post ‖ sg(prior)))`` the
    encoder; below ``free_nats`` neither has a gradient. Scale them by 0.5 and 0.1 (DreamerV3's KL balance)."""
    stop = jax.lax.stop_gradient
    dynamics = jnp.maximum(free_nats, categorical_kl(stop(posterior_logits), prior_logits))
    representation = jnp.maximum(free_nats, categorical_kl(posterior_logits, stop(prior_logits)))
    return dynamics, representation


def unimix_logits(logits: jax.Array, mix: float = 0.01) -> jax.Array:
    """Logits of ``(1 − mix) softmax(logits) + mix / K``: every class keeps at least ``mix / K``
    probability, so KLs and log-probabilities stay finite."""
    probs = (1.0 - mix) * jax.nn.softmax(logits, -1) + mix / logits.shape[-1]
    return jnp.log(probs)

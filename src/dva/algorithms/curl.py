"""CURL (Laskin et al. 2020): SAC from pixels with a contrastive auxiliary loss — one of the
paper's model-free visual baselines.

Collection and replay are :class:`~dva.algorithms.off_policy.OffPolicyAgent`'s (exploration: a
sample of the squashed-Gaussian policy); each update on a sampled batch:

* critic and encoder: clipped double-Q regression on the soft target
  ``r + γ (min Q'(f'(o'), a') − α log π(a'|o'))``, ``f'`` the momentum (key) encoder;
* actor on the critic's features, detached: ``α log π(a|o) − min Q(o, a)``;
* temperature: ``α (−log π − target_entropy)`` with ``target_entropy = −|A|``;
* contrastive (InfoNCE): two random shifts of each observation, the query through the online
  encoder and projection, the key through the momentum ones, logits ``q W kᵀ`` with a learned
  bilinear ``W``, the positives on the diagonal; it trains the encoder shared with the critic;
* targets: the critic by Polyak averaging (``critic_tau``), the key encoder and projection with
  ``encoder_tau``.

Where this differs from the original: the augmentation is the random shift of DrQ (pad 4 and
crop back, the same family as CURL's random crop), the encoder is the conv stack every pixel
algorithm here shares, and the actor and targets update on every step.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.augmentation import random_shift
from dva.algorithms.off_policy import OffPolicyAgent, OffPolicyConfig
from dva.algorithms.replay import NStepBatch
from dva.envs.observations import Env, Observation
from dva.networks import Projection, SquashedGaussianActor, TwinQ


@dataclasses.dataclass(frozen=True)
class CURLConfig(OffPolicyConfig):
    """Hyperparameters (the paper's CURL settings)."""

    batch_size: int = 32
    seed_steps: int = 1000
    lr: float = 1e-3  # actor, critic and contrastive
    betas: tuple[float, float] = (0.9, 0.99)
    critic_tau: float = 0.01
    encoder_tau: float = 0.05
    init_temperature: float = 0.1
    temperature_lr: float = 1e-4
    temperature_betas: tuple[float, float] = (0.5, 0.99)


class CURLLearner(struct.PyTreeNode):
    """CURL's networks (online and momentum) and optimiser states."""

    params: dict  # {"encoder", "critic", "actor", "projection", "bilinear", "log_alpha"}
    target: dict  # {"encoder", "projection", "critic"}: momentum key encoder and target critic
    opt_states: dict  # {"critic", "actor", "contrastive", "alpha"}


def squashed_gaussian_sample(mean: jax.Array, log_std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``a = tanh(μ + σε)`` and its log-density (change of variables through the tanh)."""
    noise = jax.random.normal(key, mean.shape)
    action = jnp.tanh(mean + jnp.exp(log_std) * noise)
    gaussian = -0.5 * noise**2 - log_std - 0.5 * math.log(2 * math.pi)
    return action, jnp.sum(gaussian - jnp.log(1.0 - action**2 + 1e-6), axis=-1)


def info_nce_logits(query: jax.Array, key: jax.Array, bilinear: jax.Array) -> jax.Array:
    """CURL's logits ``q W kᵀ`` (B, B), each row shifted by its maximum for stability."""
    logits = query @ bilinear @ key.T
    return logits - jnp.max(logits, axis=1, keepdims=True)


def temperature_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """SAC's temperature loss ``E[α (−log π − H̄)]``: α rises while the entropy is below target."""
    return jnp.mean(jnp.exp(log_alpha) * jax.lax.stop_gradient(-log_prob - target_entropy))


class CURL(OffPolicyAgent):
    """The CURL agent (an :class:`~dva.algorithms.base.Agent`); see the module docstring."""

    loss_names = ("critic_loss", "actor_loss", "contrastive_loss", "q_mean")
    config: CURLConfig

    def __init__(self, env: Env, config: CURLConfig) -> None:
        super().__init__(env, config)
        self.actor = SquashedGaussianActor(self.task.action_dim, config.feature_dim, config.hidden)
        self.critic = TwinQ(config.feature_dim, config.hidden)
        self.projection = Projection(config.feature_dim)
        self.target_entropy = -float(self.task.action_dim)
        self.optimizer = optax.adam(config.lr, b1=config.betas[0], b2=config.betas[1])
        self.alpha_optimizer = optax.adam(
            config.temperature_lr, b1=config.temperature_betas[0], b2=config.temperature_betas[1]
        )

    def init_learner(self, key: jax.Array, pixels: jax.Array) -> CURLLearner:
        keys = jax.random.split(key, 5)
        encoder = self.encoder.init(keys[0], pixels)
        features = self.encoder.apply(encoder, pixels)
        critic = self.critic.init(keys[1], features, jnp.zeros((len(pixels), self.task.action_dim)))
        projection = self.projection.init(keys[3], features)
        params = {
            "encoder": encoder,
            "critic": critic,
            "actor": self.actor.init(keys[2], features),
            "projection": projection,
            "bilinear": jax.random.uniform(keys[4], (self.config.feature_dim,) * 2),
            "log_alpha": jnp.log(jnp.asarray(self.config.init_temperature)),
        }
        return CURLLearner(
            params=params,
            target={"encoder": encoder, "projection": projection, "critic": critic},
            opt_states={
                "critic": self.optimizer.init({"encoder": encoder, "critic": critic}),
                "actor": self.optimizer.init(params["actor"]),
                "contrastive": self.optimizer.init({k: params[k] for k in ("encoder", "projection", "bilinear")}),
                "alpha": self.alpha_optimizer.init(params["log_alpha"]),
            },
        )

    def explore(self, learner: CURLLearner, pixels: jax.Array, env_steps: jax.Array, key: jax.Array):
        """A sample of the policy (reported: the temperature α)."""
        params = learner.params
        mean, log_std = self.actor.apply(params["actor"], self.features(params["encoder"], pixels))
        return squashed_gaussian_sample(mean, log_std, key)[0], jnp.exp(params["log_alpha"])

    def step(self, optimizer, grads, opt_state, params):
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    def update(self, learner: CURLLearner, batch: NStepBatch, env_steps: jax.Array, key: jax.Array):
        """Critic + encoder, actor, temperature and contrastive steps, then the targets."""
        cfg = self.config
        keys = jax.random.split(key, 5)
        obs = random_shift(batch.obs, cfg.shift_pad, keys[0])
        next_obs = random_shift(batch.next_obs, cfg.shift_pad, keys[1])
        params, target, opt = dict(learner.params), learner.target, dict(learner.opt_states)
        alpha = jnp.exp(params["log_alpha"])
        weight = batch.valid / jnp.maximum(batch.valid.sum(), 1)

        next_mean, next_log_std = self.actor.apply(params["actor"], self.features(params["encoder"], next_obs))
        next_action, next_log_prob = squashed_gaussian_sample(next_mean, next_log_std, keys[2])
        target_q = jnp.minimum(
            *self.critic.apply(target["critic"], self.features(target["encoder"], next_obs), next_action)
        )
        soft_target = jax.lax.stop_gradient(batch.reward + batch.discount * (target_q - alpha * next_log_prob))

        trained, opt["critic"], c_loss, features, q1, _ = self.fit_critic(
            params, opt["critic"], obs, batch.action, soft_target, weight
        )
        params.update(trained)

        def actor_loss(actor):
            mean, log_std = self.actor.apply(actor, features)
            action, log_prob = squashed_gaussian_sample(mean, log_std, keys[3])
            q = jnp.minimum(*self.critic.apply(params["critic"], features, action))
            return jnp.mean(jax.lax.stop_gradient(alpha) * log_prob - q), log_prob

        (a_loss, log_prob), grads = jax.value_and_grad(actor_loss, has_aux=True)(params["actor"])
        params["actor"], opt["actor"] = self.step(self.optimizer, grads, opt["actor"], params["actor"])
        grad = jax.grad(temperature_loss)(params["log_alpha"], log_prob, self.target_entropy)
        params["log_alpha"], opt["alpha"] = self.step(self.alpha_optimizer, grad, opt["alpha"], params["log_alpha"])

        anchor = random_shift(batch.obs, cfg.shift_pad, keys[4])  # a second view of each observation
        positive = jax.lax.stop_gradient(
            self.projection.apply(target["projection"], self.features(target["encoder"], anchor))
        )

        def contrastive_loss(trained):
            query = self.projection.apply(trained["projection"], self.features(trained["encoder"], obs))
            logits = info_nce_logits(query, positive, trained["bilinear"])
            return optax.softmax_cross_entropy_with_integer_labels(logits, jnp.arange(len(logits))).mean()

        trained = {k: params[k] for k in ("encoder", "projection", "bilinear")}
        n_loss, grads = jax.value_and_grad(contrastive_loss)(trained)
        trained, opt["contrastive"] = self.step(self.optimizer, grads, opt["contrastive"], trained)
        params.update(trained)

        target = {
            "critic": optax.incremental_update(params["critic"], target["critic"], cfg.critic_tau),
            "encoder": optax.incremental_update(params["encoder"], target["encoder"], cfg.encoder_tau),
            "projection": optax.incremental_update(params["projection"], target["projection"], cfg.encoder_tau),
        }
        metrics = {"critic_loss": c_loss, "actor_loss": a_loss, "contrastive_loss": n_loss, "q_mean": jnp.mean(q1)}
        return CURLLearner(params=params, target=target, opt_states=opt), metrics

    # ---- the agent's policy ------------------------------------------------------------------
    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """``tanh`` of the policy's mean: no sampling."""
        mean, _ = self.actor.apply(policy["actor"], self.features(policy["encoder"], observation["pixels"]))
        return jnp.tanh(mean)

"""DrQ-v2 (Yarats et al. 2021): DDPG from pixels with random-shift augmentation — the paper's
model-free visual baseline.

Collection and replay are :class:`~dva.algorithms.off_policy.OffPolicyAgent`'s (exploration: the
actor's action plus Gaussian noise whose std decays linearly); each update on a sampled batch:

* critic and encoder: clipped double-Q regression on n-step targets
  ``Σ γ^i r + γ^n min(Q'₁, Q'₂)(o_{t+n}, π(o_{t+n}) + clip(σε, ±c))``, both observations
  randomly shifted, the target's features from the online encoder without gradient;
* actor: ``−min(Q₁, Q₂)(f, π(f) + clip(σε, ±c))`` on the critic's features, detached (the encoder
  learns from the critic only);
* target critic: Polyak average with rate ``target_tau``.

With ``state_prediction`` > 0 (``drqv2-privileged``) the encoder also learns to predict the
normalised simulator state through a linear head on its features, as ``dva-privileged``'s does:
that weight × the mean squared error is added to the critic's loss, the state normalised by running
statistics of the replayed states.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.augmentation import random_shift
from dva.algorithms.off_policy import OffPolicyAgent, OffPolicyConfig
from dva.algorithms.replay import NStepBatch
from dva.envs.observations import Env, Observation
from dva.errors import DvaUsageError
from dva.networks import DeterministicActor, RunningStats, TwinQ


@dataclasses.dataclass(frozen=True)
class DrQV2Config(OffPolicyConfig):
    """Hyperparameters (the paper's DrQ-v2 settings; Cart-pole's envs and updates)."""

    batch_size: int = 256
    n_step: int = 3
    replay_size: int = 1_000_000
    lr: float = 1e-4
    target_tau: float = 0.01
    std_start: float = 1.0
    std_end: float = 0.1
    std_decay_steps: int = 500_000  # env (control) steps over which exploration std decays linearly
    std_clip: float = 0.3  # the noise added to the actor's action in the losses is clipped to ±this
    state_prediction: float = 0.0
    """Weight of the auxiliary loss that makes the encoder predict the normalised simulator state
    (the mean over the batch and state dimensions of the squared error, through a linear head on
    the encoder's features), added to the critic's; the replay then keeps each observation's state.
    0: DrQ-v2's loss."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.state_prediction >= 0:
            raise DvaUsageError(f"state_prediction = {self.state_prediction!r} is not allowed; use a number ≥ 0")


class DrQV2Learner(struct.PyTreeNode):
    """DrQ-v2's networks, target critic and optimiser states."""

    params: dict  # {"encoder", "actor", "critic"}
    target_critic: dict
    critic_opt_state: optax.OptState  # encoder and critic (and the state head) together
    actor_opt_state: optax.OptState
    state_stats: RunningStats | None = None  # of the replayed states (the privileged variant only)


def clipped_noise_action(mean: jax.Array, std: jax.Array, clip: float, key: jax.Array) -> jax.Array:
    """``mean + clip(σε, ±clip)`` kept inside (−1, 1); the gradient passes the final clamp
    unchanged (DrQ-v2's truncated normal)."""
    action = mean + jnp.clip(std * jax.random.normal(key, mean.shape), -clip, clip)
    return action + jax.lax.stop_gradient(jnp.clip(action, -1.0 + 1e-6, 1.0 - 1e-6) - action)


class DrQV2(OffPolicyAgent):
    """The DrQ-v2 agent (an :class:`~dva.algorithms.base.Agent`); see the module docstring."""

    loss_names: tuple[str, ...] = ("critic_loss", "actor_loss", "q_mean")
    config: DrQV2Config

    def __init__(self, env: Env, config: DrQV2Config) -> None:
        super().__init__(env, config)
        self.actor = DeterministicActor(self.task.action_dim, config.feature_dim, config.hidden)
        self.critic = TwinQ(config.feature_dim, config.hidden)
        self.optimizer = optax.adam(config.lr)
        self.keeps_state = config.state_prediction > 0
        self.state_head = nn.Dense(self.task.obs_dim)
        if self.keeps_state:
            self.loss_names = (*self.loss_names, "state_prediction_loss")

    def init_learner(self, key: jax.Array, pixels: jax.Array) -> DrQV2Learner:
        encoder_key, actor_key, critic_key, head_key = jax.random.split(key, 4)
        encoder = self.encoder.init(encoder_key, pixels)
        features = self.encoder.apply(encoder, pixels)
        actor = self.actor.init(actor_key, features)
        critic = self.critic.init(critic_key, features, jnp.zeros((len(pixels), self.task.action_dim)))
        trained = {"encoder": encoder, "critic": critic}
        if self.keeps_state:
            trained["state_head"] = self.state_head.init(head_key, features)
        return DrQV2Learner(
            params={**trained, "actor": actor},
            target_critic=critic,
            critic_opt_state=self.optimizer.init(trained),
            actor_opt_state=self.optimizer.init(actor),
            state_stats=RunningStats.create(self.task.obs_dim) if self.keeps_state else None,
        )

    def state_prediction_loss(self, stats: RunningStats, state: jax.Array):
        """``(params, features) → weight × mean squared error`` of the head's prediction of the
        normalised ``state``."""
        target = stats.normalize(state)
        return lambda trained, features: (
            self.config.state_prediction
            * jnp.mean((self.state_head.apply(trained["state_head"], features) - target) ** 2)
        )

    def exploration_std(self, env_steps: jax.Array) -> jax.Array:
        """The linear schedule from ``std_start`` to ``std_end`` over ``std_decay_steps`` env steps."""
        cfg = self.config
        fraction = jnp.clip(env_steps / cfg.std_decay_steps, 0.0, 1.0)
        return cfg.std_start + fraction * (cfg.std_end - cfg.std_start)

    def explore(self, learner: DrQV2Learner, pixels: jax.Array, env_steps: jax.Array, key: jax.Array):
        """The actor's action plus Gaussian noise of the scheduled std (reported as ``exploration``)."""
        std = self.exploration_std(env_steps)
        mean = self.actor.apply(learner.params["actor"], self.features(learner.params["encoder"], pixels))
        return jnp.clip(mean + std * jax.random.normal(key, mean.shape), -1.0, 1.0), std

    def update(self, learner: DrQV2Learner, batch: NStepBatch, env_steps: jax.Array, key: jax.Array):
        """Critic + encoder step, actor step, target update."""
        cfg = self.config
        std = self.exploration_std(env_steps)
        obs_key, next_key, target_key, actor_key = jax.random.split(key, 4)
        obs = random_shift(batch.obs, cfg.shift_pad, obs_key)
        next_obs = random_shift(batch.next_obs, cfg.shift_pad, next_key)
        params = learner.params
        weight = batch.valid / jnp.maximum(batch.valid.sum(), 1)

        next_features = self.features(params["encoder"], next_obs)
        next_action = clipped_noise_action(
            self.actor.apply(params["actor"], next_features), std, cfg.std_clip, target_key
        )
        target_q = jnp.minimum(*self.critic.apply(learner.target_critic, next_features, next_action))
        target = jax.lax.stop_gradient(batch.reward + batch.discount * target_q)

        stats, auxiliary = learner.state_stats, None
        if stats is not None and batch.state is not None:  # the privileged variant
            stats = stats.update(batch.state)
            auxiliary = self.state_prediction_loss(stats, batch.state)
        trained, critic_opt_state, c_loss, features, q1, s_loss = self.fit_critic(
            params, learner.critic_opt_state, obs, batch.action, target, weight, auxiliary
        )

        def actor_loss(actor):
            action = clipped_noise_action(self.actor.apply(actor, features), std, cfg.std_clip, actor_key)
            return -jnp.mean(jnp.minimum(*self.critic.apply(trained["critic"], features, action)))

        a_loss, grads = jax.value_and_grad(actor_loss)(params["actor"])
        updates, actor_opt_state = self.optimizer.update(grads, learner.actor_opt_state, params["actor"])
        actor = optax.apply_updates(params["actor"], updates)
        learner = DrQV2Learner(
            params={**trained, "actor": actor},
            target_critic=optax.incremental_update(trained["critic"], learner.target_critic, cfg.target_tau),
            critic_opt_state=critic_opt_state,
            actor_opt_state=actor_opt_state,
            state_stats=stats,
        )
        losses = {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": jnp.mean(q1)}
        return learner, losses | ({"state_prediction_loss": s_loss} if self.keeps_state else {})

    # ---- the agent's policy ------------------------------------------------------------------
    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """The actor's mean action, no exploration noise."""
        return self.actor.apply(policy["actor"], self.features(policy["encoder"], observation["pixels"]))

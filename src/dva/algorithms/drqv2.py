"""DrQ-v2 (Yarats et al. 2021): DDPG from pixels with random-shift augmentation — the paper's
model-free visual baseline (spec §3).

One :meth:`DrQV2.iteration` (jit it) takes one step in every env (uniform random actions during
the first ``seed_steps`` env steps, then the actor's with scheduled exploration noise), stores it
in the frame replay, and makes ``updates_per_iteration`` updates, each on a sampled batch:

* critic and encoder: clipped double-Q regression on n-step targets
  ``Σ γ^i r + γ^n min(Q'₁, Q'₂)(o_{t+n}, π(o_{t+n}) + clip(σε, ±c))``, both observations
  randomly shifted, the target's features from the online encoder without gradient;
* actor: ``−min(Q₁, Q₂)(f, π(f) + clip(σε, ±c))`` on the critic's features, detached (the encoder
  learns from the critic only);
* target critic: Polyak average with rate ``target_tau``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.envs import Observation, PixelObservations
from dva.networks import DeterministicActor, PixelEncoder, TwinQ
from dva.replay import FrameReplay, NStepBatch, Step
from dva.tasks import EnvState


@dataclasses.dataclass(frozen=True)
class DrQV2Config:
    """Hyperparameters (spec §3's DrQ-v2 row; Cart-pole's envs and updates)."""

    num_envs: int = 16
    image_size: int = 84
    frame_stack: int = 3
    action_repeat: int = 2
    updates_per_iteration: int = 8  # agent updates per collection round (one step of every env)
    batch_size: int = 256
    n_step: int = 3
    gamma: float = 0.99
    lr: float = 1e-4
    target_tau: float = 0.01
    std_start: float = 1.0
    std_end: float = 0.1
    std_decay_steps: int = 500_000  # env (control) steps over which exploration std decays linearly
    std_clip: float = 0.3  # the noise added to the actor's action in the losses is clipped to ±this
    feature_dim: int = 50
    hidden: tuple[int, ...] = (1024, 1024)
    replay_size: int = 1_000_000  # env steps kept, over all envs
    seed_steps: int = 4000  # env steps of uniform random actions before the first update
    shift_pad: int = 4  # random shifts of up to ± this many pixels
    iterations: int = 100_000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.n_step < 1 or self.updates_per_iteration < 1:
            raise ValueError("batch_size, n_step and updates_per_iteration must be ≥ 1")


class DrQV2State(struct.PyTreeNode):
    """Everything one iteration reads and writes (a pytree: jittable, checkpointable)."""

    params: dict  # {"encoder", "actor", "critic"}
    target_critic: dict
    critic_opt_state: optax.OptState  # encoder and critic together
    actor_opt_state: optax.OptState
    env: EnvState
    first: jax.Array  # (N,) bool: the current observation starts an episode
    replay: object  # flashbax trajectory buffer state
    episode_return: jax.Array  # (N,)
    key: jax.Array
    iteration: jax.Array


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


def clipped_noise_action(mean: jax.Array, std: jax.Array, clip: float, key: jax.Array) -> jax.Array:
    """``mean + clip(σε, ±clip)`` kept inside (−1, 1); the gradient passes the final clamp
    unchanged (DrQ-v2's truncated normal)."""
    action = mean + jnp.clip(std * jax.random.normal(key, mean.shape), -clip, clip)
    return action + jax.lax.stop_gradient(jnp.clip(action, -1.0 + 1e-6, 1.0 - 1e-6) - action)


class DrQV2:
    """The DrQ-v2 agent (an :class:`~dva.algorithms.base.Agent`); see the module docstring."""

    metric_names = ("critic_loss", "actor_loss", "q_mean", "exploration_std")

    def __init__(self, env: PixelObservations, config: DrQV2Config) -> None:
        if not env.has_pixels or env.num_envs != config.num_envs:
            raise ValueError(f"DrQ-v2 needs an env wrapper that renders {config.num_envs} envs")
        self.env, self.task, self.config = env, env.task, config
        self.encoder = PixelEncoder()
        self.actor = DeterministicActor(self.task.action_dim, config.feature_dim, config.hidden)
        self.critic = TwinQ(config.feature_dim, config.hidden)
        self.optimizer = optax.adam(config.lr)
        self.replay = FrameReplay(config.num_envs, config.replay_size, config.batch_size, config.frame_stack,
                                  config.n_step, config.gamma)

    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.action_repeat

    @property
    def default_iterations(self) -> int:
        return self.config.iterations

    def init(self, key: jax.Array) -> DrQV2State:
        env_key, encoder_key, actor_key, critic_key, key = jax.random.split(key, 5)
        env = self.env.reset(env_key)
        encoder = self.encoder.init(encoder_key, env.pixels[:1])
        features = self.encoder.apply(encoder, env.pixels[:1])
        actor = self.actor.init(actor_key, features)
        action = jnp.zeros((1, self.task.action_dim))
        critic = self.critic.init(critic_key, features, action)
        params = {"encoder": encoder, "actor": actor, "critic": critic}
        example = Step(frame=env.pixels[0, ..., -3:], first=jnp.ones((), bool), action=action[0],
                       reward=jnp.zeros(()), terminated=jnp.zeros((), bool), truncated=jnp.zeros((), bool))
        return DrQV2State(
            params=params, target_critic=critic,
            critic_opt_state=self.optimizer.init({"encoder": encoder, "critic": critic}),
            actor_opt_state=self.optimizer.init(actor), env=env,
            first=jnp.ones(self.config.num_envs, bool), replay=self.replay.init(example),
            episode_return=jnp.zeros(self.config.num_envs), key=key, iteration=jnp.zeros((), jnp.int32))

    def exploration_std(self, env_steps: jax.Array) -> jax.Array:
        """The linear schedule from ``std_start`` to ``std_end`` over ``std_decay_steps`` env steps."""
        cfg = self.config
        fraction = jnp.clip(env_steps / cfg.std_decay_steps, 0.0, 1.0)
        return cfg.std_start + fraction * (cfg.std_end - cfg.std_start)

    def features(self, encoder: dict, pixels: jax.Array) -> jax.Array:
        return self.encoder.apply(encoder, pixels)

    # ---- one update on a sampled batch --------------------------------------------------------
    def update(self, state: DrQV2State, batch: NStepBatch, std: jax.Array, key: jax.Array):
        """Critic + encoder step, actor step, target update; returns the new state and metrics."""
        cfg = self.config
        obs_key, next_key, target_key, actor_key = jax.random.split(key, 4)
        obs = random_shift(batch.obs, cfg.shift_pad, obs_key)
        next_obs = random_shift(batch.next_obs, cfg.shift_pad, next_key)
        params = state.params
        weight = batch.valid / jnp.maximum(batch.valid.sum(), 1)

        next_features = self.features(params["encoder"], next_obs)
        next_action = clipped_noise_action(self.actor.apply(params["actor"], next_features), std, cfg.std_clip,
                                           target_key)
        target_q = jnp.minimum(*self.critic.apply(state.target_critic, next_features, next_action))
        target = jax.lax.stop_gradient(batch.reward + batch.discount * target_q)

        def critic_loss(trained):
            features = self.features(trained["encoder"], obs)
            q1, q2 = self.critic.apply(trained["critic"], features, batch.action)
            return jnp.sum(weight * ((q1 - target) ** 2 + (q2 - target) ** 2)), (features, q1)

        trained = {"encoder": params["encoder"], "critic": params["critic"]}
        (c_loss, (features, q1)), grads = jax.value_and_grad(critic_loss, has_aux=True)(trained)
        updates, critic_opt_state = self.optimizer.update(grads, state.critic_opt_state, trained)
        trained = optax.apply_updates(trained, updates)

        features = jax.lax.stop_gradient(features)

        def actor_loss(actor):
            action = clipped_noise_action(self.actor.apply(actor, features), std, cfg.std_clip, actor_key)
            return -jnp.mean(jnp.minimum(*self.critic.apply(trained["critic"], features, action)))

        a_loss, grads = jax.value_and_grad(actor_loss)(params["actor"])
        updates, actor_opt_state = self.optimizer.update(grads, state.actor_opt_state, params["actor"])
        actor = optax.apply_updates(params["actor"], updates)
        target_critic = optax.incremental_update(trained["critic"], state.target_critic, cfg.target_tau)
        state = state.replace(params={**trained, "actor": actor}, target_critic=target_critic,
                              critic_opt_state=critic_opt_state, actor_opt_state=actor_opt_state)
        return state, {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": jnp.mean(q1)}

    # ---- one iteration ------------------------------------------------------------------------
    def iteration(self, state: DrQV2State) -> tuple[DrQV2State, dict[str, jax.Array]]:
        """One step of every env into the replay, then ``updates_per_iteration`` updates."""
        cfg = self.config
        key, act_key, random_key, update_key = jax.random.split(state.key, 4)
        env_steps = state.iteration * self.env_steps_per_iteration
        std = self.exploration_std(env_steps)
        pixels = state.env.pixels
        mean = self.actor.apply(state.params["actor"], self.features(state.params["encoder"], pixels))
        explore = jnp.clip(mean + std * jax.random.normal(act_key, mean.shape), -1.0, 1.0)
        uniform = jax.random.uniform(random_key, mean.shape, minval=-1.0, maxval=1.0)
        action = jnp.where(env_steps < cfg.seed_steps, uniform, explore)
        env = self.env.step(state.env, action)
        step = Step(frame=pixels[..., -3:], first=state.first, action=action, reward=env.reward,
                    terminated=env.terminated, truncated=env.truncated)
        replay = self.replay.add(state.replay, step)
        episode_return = state.episode_return + env.reward
        state = state.replace(env=env, first=env.done, replay=replay, key=key,
                              episode_return=jnp.where(env.done, 0.0, episode_return))

        def one_update(state, update_key):
            sample_key, step_key = jax.random.split(update_key)
            return self.update(state, self.replay.sample(state.replay, sample_key), std, step_key)

        def updates(state):
            return jax.lax.scan(one_update, state, jax.random.split(update_key, cfg.updates_per_iteration))

        def no_updates(state):
            nan = jnp.full((cfg.updates_per_iteration,), jnp.nan)
            return state, {"critic_loss": nan, "actor_loss": nan, "q_mean": nan}

        learning = (env_steps >= cfg.seed_steps) & self.replay.can_sample(replay)
        state, losses = jax.lax.cond(learning, updates, no_updates, state)
        losses = {name: jnp.mean(value) for name, value in losses.items()}
        healthy = ~learning | (jnp.isfinite(losses["critic_loss"]) & jnp.isfinite(losses["actor_loss"]))
        metrics = {**losses, "exploration_std": std, "healthy": healthy,
                   "finished_return_sum": jnp.sum(jnp.where(env.done, episode_return, 0.0)),
                   "finished_episodes": jnp.sum(env.done)}
        return state.replace(iteration=state.iteration + 1), metrics

    # ---- the agent's policy ------------------------------------------------------------------
    def policy(self, state: DrQV2State) -> dict:
        return {"encoder": state.params["encoder"], "actor": state.params["actor"]}

    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """The actor's mean action, no exploration noise."""
        return self.actor.apply(policy["actor"], self.features(policy["encoder"], observation["pixels"]))

    def abort_reason(self, metrics: dict) -> str:
        return (f"a NaN or infinite loss (critic {float(metrics['critic_loss']):.3g}, "
                f"actor {float(metrics['actor_loss']):.3g})")

"""What the off-policy pixel baselines (DrQ-v2, CURL) share: the collection round, the frame
replay and the update loop, behind the :class:`~dva.algorithms.base.Agent` protocol.

One :meth:`OffPolicyAgent.iteration` (jit it) takes one step in every env — uniform random
actions during the first ``seed_steps`` env steps, then the subclass's exploration — stores it in
the replay, and makes ``updates_per_iteration`` updates on sampled n-step batches (none before
the seed phase ends). A subclass supplies its networks (:meth:`init_learner`), its exploring
action (:meth:`explore`), one update (:meth:`update`) and its evaluation policy.
"""

from __future__ import annotations

import abc
import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from dva.envs import PixelObservations
from dva.replay import FrameReplay, NStepBatch, Step
from dva.tasks import EnvState


@dataclasses.dataclass(frozen=True)
class OffPolicyConfig:
    """What the shared loop needs; each algorithm's config adds its own fields and defaults."""

    num_envs: int = 16
    image_size: int = 84
    frame_stack: int = 3
    action_repeat: int = 2
    updates_per_iteration: int = 8  # agent updates per collection round (one step of every env)
    batch_size: int = 256
    n_step: int = 1
    gamma: float = 0.99
    feature_dim: int = 50
    hidden: tuple[int, ...] = (1024, 1024)
    replay_size: int = 100_000  # env steps kept, over all envs
    seed_steps: int = 4000  # env steps of uniform random actions before the first update
    shift_pad: int = 4  # random shifts of up to ± this many pixels
    iterations: int = 100_000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        for name in ("num_envs", "action_repeat", "updates_per_iteration", "batch_size", "n_step"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} = {getattr(self, name)!r} is not allowed; use an int ≥ 1")


class OffPolicyState(struct.PyTreeNode):
    """Everything one iteration reads and writes (a pytree: jittable, checkpointable)."""

    learner: struct.PyTreeNode  # the subclass's networks, targets and optimiser states
    env: EnvState
    first: jax.Array  # (N,) bool: the current observation starts an episode
    replay: object  # flashbax trajectory buffer state
    episode_return: jax.Array  # (N,)
    key: jax.Array
    iteration: jax.Array


class OffPolicyAgent(abc.ABC):
    """The shared collection and update loop; see the module docstring."""

    loss_names: tuple[str, ...]  # the update's metrics (NaN before the first update)
    prior_cost = (0.0, 0)

    def __init__(self, env: PixelObservations, config: OffPolicyConfig) -> None:
        if not env.has_pixels or env.num_envs != config.num_envs:
            raise ValueError(f"{type(self).__name__} needs an env wrapper that renders {config.num_envs} envs")
        self.env, self.task, self.config = env, env.task, config
        self.replay = FrameReplay(config.num_envs, config.replay_size, config.batch_size, config.frame_stack,
                                  config.n_step, config.gamma)

    @property
    def metric_names(self) -> tuple[str, ...]:
        return (*self.loss_names, "exploration")

    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.action_repeat

    @property
    def default_iterations(self) -> int:
        return self.config.iterations

    # ---- what each algorithm defines ----------------------------------------------------------
    @abc.abstractmethod
    def init_learner(self, key: jax.Array, pixels: jax.Array) -> struct.PyTreeNode:
        """Networks, targets and optimiser states, initialised on a batch of ``pixels``."""

    @abc.abstractmethod
    def explore(self, learner, pixels: jax.Array, env_steps: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The exploring actions in [−1, 1] for a batch of stacked frames, and a scalar that
        describes the exploration (logged as ``exploration``)."""

    @abc.abstractmethod
    def update(self, learner, batch: NStepBatch, env_steps: jax.Array, key: jax.Array):
        """One update on ``batch``: ``(learner, {name: scalar for name in loss_names})``."""

    # ---- the shared loop ----------------------------------------------------------------------
    def init(self, key: jax.Array) -> OffPolicyState:
        env_key, learner_key, key = jax.random.split(key, 3)
        env = self.env.reset(env_key)
        example = Step(frame=env.pixels[0, ..., -3:], first=jnp.ones((), bool), action=jnp.zeros(self.task.action_dim),
                       reward=jnp.zeros(()), terminated=jnp.zeros((), bool), truncated=jnp.zeros((), bool))
        return OffPolicyState(learner=self.init_learner(learner_key, env.pixels[:1]), env=env,
                              first=jnp.ones(self.config.num_envs, bool), replay=self.replay.init(example),
                              episode_return=jnp.zeros(self.config.num_envs), key=key,
                              iteration=jnp.zeros((), jnp.int32))

    def iteration(self, state: OffPolicyState) -> tuple[OffPolicyState, dict[str, jax.Array]]:
        """One step of every env into the replay, then ``updates_per_iteration`` updates."""
        cfg = self.config
        key, act_key, random_key, update_key = jax.random.split(state.key, 4)
        env_steps = state.iteration * self.env_steps_per_iteration
        pixels = state.env.pixels
        explored, exploration = self.explore(state.learner, pixels, env_steps, act_key)
        uniform = jax.random.uniform(random_key, explored.shape, minval=-1.0, maxval=1.0)
        action = jnp.where(env_steps < cfg.seed_steps, uniform, explored)
        env = self.env.step(state.env, action)
        replay = self.replay.add(state.replay, Step(frame=pixels[..., -3:], first=state.first, action=action,
                                                    reward=env.reward, terminated=env.terminated,
                                                    truncated=env.truncated))
        episode_return = state.episode_return + env.reward

        def one_update(learner, key):
            sample_key, step_key = jax.random.split(key)
            return self.update(learner, self.replay.sample(replay, sample_key), env_steps, step_key)

        def updates(learner):
            return jax.lax.scan(one_update, learner, jax.random.split(update_key, cfg.updates_per_iteration))

        def no_updates(learner):
            return learner, {name: jnp.full(cfg.updates_per_iteration, jnp.nan) for name in self.loss_names}

        learning = (env_steps >= cfg.seed_steps) & self.replay.can_sample(replay)
        learner, losses = jax.lax.cond(learning, updates, no_updates, state.learner)
        losses = {name: jnp.mean(value) for name, value in losses.items()}
        finite = jnp.all(jnp.array([jnp.isfinite(value) for value in losses.values()]))
        metrics = {**losses, "exploration": exploration, "healthy": ~learning | finite,
                   "finished_return_sum": jnp.sum(jnp.where(env.done, episode_return, 0.0)),
                   "finished_episodes": jnp.sum(env.done)}
        state = state.replace(learner=learner, env=env, first=env.done, replay=replay, key=key,
                              episode_return=jnp.where(env.done, 0.0, episode_return), iteration=state.iteration + 1)
        return state, metrics

    def abort_reason(self, metrics: dict) -> str:
        losses = ", ".join(f"{name} {float(metrics[name]):.3g}" for name in self.loss_names)
        return f"a NaN or infinite loss ({losses})"

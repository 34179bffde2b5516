"""What the off-policy pixel baselines (DrQ-v2, CURL) share: the collection round, the frame
replay and the update loop, behind the :class:`~dva.algorithms.base.Agent` protocol.

:meth:`OffPolicyAgent.init` fills the replay with ``seed_steps`` env steps of uniform random
actions; one :meth:`OffPolicyAgent.iteration` (jit it) then takes one exploring step in every env,
stores it in the replay, and makes ``updates_per_iteration`` updates on sampled n-step batches. A subclass
supplies its networks (:meth:`init_learner`), its exploring
action (:meth:`explore`), one update (:meth:`update`) and its evaluation policy.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.base import Metrics, all_finite, nan_loss_reason
from dva.algorithms.replay import FrameReplay, NStepBatch, SequenceReplay, Step
from dva.envs.observations import Env
from dva.errors import DvaUsageError, check_numbers
from dva.networks import PixelEncoder
from dva.tasks.base import EnvState


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
    reward_scale: float = 1.0  # rewards are multiplied by this in the replay (what the critic learns)
    feature_dim: int = 50
    hidden: tuple[int, ...] = (1024, 1024)
    replay_size: int = 100_000  # env steps kept, over all envs
    seed_steps: int = 4000  # env steps of uniform random actions before the first update
    shift_pad: int = 4  # random shifts of up to ± this many pixels
    iterations: int = 100_000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_envs", "action_repeat", "updates_per_iteration", "batch_size", "n_step"):
            if getattr(self, name) < 1:
                raise DvaUsageError(f"{name} = {getattr(self, name)!r} is not allowed; use an int ≥ 1")


class OffPolicyState(struct.PyTreeNode):
    """Everything one iteration reads and writes (a pytree: jittable, checkpointable)."""

    learner: struct.PyTreeNode  # the subclass's networks, targets and optimiser states
    env: EnvState
    first: jax.Array  # (N,) bool: the current observation starts an episode
    replay: object  # flashbax trajectory buffer state
    episode_return: jax.Array  # (N,)
    key: jax.Array
    iteration: jax.Array


def newest_frame(env: EnvState) -> jax.Array:
    """What a pixel agent's replay stores of an observation: its newest frame."""
    return env.frames[..., -3:]


def collect_into_replay(
    env: Env,
    replay: SequenceReplay,
    state,
    action: jax.Array,
    reward_scale: float = 1.0,
    stored=newest_frame,
    keep_state: bool = False,
):
    """One step of every env with ``action``, stored in ``replay`` (``stored`` of the observation
    the action was taken in, with ``keep_state`` its state vector too, the reward ×
    ``reward_scale``). ``state`` is any agent
    state with ``env``, ``first``, ``replay`` and ``episode_return`` fields; returns it updated and
    the returns of the episodes that just ended (0 elsewhere; unscaled)."""
    next_env = env.step(state.env, action)
    replay_state = replay.add(
        state.replay,
        Step(
            frame=stored(state.env),
            first=state.first,
            action=action,
            reward=reward_scale * next_env.reward,
            terminated=next_env.terminated,
            truncated=next_env.truncated,
            state=state.env.obs if keep_state else None,
        ),
    )
    episode_return = state.episode_return + next_env.reward
    state = state.replace(
        env=next_env,
        first=next_env.done,
        replay=replay_state,
        episode_return=jnp.where(next_env.done, 0.0, episode_return),
    )
    return state, jnp.where(next_env.done, episode_return, 0.0)


def empty_step(observed: jax.Array, action_dim: int, state_dim: int = 0) -> Step:
    """A step shaped like one env's ``observed`` (no leading axis), with a state vector of
    ``state_dim`` entries if > 0: what a replay's ``init`` needs."""
    return Step(
        frame=observed,
        first=jnp.ones((), bool),
        action=jnp.zeros(action_dim),
        reward=jnp.zeros(()),
        terminated=jnp.zeros((), bool),
        truncated=jnp.zeros((), bool),
        state=jnp.zeros(state_dim) if state_dim else None,
    )


def seed_rounds(seed_steps: int, steps_per_round: int, sequence_length: int) -> int:
    """Collection rounds of uniform random actions before learning: ``seed_steps`` env steps, and
    at least one sampled sequence per env."""
    return max(-(-seed_steps // steps_per_round), sequence_length)


def seed_replay(
    env: Env,
    replay: SequenceReplay,
    state,
    rounds: int,
    key: jax.Array,
    reward_scale: float = 1.0,
    stored=newest_frame,
    keep_state: bool = False,
):
    """``rounds`` steps of every env with uniform random actions, stored as
    :func:`collect_into_replay` stores them (the seed phase, run by an agent's ``init``: the
    iteration then stays free of a ``lax.cond`` around its updates)."""

    def seed_round(state, round_key):
        shape = (env.num_envs, env.task.action_dim)
        uniform = jax.random.uniform(round_key, shape, minval=-1.0, maxval=1.0)
        return collect_into_replay(env, replay, state, uniform, reward_scale, stored, keep_state)[0], None

    return jax.lax.scan(seed_round, state, jax.random.split(key, rounds))[0]


class OffPolicyAgent(abc.ABC):
    """The shared collection and update loop; see the module docstring."""

    loss_names: tuple[str, ...]  # the update's metrics
    optimizer: optax.GradientTransformation  # the critic's (and encoder's), made by the agent

    def __init__(self, env: Env, config: OffPolicyConfig) -> None:
        if not env.has_pixels or env.num_envs != config.num_envs:
            raise DvaUsageError(f"{type(self).__name__} needs an env wrapper that renders {config.num_envs} envs")
        self.env, self.task, self.config = env, env.task, config
        self.encoder = PixelEncoder()  # every algorithm's params hold its weights under "encoder"
        self.replay = FrameReplay(
            config.num_envs, config.replay_size, config.batch_size, config.frame_stack, config.n_step, config.gamma
        )

    batch_fields = ()  # one device: the replay is not split
    keeps_state = False  # whether the replay keeps each observation's state vector (a privileged agent)

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

    def features(self, encoder: dict, pixels: jax.Array) -> jax.Array:
        return self.encoder.apply(encoder, pixels)

    def policy(self, state: OffPolicyState) -> dict:
        """The encoder and actor (what ``act`` needs)."""
        return {"encoder": state.learner.params["encoder"], "actor": state.learner.params["actor"]}

    def fit_critic(
        self,
        params: dict,
        opt_state,
        obs: jax.Array,
        action: jax.Array,
        target: jax.Array,
        weight: jax.Array,
        auxiliary: Callable[[dict, jax.Array], jax.Array] | None = None,
    ):
        """One clipped double-Q regression step of the encoder and critic towards ``target``
        (both heads, per-sample ``weight``), with the subclass's ``features``, ``critic`` and
        ``optimizer``; ``auxiliary(params, features)``, a loss added to it, trains
        ``params["state_head"]`` too. Returns the new ``{"encoder", "critic"(, "state_head")}``, the
        optimiser state, the critic's loss, the (detached) features of ``obs``, Q₁ and the auxiliary
        loss (0 without one)."""

        def loss(trained):
            features = self.features(trained["encoder"], obs)
            q1, q2 = self.critic.apply(trained["critic"], features, action)
            critic_loss = jnp.sum(weight * ((q1 - target) ** 2 + (q2 - target) ** 2))
            extra = jnp.zeros(()) if auxiliary is None else auxiliary(trained, features)
            return critic_loss + extra, (critic_loss, features, q1, extra)

        trained = {key: params[key] for key in ("encoder", "critic", "state_head") if key in params}
        (_, (value, features, q1, extra)), grads = jax.value_and_grad(loss, has_aux=True)(trained)
        updates, opt_state = self.optimizer.update(grads, opt_state, trained)
        return optax.apply_updates(trained, updates), opt_state, value, jax.lax.stop_gradient(features), q1, extra

    # ---- the shared loop ----------------------------------------------------------------------
    @property
    def seed_rounds(self) -> int:
        return seed_rounds(self.config.seed_steps, self.env_steps_per_iteration, self.replay.sequence_length)

    @property
    def prior_cost(self) -> tuple[float, int]:
        """The seed phase's env steps, taken in :meth:`init` (its time is in the run's clock)."""
        return 0.0, self.seed_rounds * self.env_steps_per_iteration

    def init(self, key: jax.Array) -> OffPolicyState:
        """Fresh networks and envs, and a replay filled by the seed phase (uniform random actions)."""
        env_key, learner_key, seed_key, key = jax.random.split(key, 4)
        env = self.env.reset(env_key)
        state = OffPolicyState(
            learner=self.init_learner(learner_key, env.frames[:1]),
            env=env,
            first=jnp.ones(self.config.num_envs, bool),
            replay=self.replay.init(
                empty_step(newest_frame(env)[0], self.task.action_dim, self.task.obs_dim * self.keeps_state)
            ),
            episode_return=jnp.zeros(self.config.num_envs),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )
        cfg = self.config
        return seed_replay(
            self.env, self.replay, state, self.seed_rounds, seed_key, cfg.reward_scale, keep_state=self.keeps_state
        )

    def collect(self, state: OffPolicyState, action: jax.Array) -> tuple[OffPolicyState, jax.Array]:
        """:func:`collect_into_replay` with this agent's env, replay and reward scale."""
        return collect_into_replay(
            self.env, self.replay, state, action, self.config.reward_scale, keep_state=self.keeps_state
        )

    def iteration(self, state: OffPolicyState) -> tuple[OffPolicyState, Metrics]:
        """One exploring step of every env into the replay, then ``updates_per_iteration`` updates."""
        cfg = self.config
        key, act_key, update_key = jax.random.split(state.key, 3)
        env_steps = self.prior_cost[1] + state.iteration * self.env_steps_per_iteration
        action, exploration = self.explore(state.learner, state.env.frames, env_steps, act_key)
        state, finished = self.collect(state, action)

        def one_update(learner, key):
            sample_key, step_key = jax.random.split(key)
            return self.update(learner, self.replay.sample(state.replay, sample_key), env_steps, step_key)

        learner, losses = jax.lax.scan(
            one_update, state.learner, jax.random.split(update_key, cfg.updates_per_iteration)
        )
        losses = {name: jnp.mean(losses[name]) for name in self.loss_names}
        logged = {**losses, "exploration": exploration}
        metrics = Metrics(all_finite(losses), finished.sum(), state.env.done.sum(), logged)
        return state.replace(learner=learner, key=key, iteration=state.iteration + 1), metrics

    def abort_reason(self, logged: dict) -> str:
        return nan_loss_reason(logged, self.loss_names)

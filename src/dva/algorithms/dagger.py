"""State-to-visual DAgger (Mu et al. 2025): a pixel student with D.Va's architecture
imitates a SHAC teacher trained on the state.

One :meth:`DAgger.iteration` (jit it) rolls out ``horizon`` steps over ``num_envs`` envs — each
env follows the teacher with probability ``teacher_fraction · teacher_decay^iteration`` per step,
else the student — relabels every visited observation with the teacher's deterministic action,
adds the (frames, action) pairs to a replay of at most ``replay_size`` and takes
``updates_per_iteration`` Adam steps on the behaviour-cloning loss ``‖tanh μ_student(o) − a*‖²``
over sampled batches. Training stops once the student drives (the teacher's share is at most
``stop_teacher_fraction``) and the cloning loss on the states just visited, measured before they
are trained on and averaged over iterations (an EMA with ``stop_loss_decay``), is below
``stop_bc_loss`` — on the replay's own samples the loss is near 0 after the first iteration (a few
hundred teacher-driven frames), so it cannot be the criterion, and one iteration's fresh loss is
too noisy: on Cart-pole it swings between 0.1 and 2 from one iteration to the next, and a single
dip below 0.1 stopped a student at 462 whose peers went on to ≈ 1900.

The teacher is a finished ``dva train --algo shac`` run (``teacher``); without one, ``dva train
--algo dagger`` trains it first (``teacher_minutes``) and the student's logged wall-clock and
env steps continue from the teacher's, so comparisons include its cost.
"""

from __future__ import annotations

import dataclasses

import flashbax
import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.base import Metrics, TeacherRun
from dva.envs.observations import DifferentiableEnv, Observation
from dva.errors import DvaUsageError, check_numbers
from dva.networks import Actor
from dva.tasks.base import EnvState


@dataclasses.dataclass(frozen=True)
class DAggerConfig:
    """Hyperparameters (the paper's DAgger settings; the student's networks are D.Va's for the task)."""

    teacher: str | None = None  # run directory of a SHAC teacher on state (None: train one first)
    teacher_minutes: float = 20.0  # its training budget when none is given
    num_envs: int = 64
    horizon: int = 32
    image_size: int = 84
    frame_stack: int = 3
    lr: float = 2e-3
    betas: tuple[float, float] = (0.7, 0.95)
    batch_size: int = 128
    updates_per_iteration: int = 16
    replay_size: int = 100_000  # observations kept
    teacher_fraction: float = 1.0  # probability of acting with the teacher at iteration 0 …
    teacher_decay: float = 0.9  # … times this per iteration
    stop_bc_loss: float = 0.1
    stop_teacher_fraction: float = 0.1  # the stop rule applies once the teacher acts this rarely
    stop_loss_decay: float = 0.9  # EMA of the fresh cloning loss the stop rule reads (≈ 10 iterations)
    trunk: int = 64
    actor_hidden: tuple[int, ...] = (64, 64)
    iterations: int = 2000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        check_numbers(self)
        if not 0.0 <= self.stop_loss_decay < 1.0:
            raise DvaUsageError(f"stop_loss_decay = {self.stop_loss_decay!r} is not allowed; use a number in [0, 1)")


class DAggerState(struct.PyTreeNode):
    """Everything one iteration reads and writes (a pytree: jittable, checkpointable)."""

    student: dict
    opt_state: optax.OptState
    env: EnvState
    replay: object  # flashbax item buffer state: {"pixels", "action"}
    episode_return: jax.Array
    fresh_loss_average: jax.Array  # EMA of the fresh cloning loss (the stop rule's input)
    key: jax.Array
    iteration: jax.Array


class DAgger:
    """The DAgger agent (an :class:`~dva.algorithms.base.Agent`); see the module docstring.

    ``teacher`` is the teacher's agent and ``teacher_policy`` its :meth:`policy` parameters.
    """

    metric_names = ("bc_loss", "fresh_bc_loss", "fresh_bc_loss_average", "teacher_fraction")
    batch_fields = ()  # one device: its replay is not split

    def __init__(
        self,
        env: DifferentiableEnv,
        config: DAggerConfig,
        teacher,
        teacher_policy,
        teacher_cost: tuple[float, int] = (0.0, 0),
    ) -> None:
        if not env.has_pixels or env.num_envs != config.num_envs:
            raise DvaUsageError(f"DAgger needs an env wrapper that renders {config.num_envs} envs")
        if teacher.task.name != env.task.name:
            raise DvaUsageError(f"the teacher was trained on {teacher.task.name!r}, the student runs {env.task.name!r}")
        self.env, self.task, self.config = env, env.task, config
        self.teacher, self.teacher_policy, self.prior_cost = teacher, teacher_policy, teacher_cost
        self.student = Actor(self.task.action_dim, config.actor_hidden, pixels=True, trunk=config.trunk)
        self.optimizer = optax.adam(config.lr, b1=config.betas[0], b2=config.betas[1])
        self.replay = flashbax.make_item_buffer(
            max_length=config.replay_size,
            min_length=config.batch_size,
            sample_batch_size=config.batch_size,
            add_batches=True,
        )

    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.horizon

    @property
    def default_iterations(self) -> int:
        return self.config.iterations

    def init(self, key: jax.Array) -> DAggerState:
        env_key, student_key, key = jax.random.split(key, 3)
        env = self.env.reset(env_key)
        student = self.student.init(student_key, env.frames[:1])
        example = {"pixels": env.frames[0], "action": jnp.zeros(self.task.action_dim)}
        return DAggerState(
            student=student,
            opt_state=self.optimizer.init(student),
            env=env,
            replay=self.replay.init(example),
            episode_return=jnp.zeros(self.config.num_envs),
            fresh_loss_average=jnp.zeros(()),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def teacher_action(self, observation: Observation) -> jax.Array:
        return jax.lax.stop_gradient(self.teacher.act(self.teacher_policy, observation))

    def bc_loss(self, student: dict, pixels: jax.Array, action: jax.Array) -> jax.Array:
        """Mean over the batch of ``‖tanh μ_student(pixels) − action‖²``."""
        mean, _ = self.student.apply(student, pixels)
        return jnp.mean(jnp.sum((jnp.tanh(mean) - action) ** 2, axis=-1))

    def iteration(self, state: DAggerState) -> tuple[DAggerState, Metrics]:
        """Roll out the mixture, relabel with the teacher, aggregate, fit the student."""
        cfg = self.config
        key, mix_key, update_key = jax.random.split(state.key, 3)
        fraction = cfg.teacher_fraction * cfg.teacher_decay ** state.iteration.astype(jnp.float32)

        def step(carry, step_key):
            env, episode_return = carry
            observation = self.env.observe(env)
            label = self.teacher_action(observation)
            use_teacher = jax.random.uniform(step_key, (cfg.num_envs, 1)) < fraction
            action = jnp.where(use_teacher, label, self.act(state.student, observation))
            env = self.env.step(env, action)
            episode_return = episode_return + env.reward
            finished = jnp.where(env.done, episode_return, 0.0)
            return (env, jnp.where(env.done, 0.0, episode_return)), (observation["pixels"], label, finished, env.done)

        (env, episode_return), (pixels, labels, finished, done) = jax.lax.scan(
            step, (state.env, state.episode_return), jax.random.split(mix_key, cfg.horizon)
        )
        flat = lambda x: x.reshape((-1,) + x.shape[2:])
        replay = self.replay.add(state.replay, {"pixels": flat(pixels), "action": flat(labels)})
        fresh_bc_loss = self.bc_loss(state.student, flat(pixels), flat(labels))  # held out: not yet trained on
        average = jnp.where(
            state.iteration == 0,
            fresh_bc_loss,  # the EMA starts at the first value
            cfg.stop_loss_decay * state.fresh_loss_average + (1.0 - cfg.stop_loss_decay) * fresh_bc_loss,
        )

        def update(carry, key):
            student, opt_state = carry
            batch = self.replay.sample(replay, key).experience
            loss, grads = jax.value_and_grad(self.bc_loss)(student, batch["pixels"], batch["action"])
            updates, opt_state = self.optimizer.update(grads, opt_state, student)
            return (optax.apply_updates(student, updates), opt_state), loss

        (student, opt_state), losses = jax.lax.scan(
            update, (state.student, state.opt_state), jax.random.split(update_key, cfg.updates_per_iteration)
        )
        bc_loss = losses[-1]
        logged = {
            "bc_loss": bc_loss,
            "fresh_bc_loss": fresh_bc_loss,
            "fresh_bc_loss_average": average,
            "teacher_fraction": fraction,
        }
        stop = (average < cfg.stop_bc_loss) & (fraction <= cfg.stop_teacher_fraction)
        metrics = Metrics(jnp.isfinite(bc_loss), finished.sum(), done.sum(), logged, stop)
        return state.replace(
            student=student,
            opt_state=opt_state,
            env=env,
            replay=replay,
            episode_return=episode_return,
            fresh_loss_average=average,
            key=key,
            iteration=state.iteration + 1,
        ), metrics

    # ---- the agent's policy ------------------------------------------------------------------
    def policy(self, state: DAggerState) -> dict:
        return state.student

    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """The student's deterministic action ``tanh(μ)`` from the frames."""
        mean, _ = self.student.apply(policy, observation["pixels"])
        return jnp.tanh(mean)

    def abort_reason(self, logged: dict) -> str:
        return f"behaviour-cloning loss {float(logged['bc_loss']):.3g} is NaN or infinite"


def make_dagger(env: DifferentiableEnv, config: DAggerConfig, teacher: TeacherRun) -> DAgger:
    """The student of ``teacher``, which must act on the state (SHAC or DPG on the state)."""
    if getattr(teacher.agent.config, "observation", None) != "state":
        raise DvaUsageError(
            f"the teacher {config.teacher} is a {teacher.algo!r} run; DAgger needs a teacher on the state (--algo shac)"
        )
    return DAgger(env, config, teacher.agent, teacher.policy, teacher.cost)

"""Short-horizon actor-critic through the differentiable simulator — one implementation for

* **D.Va**: ``observation="pixels"``, ``gradient="decoupled"`` (pixels enter via stop_gradient),
* **SHAC**: ``observation="state"``, ``gradient="full"``,
* **DPG on state** (paper Fig 13): ``observation="state"``, ``gradient="decoupled"``,
* **visual SHAC** (the paper's baseline): ``observation="pixels"``, ``gradient="full"``, pixels
  from the differentiable :class:`~dva.envs.soft_rendering.SoftRenderer`.

One :meth:`SHAC.iteration` (jit it) rolls the policy out for ``horizon`` steps over ``num_envs``
environments (physics, and the rendering and frame stack of :class:`~dva.envs.observations.PixelObservations`),
differentiates the actor loss
``L = −1/(N h) Σ [Σ_t γ^t r_t + γ^h V'(s_h)]`` through the dynamics, fits the critic to TD-λ
targets for ``critic_iterations × critic_minibatches`` steps and updates the target critic.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.base import Metrics
from dva.envs.observations import DifferentiableEnv, Observation
from dva.errors import DvaUsageError, check_numbers
from dva.networks import NETWORK_STYLES, Actor, Critic, NetworkStyle, RunningStats
from dva.tasks.base import EnvState


@dataclasses.dataclass(frozen=True)
class SHACConfig:
    """Hyperparameters (defaults: Cart-pole's row of the paper's Table 7)."""

    observation: Literal["pixels", "state"] = "pixels"
    gradient: Literal["decoupled", "full"] = "decoupled"
    num_envs: int = 64
    horizon: int = 32
    gamma: float = 0.99
    lam: float = 0.95
    actor_lr: float = 2e-3
    critic_lr: float = 2e-4
    final_lr: float = 1e-5
    betas: tuple[float, float] = (0.7, 0.95)
    clip_grad_norm: float = 1.0  # each update's gradients are scaled to at most this global norm
    abort_grad_norm: float = 1e8  # an actor gradient norm above this (or NaN) stops training (ref. code)
    state_grad_clip: float | None = None
    """Per-env bound on the norm of the gradient w.r.t. (qpos, qvel) as it flows back from one
    step to the one before (AHAC's per-step clipping), in units of one env's window return
    (the loss is their mean over N·h, so the bound on the loss's cotangent is this ÷ N·h);
    None: exact gradients."""
    pre_tanh_penalty: float = 0.0
    """Weight of ``mean(u²)`` over the taken pre-tanh actions ``u = μ + σε``, added to the actor
    loss (as rlkit's SAC ``policy_pre_activation_weight``). Where |μ| ≫ 1 the tanh is flat: the
    return's gradient does not reach μ and the exploration noise does not reach the env, so a
    policy pinned at its action limits stays there (D.Va's Ant standing still); this pulls μ back.
    Its share of the gradient on log σ (≈ 2·weight·σ²) is a small push towards less noise. 0: the
    paper's loss."""
    init_log_std: float = -1.0
    """The actor's state-independent log σ of the pre-tanh action at initialisation (learned after;
    SHAC's −1). Larger: more exploration noise at the start, so that a pixel actor sees frames that
    differ from step to step before its policy settles into a posture."""
    actor_backward_chunk: int = 1
    """Decoupled gradients only: c ≥ 1 differentiates the actor (the encoder above all) c steps
    (c·N observations) at a time inside a scan, recomputing their forward pass, and adds up the
    gradients — one chunk's activations in memory; 0 reuses the backward passes the rollout kept
    for every step instead (no recomputed forward, all h steps' activations in memory; for
    hardware where the recompute costs more than it saves). Chunks of 1 step have the least
    memory (docs/development.md, "CPU speed notes")."""
    state_prediction: float = 0.0
    """D.Va only: weight of an auxiliary loss, added to the actor's, that makes the actor's pixel
    encoder predict the normalised simulator state (the critic's input) through a linear head on
    its trunk: the mean over steps, envs and state dimensions of the squared error. It trains the
    encoder on what the frames show without the return's gradient passing through the pixels.
    0: the paper's loss."""
    use_critic: bool = True
    """False: the paper's value ablation — the window's end bootstraps nothing (V = 0) and no
    critic is trained."""
    target_alpha: float = 0.2
    critic_iterations: int = 16
    critic_minibatches: int = 4
    trunk: int = 64
    actor_hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (64, 64)
    image_size: int = 84
    frame_stack: int = 3
    networks: NetworkStyle = "flax"
    """How the actor's and critic's layers are ordered and initialised: "flax" (Dense → LayerNorm →
    ELU, Flax's default initialisers) or "authors" (as the paper's authors' PyTorch code: Linear →
    ELU → LayerNorm, orthogonal convolutions, trunk and critic, PyTorch's default for the actor's
    MLP). The same shapes and parameter names either way."""
    lr_decay_iterations: int = 4000
    """Iterations over which the learning rates decay linearly to ``final_lr`` (then stay there);
    also the run's length when neither an iteration count nor a time budget is given."""

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_envs", "horizon", "critic_iterations", "critic_minibatches", "image_size", "frame_stack"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise DvaUsageError(f"{name} = {value!r} is not allowed; use a whole number > 0")
        if not self.lr_decay_iterations > 0:
            raise DvaUsageError(f"lr_decay_iterations = {self.lr_decay_iterations!r} is not allowed; use a number > 0")
        if self.observation not in ("pixels", "state"):
            raise DvaUsageError(f"observation {self.observation!r} is not allowed; use 'pixels' or 'state'")
        if self.gradient not in ("decoupled", "full"):
            raise DvaUsageError(f"gradient {self.gradient!r} is not allowed; use 'decoupled' or 'full'")
        if self.networks not in NETWORK_STYLES:
            raise DvaUsageError(f"networks {self.networks!r} is not allowed; use one of {', '.join(NETWORK_STYLES)}")
        if self.actor_backward_chunk is None:  # run.json of earlier versions: the kept passes
            object.__setattr__(self, "actor_backward_chunk", 0)
        chunk = self.actor_backward_chunk
        if not isinstance(chunk, int) or chunk < 0 or (chunk and self.horizon % chunk):
            raise DvaUsageError(
                f"actor_backward_chunk = {chunk!r} is not allowed; use 0 (the kept backward passes) or a divisor of "
                f"horizon = {self.horizon}"
            )
        if self.state_prediction < 0 or (
            self.state_prediction and (self.observation, self.gradient) != ("pixels", "decoupled")
        ):
            raise DvaUsageError(
                f"state_prediction = {self.state_prediction!r} is not allowed here; use 0, or a positive weight with "
                "observation='pixels' and gradient='decoupled' (D.Va)"
            )
        if (self.num_envs * self.horizon) % self.critic_minibatches:
            raise DvaUsageError(
                f"num_envs × horizon = {self.num_envs * self.horizon} must divide into "
                f"{self.critic_minibatches} critic minibatches"
            )


class TrainState(struct.PyTreeNode):
    """Everything one iteration reads and writes (a pytree: jittable, checkpointable)."""

    actor_params: dict
    critic_params: dict
    target_critic_params: dict
    actor_opt_state: optax.OptState
    critic_opt_state: optax.OptState
    obs_stats: RunningStats  # running mean/std of the state observation
    env: EnvState  # with its frame stack in env.pixels (uint8; float from SoftRenderer; (N, 0) for state)
    episode_return: jax.Array  # (N,) undiscounted return of the running episodes
    key: jax.Array
    iteration: jax.Array


class Trajectory(struct.PyTreeNode):
    """What the critic learns from, one entry per step (h, N, ...); no gradients attached."""

    critic_obs: jax.Array  # normalised state at the start of the step
    reward: jax.Array
    next_value: jax.Array  # V'(state reached), 0 where the episode terminated
    boundary: jax.Array  # the episode or the horizon ends after this step (no λ-mixing past it)


class StepRecord(NamedTuple):
    """What one step of :meth:`SHAC.rollout`'s scan records (stacked to (h, N, ...) by the scan)."""

    ended: jax.Array  # discounted return (+ bootstrap) of an episode that ended at this step, else 0
    critic_obs: jax.Array  # normalised state at the start of the step (the critic's input)
    reward: jax.Array
    next_value: jax.Array  # V'(state reached), 0 where the episode terminated
    done: jax.Array  # the episode ended at this step
    finished_return: jax.Array  # undiscounted return of the episode that ended here, else 0
    visited_obs: jax.Array  # raw state reached, for the observation statistics
    observation: jax.Array  # the actor's input
    pre_tanh: jax.Array  # the action taken, before its tanh
    actor_vjp: Any  # the actor's kept backward pass (decoupled, chunk 0), else None


class Rollout(NamedTuple):
    """The by-products of :meth:`SHAC.rollout` beside its loss."""

    env: EnvState  # the environments after the window
    episode_return: jax.Array  # (N,) running return of each env's current episode
    trajectory: Trajectory  # what the critic learns from
    visited_obs: jax.Array  # (h, N, obs_dim) raw states, for the observation statistics
    stats: dict[str, Any]  # the window's logged numbers (finished episodes' returns, …)
    taken: dict[str, Any]  # per step: the actor's inputs, pre-tanh actions, backward passes, states


class SHAC:
    """The trainer (an :class:`~dva.algorithms.base.Agent`); see the module docstring. Pixel
    observations need ``env`` to render them."""

    prior_cost = (0.0, 0)
    batch_fields = ("env", "episode_return")

    def __init__(self, env: DifferentiableEnv, config: SHACConfig) -> None:
        if env.num_envs != config.num_envs:
            raise DvaUsageError(f"the env wrapper runs {env.num_envs} envs; config.num_envs is {config.num_envs}")
        if config.observation == "pixels":
            if not env.has_pixels:
                raise DvaUsageError("pixel observations need an env wrapper with a renderer")
            if config.gradient == "full" and not env.differentiable_pixels:
                raise DvaUsageError(
                    "gradient 'full' through pixels needs a differentiable renderer (SoftRenderer); "
                    "the Warp renderer is not — use gradient='decoupled' (D.Va)"
                )
        self.env, self.task, self.config = env, env.task, config
        self.actor = Actor(
            self.task.action_dim,
            config.actor_hidden,
            pixels=config.observation == "pixels",
            trunk=config.trunk,
            init_log_std=config.init_log_std,
            state_dim=self.task.obs_dim if config.state_prediction else 0,
            style=config.networks,
        )
        self.critic = Critic(config.critic_hidden, style=config.networks)

        def optimizer(lr: float, steps: int) -> optax.GradientTransformation:
            """Adam after global-norm clipping, learning rate decayed linearly over ``steps``."""
            schedule = optax.linear_schedule(lr, config.final_lr, steps)
            return optax.chain(
                optax.clip_by_global_norm(config.clip_grad_norm),
                optax.adam(schedule, b1=config.betas[0], b2=config.betas[1]),
            )

        self.actor_opt = optimizer(config.actor_lr, config.lr_decay_iterations)
        # The critic takes critic_iterations × critic_minibatches steps per iteration.
        self.critic_opt = optimizer(
            config.critic_lr, config.lr_decay_iterations * config.critic_iterations * config.critic_minibatches
        )

    @property
    def metric_names(self) -> tuple[str, ...]:
        extra = ("state_prediction_loss",) if self.config.state_prediction else ()
        return ("actor_loss", "actor_grad_norm", "critic_loss", *extra)

    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.horizon

    @property
    def default_iterations(self) -> int:
        return self.config.lr_decay_iterations

    # ---- set-up -------------------------------------------------------------------------------
    def init(self, key: jax.Array) -> TrainState:
        """Fresh networks, optimisers and environments."""
        env_key, actor_key, critic_key, key = jax.random.split(key, 4)
        env = self.env.reset(env_key)
        observation = self.observe(env, RunningStats.create(self.task.obs_dim))
        actor_params = self.actor.init(actor_key, observation, predict_state=bool(self.config.state_prediction))
        critic_params = self.critic.init(critic_key, env.obs)
        return TrainState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=critic_params,
            actor_opt_state=self.actor_opt.init(actor_params),
            critic_opt_state=self.critic_opt.init(critic_params),
            obs_stats=RunningStats.create(self.task.obs_dim),
            env=env,
            episode_return=jnp.zeros(self.config.num_envs),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def observe(self, env: EnvState, stats: RunningStats) -> jax.Array:
        """What the actor sees: the stacked frames, or the normalised state."""
        return self.actor_input(self.env.observe(env), stats)

    def actor_input(self, observation: Observation, stats: RunningStats) -> jax.Array:
        """The actor's input from an observation: its pixels, or its normalised state."""
        if self.config.observation == "pixels":
            return observation["pixels"]
        return stats.normalize(observation["state"])

    # ---- the policy ---------------------------------------------------------------------------
    def pre_tanh_action(self, actor_params: dict, observation: jax.Array, noise: jax.Array | None) -> jax.Array:
        """``μ + σ ⊙ ε`` (reparameterised); ``μ`` when ``noise`` is None. The env gets its tanh."""
        mean, log_std = self.actor.apply(actor_params, observation)
        return mean if noise is None else mean + jnp.exp(log_std) * noise

    def actor_outputs(self, actor_params: dict, observation: jax.Array, noise: jax.Array, state: jax.Array):
        """``(pre-tanh action, squared error of the state prediction summed over its entries)``;
        the error is 0 without the auxiliary loss."""
        if not self.config.state_prediction:
            return self.pre_tanh_action(actor_params, observation, noise), jnp.zeros(())
        mean, log_std, predicted = self.actor.apply(actor_params, observation, predict_state=True)
        return mean + jnp.exp(log_std) * noise, jnp.sum((predicted - state) ** 2)

    def rollout(self, actor_params: dict, train: TrainState, noise: jax.Array, action_offset: jax.Array | None = None):
        """Roll the policy out for ``len(noise)`` steps; returns the actor loss and its by-products.

        Differentiable with respect to ``actor_params``: the gradient flows through the physics,
        the rewards and the target critic's value of the last state; with ``gradient="decoupled"``
        it does not flow through the observation. ``action_offset`` (h, N, A), added to the
        pre-tanh actions, exposes the gradient with respect to the open-loop actions.
        """
        cfg = self.config

        def value(obs: jax.Array) -> jax.Array:
            if not cfg.use_critic:
                return jnp.zeros(obs.shape[:-1])
            return self.critic.apply(train.target_critic_params, train.obs_stats.normalize(obs))

        def step(carry, inputs):
            env, discount, discounted_sum, episode_return = carry
            eps, offset = inputs
            observation = self.observe(env, train.obs_stats)
            if cfg.gradient == "decoupled":
                observation = jax.lax.stop_gradient(observation)
            critic_obs = jax.lax.stop_gradient(train.obs_stats.normalize(env.obs))
            if cfg.gradient == "decoupled" and cfg.actor_backward_chunk == 0:  # kept for actor_backward
                (pre_tanh, error), vjp = jax.vjp(
                    lambda p: self.actor_outputs(p, observation, eps, critic_obs), actor_params
                )
                actor_vjp = (vjp, error)
            else:
                pre_tanh, actor_vjp = self.pre_tanh_action(actor_params, observation, eps), None
            pre_tanh = pre_tanh + offset
            if cfg.state_grad_clip is not None:
                qpos, qvel = clip_gradient_per_env(
                    (env.data.qpos, env.data.qvel), cfg.state_grad_clip / (cfg.num_envs * len(noise))
                )
                env = env.replace(data=env.data.replace(qpos=qpos, qvel=qvel))
            env = self.env.step(env, jnp.tanh(pre_tanh))
            next_value = jnp.where(env.terminated, 0.0, value(env.final_obs))
            discounted_sum = discounted_sum + discount * env.reward
            discount = discount * cfg.gamma
            # An episode that ends inside the window adds its discounted return (+ bootstrap).
            ended = jnp.where(env.done, discounted_sum + discount * next_value, 0.0)
            episode_return = episode_return + jax.lax.stop_gradient(env.reward)
            finished_return = jnp.where(env.done, episode_return, 0.0)
            carry = (
                env,
                jnp.where(env.done, 1.0, discount),
                jnp.where(env.done, 0.0, discounted_sum),
                jnp.where(env.done, 0.0, episode_return),
            )
            record = StepRecord(
                ended=ended,
                critic_obs=critic_obs,
                reward=jax.lax.stop_gradient(env.reward),
                next_value=jax.lax.stop_gradient(next_value),
                done=env.done,
                finished_return=finished_return,
                visited_obs=env.obs,
                observation=observation,
                pre_tanh=pre_tanh,
                actor_vjp=actor_vjp,
            )
            return carry, record

        num_envs = cfg.num_envs
        carry = (train.env, jnp.ones(num_envs), jnp.zeros(num_envs), train.episode_return)
        offsets = jnp.zeros_like(noise) if action_offset is None else action_offset
        (env, discount, discounted_sum, episode_return), steps = jax.lax.scan(step, carry, (noise, offsets))
        # Episodes still running at the end of the window bootstrap from the target critic.
        tail = jnp.where(steps.done[-1], 0.0, discounted_sum + discount * value(env.obs))
        loss = -(steps.ended.sum() + tail.sum()) / (num_envs * len(noise))
        loss = loss + cfg.pre_tanh_penalty * jnp.mean(steps.pre_tanh**2)
        boundary = steps.done.at[-1].set(True)
        trajectory = Trajectory(
            critic_obs=steps.critic_obs, reward=steps.reward, next_value=steps.next_value, boundary=boundary
        )
        stats = {
            "finished_return_sum": steps.finished_return.sum(),
            "finished_episodes": steps.done.sum(),
            "mean_reward": steps.reward.mean(),
        }
        # The actor's inputs, pre-tanh actions and (decoupled) backward passes, per step.
        taken = {
            "observations": steps.observation,
            "actions": steps.pre_tanh,
            "actor_vjp": steps.actor_vjp,
            "states": steps.critic_obs,
        }
        return loss, Rollout(env, episode_return, trajectory, steps.visited_obs, stats, taken)

    def actor_gradient(self, actor_params: dict, train: TrainState, noise: jax.Array):
        """``(loss, rollout, ∇θ loss)`` of :meth:`rollout` (``rollout`` its :class:`Rollout`).

        Decoupled: by Theorem 1 the gradient is ``Σ_t (∂a_t/∂θ)ᵀ ∇_{a_t} L`` with the open-loop
        action gradient ``∇_{a_t} L``. So the scan differentiates only the physics (with respect
        to action offsets), and the actor — the pixel encoder above all — is differentiated
        afterwards (:meth:`actor_backward`) instead of inside the reverse scan through the physics.
        Full: plain reverse mode through everything. The auxiliary state-prediction loss (decoupled
        only) joins the actor's gradient in :meth:`actor_backward`; its mean squared error is
        ``rollout.stats["state_prediction_loss"]``.
        """
        cfg = self.config
        if cfg.gradient == "full":
            (loss, aux), grads = jax.value_and_grad(self.rollout, has_aux=True)(actor_params, train, noise)
            return loss, aux, grads
        offsets = jnp.zeros_like(noise)
        (loss, aux), action_grad = jax.value_and_grad(
            lambda w: self.rollout(actor_params, train, noise, w), has_aux=True
        )(offsets)
        grads, squared_error = self.actor_backward(actor_params, aux.taken, noise, action_grad)
        if cfg.state_prediction:
            aux.stats["state_prediction_loss"] = squared_error / aux.taken["states"].size
        return loss, aux, grads

    def actor_backward(self, actor_params: dict, taken: dict, noise: jax.Array, action_grad: jax.Array):
        """``Σ_t (∂a_t/∂θ)ᵀ ∇_{a_t} L`` (plus the state-prediction loss's gradient) from what the
        rollout took (``taken``) and the open-loop action gradient ``(h, N, A)``: a scan over chunks
        of ``actor_backward_chunk`` steps, each recomputing the actor's forward, or over the
        backward passes the rollout kept (0) — one chunk's (step's) workspace at a time.
        (Convolution gradients run at full speed inside a loop only as
        :func:`dva.networks.conv_valid` writes them.) Returns the gradient and the prediction's
        summed squared error."""
        cfg = self.config
        # The auxiliary loss is the weight times the mean of the squared error over its entries.
        error_weight = jnp.asarray(cfg.state_prediction / taken["states"].size)
        if cfg.actor_backward_chunk == 0:

            def step_gradient(step):
                (vjp, error), grad = step
                return vjp((grad, error_weight))[0], error

            steps: tuple[jax.Array, ...] = (taken["actor_vjp"], action_grad)
        else:

            def chunks(x: jax.Array) -> jax.Array:  # (h, N, ...) → (h / c, c·N, ...)
                return x.reshape((-1, cfg.actor_backward_chunk * x.shape[1]) + x.shape[2:])

            def step_gradient(chunk):
                observation, eps, state, grad = chunk
                (_, error), vjp = jax.vjp(lambda p: self.actor_outputs(p, observation, eps, state), actor_params)
                return vjp((grad, error_weight))[0], error

            steps = (chunks(taken["observations"]), chunks(noise), chunks(taken["states"]), chunks(action_grad))

        def accumulate(total, step):
            grads, error = step_gradient(step)
            return jax.tree.map(jnp.add, total, (grads, error)), None

        (grads, squared_error), _ = jax.lax.scan(
            accumulate, (jax.tree.map(jnp.zeros_like, actor_params), jnp.zeros(())), steps
        )
        return grads, squared_error

    # ---- the critic ---------------------------------------------------------------------------
    def critic_update(self, train: TrainState, trajectory: Trajectory, key: jax.Array):
        """Fit the critic to TD-λ targets: ``critic_iterations`` epochs × ``critic_minibatches``."""
        cfg = self.config
        targets = td_lambda_targets(trajectory.reward, trajectory.next_value, trajectory.boundary, cfg.gamma, cfg.lam)
        inputs = trajectory.critic_obs.reshape(-1, trajectory.critic_obs.shape[-1])
        targets = targets.reshape(-1)
        batch = inputs.shape[0] // cfg.critic_minibatches

        def loss_fn(params, x, y):
            return jnp.mean((self.critic.apply(params, x) - y) ** 2)

        def minibatch_step(carry, indices):
            params, opt_state = carry
            loss, grads = jax.value_and_grad(loss_fn)(params, inputs[indices], targets[indices])
            # NaN guard (ref. code): skip a step whose gradient is not finite.
            finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)]))
            grads = jax.tree.map(lambda g: jnp.where(finite, g, 0.0), grads)
            updates, opt_state = self.critic_opt.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss

        def epoch(carry, epoch_key):
            order = jax.random.permutation(epoch_key, inputs.shape[0]).reshape(cfg.critic_minibatches, batch)
            return jax.lax.scan(minibatch_step, carry, order)

        (params, opt_state), losses = jax.lax.scan(
            epoch, (train.critic_params, train.critic_opt_state), jax.random.split(key, cfg.critic_iterations)
        )
        return params, opt_state, losses[-1].mean()

    # ---- one iteration ------------------------------------------------------------------------
    def iteration(self, train: TrainState) -> tuple[TrainState, Metrics]:
        """One training iteration: rollout + actor step, critic fit, target update."""
        cfg = self.config
        key, noise_key, critic_key = jax.random.split(train.key, 3)
        noise = jax.random.normal(noise_key, (cfg.horizon, cfg.num_envs, self.task.action_dim))
        loss, rollout, grads = self.actor_gradient(train.actor_params, train, noise)
        env, episode_return, trajectory, visited_obs, stats, _ = rollout
        grad_norm = optax.tree.norm(grads)
        healthy = jnp.isfinite(grad_norm) & (grad_norm <= cfg.abort_grad_norm)
        updates, actor_opt_state = self.actor_opt.update(grads, train.actor_opt_state, train.actor_params)
        actor_params = optax.apply_updates(train.actor_params, updates)
        # A bad gradient leaves the actor untouched; the training loop stops on it.
        actor_params, actor_opt_state = jax.tree.map(
            lambda new, old: jnp.where(healthy, new, old),
            (actor_params, actor_opt_state),
            (train.actor_params, train.actor_opt_state),
        )

        if cfg.use_critic:
            critic_params, critic_opt_state, critic_loss = self.critic_update(train, trajectory, critic_key)
        else:
            critic_params, critic_opt_state, critic_loss = train.critic_params, train.critic_opt_state, jnp.zeros(())
        target = jax.tree.map(
            lambda t, p: cfg.target_alpha * t + (1.0 - cfg.target_alpha) * p, train.target_critic_params, critic_params
        )
        train = train.replace(
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=target,
            actor_opt_state=actor_opt_state,
            critic_opt_state=critic_opt_state,
            obs_stats=train.obs_stats.update(visited_obs),
            env=env,
            episode_return=episode_return,
            key=key,
            iteration=train.iteration + 1,
        )
        logged = {"actor_loss": loss, "actor_grad_norm": grad_norm, "critic_loss": critic_loss}
        logged |= {name: stats[name] for name in self.metric_names if name in stats}
        return train, Metrics(healthy, stats["finished_return_sum"], stats["finished_episodes"], logged)

    # ---- the agent's policy ------------------------------------------------------------------
    def policy(self, train: TrainState) -> tuple[dict, RunningStats]:
        """What the deterministic policy needs: the actor and the state statistics."""
        return train.actor_params, train.obs_stats

    def act(self, policy: tuple[dict, RunningStats], observation: Observation) -> jax.Array:
        """The deterministic action ``tanh(μ)``."""
        actor_params, obs_stats = policy
        return jnp.tanh(self.pre_tanh_action(actor_params, self.actor_input(observation, obs_stats), None))

    def sample(self, policy: tuple[dict, RunningStats], observation: Observation, key: jax.Array) -> jax.Array:
        """The training action ``tanh(μ + σε)``, ``ε`` standard normal from ``key``."""
        actor_params, obs_stats = policy
        actor_input = self.actor_input(observation, obs_stats)
        noise = jax.random.normal(key, (actor_input.shape[0], self.task.action_dim))
        return jnp.tanh(self.pre_tanh_action(actor_params, actor_input, noise))

    def abort_reason(self, logged: dict) -> str:
        return (
            f"actor gradient norm {float(logged['actor_grad_norm']):.3g} is NaN or above "
            f"abort_grad_norm = {self.config.abort_grad_norm:.3g}"
        )


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def clip_gradient_per_env(tree, max_norm: float):
    """The identity, whose backward pass rescales each env's cotangent (leading axis, all leaves
    together) to a norm of at most ``max_norm``."""
    return tree


def _clip_forward(tree, max_norm):
    return tree, None


def _clip_backward(max_norm, _, cotangent):
    leaves = jax.tree.leaves(cotangent)
    squared = sum(jnp.sum(jnp.square(leaf.reshape(leaf.shape[0], -1)), axis=1) for leaf in leaves)
    scale = jnp.minimum(1.0, max_norm / jnp.maximum(jnp.sqrt(squared), 1e-12))
    return (jax.tree.map(lambda leaf: leaf * scale.reshape((-1,) + (1,) * (leaf.ndim - 1)), cotangent),)


clip_gradient_per_env.defvjp(_clip_forward, _clip_backward)


def td_lambda_targets(
    reward: jax.Array, next_value: jax.Array, boundary: jax.Array, gamma: float, lam: float
) -> jax.Array:
    """TD-λ targets over a window (time-major, (h, N)).

    ``R_t = r_t + γ [(1 − λ) V_{t+1} + λ R_{t+1}]`` inside an episode and ``R_t = r_t + γ V_{t+1}``
    where the episode or the window ends after step t (``V_{t+1}`` is 0 on termination). This is
    the truncated TD-λ sum ``(1−λ) Σ_k λ^{k−1} G_t^k + λ^{H−t−1} G_t^{H−t}`` computed backwards.
    """

    def back(next_return, inputs):
        r, v, end = inputs
        ret = r + gamma * jnp.where(end, v, (1.0 - lam) * v + lam * next_return)
        return ret, ret

    _, returns = jax.lax.scan(back, jnp.zeros_like(reward[0]), (reward, next_value, boundary), reverse=True)
    return returns

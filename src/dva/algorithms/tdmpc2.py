"""TD-MPC2 (Hansen, Su, Wang, ICLR 2024) from pixels or from the state vector
(``observation="state"``): an implicit world model learned by temporal difference, planned over
with MPPI.

The world model never reconstructs an observation. An encoder maps the observation to a latent
``z`` (SimNorm: groups of 8 entries, each a softmax); a dynamics MLP predicts the next latent
from ``(z, a)``, a reward head the reward, an ensemble of ``num_q`` Q-functions the value, a
termination head whether the episode ended; reward and Q heads regress two-hot targets over
``num_bins`` bins of the ``symlog`` of the value. A Gaussian policy prior (tanh-squashed) learns
to maximise Q and proposes trajectories to the planner.

One iteration plans and takes one step in every env (the planner's plan of the previous step
warm-starts the next), stores it in a sequence replay, then makes ``updates_per_iteration``
updates, each on ``batch_size`` replayed sequences of ``horizon`` + 1 observations:

* **model**: the latent rolled out through the dynamics from the first observation's encoding;
  per step ``t`` (weight ``ρ^t``) ``consistency_coef`` × the squared distance to the
  (detached) encoding of the next observation, ``reward_coef`` × the reward's cross-entropy,
  ``value_coef`` × every Q member's cross-entropy to the TD target
  ``r + γ (1 − terminated) min(Q̄ᵢ, Q̄ⱼ)(z', π(z'))`` (two random target members, ``z'`` the
  next observation's encoding), and ``termination_coef`` × the termination's binary cross-entropy;
  global-norm clipping at ``grad_clip``, Adam, the encoder at ``encoder_lr_scale`` × the rate;
* **policy prior**: ``−(Q(z, π(z)) / S + entropy_coef · action_dim · H(π))`` on the rolled-out
  latents (detached; weight ``ρ^t``), Q the mean of two random members, S the EMA (rate ``tau``)
  of the 5th–95th percentile spread of Q, at least 1;
* **target Q**: Polyak average with rate ``tau``.

**Planning** (MPPI, per env): ``num_samples`` action sequences of ``horizon`` steps —
``num_pi_trajs`` of them rolled out by the policy prior, the others drawn from a Gaussian whose
mean starts at the previous step's plan shifted by one — scored by the model's discounted
rewards plus ``γ^H`` Q at the end (zero after a predicted termination); ``mppi_iterations`` times
the Gaussian is refit to the ``num_elites`` best, weighted by ``exp(temperature · value)``
(two refits more for 20 or more actions, the reference's rule). The
action is the first of one elite drawn by that weight, plus the final std's noise while training
(not in evaluation, where the plan is carried from step to step as a recurrent policy's memory).
The Q members use dropout in the model and policy-prior updates, not in the TD target or the planner.
The discount follows TD-MPC2's rule from the episode's length in agent steps ``T``:
``(T/5 − 1) / (T/5)`` within [0.95, 0.995].

Simplified against the reference implementation (the method kept): many envs step in parallel
(the reference steps one; ``updates_per_iteration`` per step of all envs keeps its one update per
agent step); replayed sequences may cross an episode's end, and the steps past it are weighted 0
(the reference samples within episodes); the random-shift augmentation applies in updates only
(the reference's encoder shifts every frame it sees, the planner's too); the seed phase is not
followed by the reference's burst of as many updates as seed steps; the termination head is
always learned (the reference's "episodic" mode), since our tasks may end early.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.augmentation import random_shift
from dva.algorithms.base import Metrics, all_finite, nan_loss_reason
from dva.algorithms.model_based_math import categorical_cross_entropy, symlog_bins, twohot, twohot_decode
from dva.algorithms.off_policy import collect_into_replay, empty_step, newest_frame, seed_replay, seed_rounds
from dva.algorithms.replay import SequenceReplay, Step, stack_at
from dva.envs.observations import Env, Observation
from dva.errors import DvaUsageError, check_numbers
from dva.networks.tdmpc2 import NormedMLP, QEnsemble, TDMPC2PixelEncoder, concat_action, pixel_latent_dim
from dva.tasks.base import EnvState


@dataclasses.dataclass(frozen=True)
class TDMPC2Config:
    """Hyperparameters: the reference's defaults (its 5M-parameter model: latent 512, MLPs 512
    wide, five Q members), its 64² × 3-frame pixels and its action repeat 2."""

    observation: Literal["pixels", "state"] = "pixels"
    num_envs: int = 4
    image_size: int = 64
    frame_stack: int = 3
    action_repeat: int = 2
    updates_per_iteration: int = 4  # one update per agent step of one env, as the reference
    batch_size: int = 256
    horizon: int = 3  # latent rollout in the model loss, and the planner's horizon
    replay_size: int = 1_000_000  # agent steps kept, over all envs
    # env (control) steps of uniform random actions first; None: the reference's
    # max(1000, 5 × episode length) agent steps
    seed_steps: int | None = None
    latent_dim: int = 512  # state observations; pixels: what the encoder's last convolution gives
    encoder_dim: int = 256
    encoder_layers: int = 2
    mlp_dim: int = 512
    channels: int = 32
    simnorm_group: int = 8
    num_q: int = 5
    dropout: float = 0.01  # in each Q member's first layer, while training
    num_bins: int = 101
    value_low: float = -10.0  # the bins' range, in symlog space
    value_high: float = 10.0
    lr: float = 3e-4
    encoder_lr_scale: float = 0.3
    grad_clip: float = 20.0
    tau: float = 0.01  # target-Q Polyak rate, and the Q scale's EMA rate
    rho: float = 0.5  # the weight of step t in the losses is rho^t
    consistency_coef: float = 20.0
    reward_coef: float = 0.1
    value_coef: float = 0.1
    termination_coef: float = 1.0
    entropy_coef: float = 1e-4
    log_std_min: float = -10.0
    log_std_max: float = 2.0
    mppi_iterations: int = 6
    num_samples: int = 512
    num_elites: int = 64
    num_pi_trajs: int = 24
    min_std: float = 0.05
    max_std: float = 2.0
    temperature: float = 0.5
    shift_pad: int = 3
    iterations: int = 100_000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_envs", "action_repeat", "updates_per_iteration", "batch_size", "horizon", "num_q"):
            if getattr(self, name) < 1:
                raise DvaUsageError(f"{name} = {getattr(self, name)!r} is not allowed; use an int ≥ 1")
        if self.observation not in ("pixels", "state"):
            raise DvaUsageError(f"observation = {self.observation!r} is not allowed; use 'pixels' or 'state'")
        if self.num_q < 2:
            raise DvaUsageError(f"num_q = {self.num_q} is not allowed; use ≥ 2 (targets take two members)")
        if not 0 < self.num_elites <= self.num_samples or not 0 <= self.num_pi_trajs < self.num_samples:
            raise DvaUsageError(
                f"num_elites = {self.num_elites}, num_pi_trajs = {self.num_pi_trajs} are not allowed with "
                f"num_samples = {self.num_samples}; use 0 < num_elites ≤ num_samples and 0 ≤ num_pi_trajs < num_samples"
            )
        latent = pixel_latent_dim(self.image_size, self.channels) if self.observation == "pixels" else self.latent_dim
        if latent % self.simnorm_group:
            raise DvaUsageError(
                f"simnorm_group = {self.simnorm_group} does not divide the latent's {latent} entries; use a divisor"
            )


class TDMPC2State(struct.PyTreeNode):
    """Everything one iteration reads and writes."""

    params: dict  # {"encoder", "dynamics", "reward", "termination", "q", "policy"}
    target_q: dict
    opt_states: dict  # {"model", "policy"}
    q_scale: jax.Array  # S: the EMA of Q's 5th–95th percentile spread (≥ 1)
    env: EnvState
    first: jax.Array  # (N,) bool: the current observation starts an episode
    plan: jax.Array  # (N, horizon, A): each env's last plan (the next one's warm start)
    replay: object
    episode_return: jax.Array
    key: jax.Array
    iteration: jax.Array


class Sequences(struct.PyTreeNode):
    """Replayed sequences, time-major: observations 0…H and the H steps between them, with the
    weights that stop each loss at an episode's end."""

    obs: jax.Array  # (H + 1, B, …)
    action: jax.Array  # (H, B, A)
    reward: jax.Array  # (H, B)
    terminated: jax.Array  # (H, B)
    reached: jax.Array  # (H + 1, B): no episode ended before this observation
    bootstrap: jax.Array  # (H, B): observation t + 1 follows step t (no episode ended there)
    truncated: jax.Array  # (H, B)


def discount_for(episode_steps: int) -> float:
    """TD-MPC2's discount from the episode's length in agent steps: ``(T/5 − 1)/(T/5)`` in [0.95, 0.995]."""
    fraction = episode_steps / 5
    return min(max((fraction - 1) / fraction, 0.95), 0.995)


class TDMPC2:
    """The TD-MPC2 agent (an :class:`~dva.algorithms.base.Agent` and
    :class:`~dva.algorithms.base.RecurrentAgent`: the plan is its memory); see the module docstring."""

    batch_fields = ()  # one device: its replay is not split
    metric_names = (
        "consistency_loss",
        "reward_loss",
        "value_loss",
        "termination_loss",
        "policy_loss",
        "q_scale",
        "exploration",
    )

    def __init__(self, env: Env, config: TDMPC2Config) -> None:
        self.pixels = config.observation == "pixels"
        if env.num_envs != config.num_envs or env.has_pixels != self.pixels:
            seen = "renders" if self.pixels else "renders nothing"
            raise DvaUsageError(
                f"TD-MPC2 on {config.observation} needs an env wrapper of {config.num_envs} envs that {seen}"
            )
        self.env, self.task, self.config = env, env.task, config
        cfg = config
        hidden = (cfg.mlp_dim, cfg.mlp_dim)
        if self.pixels:
            self.latent_dim = pixel_latent_dim(cfg.image_size, cfg.channels)
            self.encoder = TDMPC2PixelEncoder(cfg.channels, cfg.simnorm_group)
        else:
            self.latent_dim = cfg.latent_dim
            encoder_hidden = (cfg.encoder_dim,) * max(cfg.encoder_layers - 1, 1)
            self.encoder = NormedMLP(encoder_hidden, cfg.latent_dim, simnorm_group=cfg.simnorm_group)
        self.dynamics = NormedMLP(hidden, self.latent_dim, simnorm_group=cfg.simnorm_group)
        self.reward_head = NormedMLP(hidden, cfg.num_bins, zero_output=True)
        self.termination_head = NormedMLP(hidden, 1)
        self.policy_net = NormedMLP(hidden, 2 * env.task.action_dim)
        self.q = QEnsemble(cfg.num_q, hidden, cfg.num_bins, cfg.dropout)
        self.bins = symlog_bins(cfg.num_bins, cfg.value_low, cfg.value_high)
        self.gamma = discount_for(env.episode_steps)
        encoder_first = lambda params: {name: "encoder" if name == "encoder" else "rest" for name in params}
        self.optimizers = {
            "model": optax.chain(
                optax.clip_by_global_norm(cfg.grad_clip),
                optax.multi_transform(
                    {"encoder": optax.adam(cfg.lr * cfg.encoder_lr_scale), "rest": optax.adam(cfg.lr)}, encoder_first
                ),
            ),
            "policy": optax.chain(optax.clip_by_global_norm(cfg.grad_clip), optax.adam(cfg.lr, eps=1e-5)),
        }
        self.stack = cfg.frame_stack if self.pixels else 1  # observations a stored step contributes to
        self.replay = SequenceReplay(cfg.num_envs, cfg.replay_size, cfg.batch_size, self.stack + cfg.horizon)

    # ---- the agent's sizes --------------------------------------------------------------------
    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.action_repeat

    @property
    def default_iterations(self) -> int:
        return self.config.iterations

    @property
    def seed_steps(self) -> int:
        if self.config.seed_steps is not None:
            return self.config.seed_steps
        return max(1000, 5 * self.env.episode_steps) * self.config.action_repeat

    @property
    def seed_rounds(self) -> int:
        return seed_rounds(self.seed_steps, self.env_steps_per_iteration, self.replay.sequence_length)

    @property
    def prior_cost(self) -> tuple[float, int]:
        """The seed phase's env steps, taken in :meth:`init` (its time is in the run's clock)."""
        return 0.0, self.seed_rounds * self.env_steps_per_iteration

    # ---- the world model ----------------------------------------------------------------------
    def observed(self, env: EnvState) -> jax.Array:
        """What the replay stores of an observation: its newest frame, or the state."""
        return newest_frame(env) if self.pixels else env.obs

    def observation(self, env: EnvState) -> jax.Array:
        """What the encoder reads: the frame stack, or the state."""
        return env.frames if self.pixels else env.obs

    def encode(self, params: dict, observation: jax.Array) -> jax.Array:
        return self.encoder.apply(params["encoder"], observation)

    def next(self, params: dict, z: jax.Array, action: jax.Array) -> jax.Array:
        return self.dynamics.apply(params["dynamics"], concat_action(z, action))

    def reward(self, params: dict, z: jax.Array, action: jax.Array) -> jax.Array:
        """The predicted reward (decoded from its two-hot logits)."""
        return twohot_decode(self.reward_head.apply(params["reward"], concat_action(z, action)), self.bins)

    def terminated(self, params: dict, z: jax.Array) -> jax.Array:
        """Whether the termination head calls the episode over on arriving in ``z``."""
        return self.termination_head.apply(params["termination"], z)[..., 0] > 0.0

    def q_value(
        self,
        q_params: dict,
        z: jax.Array,
        action: jax.Array,
        key: jax.Array,
        reduce: Literal["min", "mean"],
        dropout_key: jax.Array | None = None,
    ) -> jax.Array:
        """The min or the mean of two Q members drawn at random (the reference's rule), with
        dropout where ``dropout_key`` is given (the reference's Q in training mode)."""
        members = jax.random.choice(key, self.config.num_q, (2,), replace=False)
        logits = self.q.apply(q_params, concat_action(z, action), members, dropout_key=dropout_key)
        values = twohot_decode(logits, self.bins)
        return jnp.min(values, 0) if reduce == "min" else jnp.mean(values, 0)

    def policy_sample(self, policy: dict, z: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """An action of the policy prior (tanh of a reparameterised Gaussian), its mean action, and
        the entropy term of its loss: ``−action_dim · log N(ε; 0, σ)``, the Gaussian's before the
        squashing scaled by the action's size (what the reference's scaled entropy works out to)."""
        cfg = self.config
        mean, raw_log_std = jnp.split(self.policy_net.apply(policy, z), 2, axis=-1)
        log_std = cfg.log_std_min + 0.5 * (cfg.log_std_max - cfg.log_std_min) * (jnp.tanh(raw_log_std) + 1.0)
        noise = jax.random.normal(key, mean.shape)
        log_prob = jnp.sum(-0.5 * noise**2 - log_std - 0.5 * jnp.log(2 * jnp.pi), -1)
        action = jnp.tanh(mean + noise * jnp.exp(log_std))
        return action, jnp.tanh(mean), -mean.shape[-1] * log_prob

    # ---- planning -----------------------------------------------------------------------------
    @property
    def mppi_iterations(self) -> int:
        """The configured refits, two more for 20 or more actions (the reference's rule for large
        action spaces: the Humanoid's 21)."""
        return self.config.mppi_iterations + 2 * (self.task.action_dim >= 20)

    def trajectory_value(self, params: dict, z: jax.Array, actions: jax.Array, key: jax.Array) -> jax.Array:
        """The value of action sequences ``actions`` (H, S, A) from latents ``z`` (S, L): the
        model's discounted rewards, then ``γ^H`` × Q (the mean of two members) with the policy's
        action; nothing after a predicted termination."""
        policy_key, q_key = jax.random.split(key)
        total, discount, ended = jnp.zeros(z.shape[0]), 1.0, jnp.zeros(z.shape[0])
        for action in actions:
            reward = self.reward(params, z, action)
            z = self.next(params, z, action)
            total = total + discount * (1.0 - ended) * reward
            discount = discount * self.gamma
            ended = jnp.maximum(ended, self.terminated(params, z).astype(z.dtype))
        action = self.policy_sample(params["policy"], z, policy_key)[0]
        return total + discount * (1.0 - ended) * self.q_value(params["q"], z, action, q_key, "mean")

    def plan(
        self, params: dict, z: jax.Array, warm_start: jax.Array, key: jax.Array, explore: bool
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """MPPI from one latent ``z`` (L,): the action (A,), the plan's mean (H, A), which the
        next step's plan starts from, shifted by one (``warm_start``: this step's, shifted), and
        the mean std of its first action (the exploration noise while training)."""
        cfg, action_dim = self.config, self.task.action_dim
        prior_key, sample_key, value_key, choice_key, noise_key = jax.random.split(key, 5)
        prior_steps = []
        prior_z = jnp.broadcast_to(z, (cfg.num_pi_trajs, z.shape[-1]))
        for step_key in jax.random.split(prior_key, cfg.horizon):
            action = self.policy_sample(params["policy"], prior_z, step_key)[0]
            prior_steps.append(action)
            prior_z = self.next(params, prior_z, action)
        prior_actions = jnp.stack(prior_steps)  # (H, P, A)
        samples_z = jnp.broadcast_to(z, (cfg.num_samples, z.shape[-1]))

        def refit(carry, keys):
            mean, std, _, _ = carry
            draw_key, key = keys
            noise = jax.random.normal(draw_key, (cfg.horizon, cfg.num_samples - cfg.num_pi_trajs, action_dim))
            actions = jnp.concatenate([prior_actions, jnp.clip(mean[:, None] + std[:, None] * noise, -1.0, 1.0)], 1)
            value = jnp.nan_to_num(self.trajectory_value(params, samples_z, actions, key))
            elite_value, elite = jax.lax.top_k(value, cfg.num_elites)
            elite_actions = actions[:, elite]  # (H, E, A)
            score = jax.nn.softmax(cfg.temperature * elite_value)
            mean = jnp.einsum("e,hea->ha", score, elite_actions)
            std = jnp.sqrt(jnp.einsum("e,hea->ha", score, (elite_actions - mean[:, None]) ** 2))
            return (mean, jnp.clip(std, cfg.min_std, cfg.max_std), score, elite_actions), None

        initial = (
            warm_start,
            jnp.full((cfg.horizon, action_dim), cfg.max_std),
            jnp.zeros(cfg.num_elites),
            jnp.zeros((cfg.horizon, cfg.num_elites, action_dim)),
        )
        iterations = self.mppi_iterations
        keys = (jax.random.split(sample_key, iterations), jax.random.split(value_key, iterations))
        (mean, std, score, elite_actions), _ = jax.lax.scan(refit, initial, keys)
        chosen = jax.random.categorical(choice_key, jnp.log(score + 1e-20))
        action = elite_actions[0, chosen]
        if explore:
            action = action + std[0] * jax.random.normal(noise_key, (action_dim,))
        return jnp.clip(action, -1.0, 1.0), mean, jnp.mean(std[0])

    def act_batch(
        self, params: dict, observation: jax.Array, plans: jax.Array, key: jax.Array, explore: bool
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """A plan per env from its observation and its previous plan (N, H, A): actions (N, A),
        the plans' means and their first actions' stds (N,)."""
        warm_start = jnp.concatenate([plans[:, 1:], jnp.zeros_like(plans[:, :1])], axis=1)
        z = self.encode(params, observation)
        keys = jax.random.split(key, len(z))
        return jax.vmap(lambda z, w, k: self.plan(params, z, w, k, explore))(z, warm_start, keys)

    def initial_memory(self, num_envs: int) -> jax.Array:
        """No plan yet: the first plan starts from a zero mean."""
        return jnp.zeros((num_envs, self.config.horizon, self.task.action_dim))

    def act_recurrent(
        self, policy: dict, observation: Observation, memory: jax.Array, key: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """The planner's action without exploration noise; the plan is the memory."""
        return self.act_batch(policy, observation[self.config.observation], memory, key, explore=False)[:2]

    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """The planner's action from no previous plan, with a fixed key."""
        memory = self.initial_memory(len(observation[self.config.observation]))
        return self.act_recurrent(policy, observation, memory, jax.random.PRNGKey(0))[0]

    def policy(self, state: TDMPC2State) -> dict:
        """The world model and the policy prior (the planner uses them all; not the target Qs)."""
        return state.params

    # ---- learning -----------------------------------------------------------------------------
    def sequences(self, steps: Step) -> Sequences:
        """Replayed steps (B, stack − 1 + H + 1, …) as time-major model-loss inputs: the frame
        stacks rebuilt, and the weights of the steps before and after an episode's end."""
        cfg, first = self.config, self.stack - 1
        if self.pixels:
            rebuild = lambda t: jax.vmap(lambda s: stack_at(s.frame, s.first, first + t, cfg.frame_stack))(steps)
            obs = jnp.stack([rebuild(t) for t in range(cfg.horizon + 1)])
        else:
            obs = jnp.swapaxes(steps.frame, 0, 1)
        window = lambda x: jnp.swapaxes(x[:, first : first + cfg.horizon], 0, 1)
        terminated, truncated = window(steps.terminated), window(steps.truncated)
        ended = terminated | truncated
        going_on = jnp.concatenate([jnp.ones_like(ended[:1]), ~ended]).astype(jnp.int32)
        reached = jnp.cumprod(going_on, axis=0).astype(bool)
        return Sequences(
            obs=obs,
            action=window(steps.action),
            reward=window(steps.reward),
            terminated=terminated.astype(jnp.float32),
            reached=reached,
            bootstrap=reached[:-1] & ~ended,
            truncated=truncated,
        )

    def augment(self, obs: jax.Array, key: jax.Array) -> jax.Array:
        """Every frame stack shifted by its own random offset (pixels); the state as it is."""
        if not self.pixels:
            return obs
        flat = obs.reshape((-1,) + obs.shape[2:])
        return random_shift(flat, self.config.shift_pad, key).reshape(obs.shape)

    def model_loss(
        self, params: dict, batch: Sequences, first_obs: jax.Array, next_z: jax.Array, td_target: jax.Array, key
    ):
        """The world model's loss (see the module docstring) from the augmented first observation
        ``first_obs`` (B, …), with ``next_z`` (H, B, L) the encodings of the next ones (the
        consistency targets, without gradient); also returns the rolled-out latents (H + 1, B, L)
        and the loss terms."""
        cfg = self.config
        weight = cfg.rho ** jnp.arange(cfg.horizon)[:, None] / cfg.batch_size  # (H, 1)
        z = self.encode(params, first_obs)
        rollout, consistency = [z], jnp.zeros(())
        for t in range(cfg.horizon):
            z = self.next(params, z, batch.action[t])
            rollout.append(z)
            error = jnp.mean((z - next_z[t]) ** 2, -1)
            consistency = consistency + jnp.sum(weight[t] * batch.bootstrap[t] * error)
        zs = jnp.stack(rollout)
        inputs = concat_action(zs[:-1], batch.action)
        reward_logits = self.reward_head.apply(params["reward"], inputs)
        reward_error = categorical_cross_entropy(reward_logits, twohot(batch.reward, self.bins))
        q_logits = self.q.apply(params["q"], inputs, dropout_key=key)  # (num_q, H, B, bins)
        value_error = jnp.sum(categorical_cross_entropy(q_logits, twohot(td_target, self.bins)[None]), 0)
        value_weight = batch.reached[:-1] & ~batch.truncated
        termination_logit = self.termination_head.apply(params["termination"], zs[1:])[..., 0]
        termination_error = optax.sigmoid_binary_cross_entropy(termination_logit, batch.terminated)
        terms = {
            "consistency_loss": consistency / cfg.horizon,
            "reward_loss": jnp.sum(weight * batch.reached[:-1] * reward_error) / cfg.horizon,
            "value_loss": jnp.sum(weight * value_weight * value_error) / (cfg.horizon * cfg.num_q),
            "termination_loss": jnp.sum(batch.reached[:-1] * termination_error) / (cfg.horizon * cfg.batch_size),
        }
        loss = (
            cfg.consistency_coef * terms["consistency_loss"]
            + cfg.reward_coef * terms["reward_loss"]
            + cfg.value_coef * terms["value_loss"]
            + cfg.termination_coef * terms["termination_loss"]
        )
        return loss, (zs, terms)

    def td_target(self, params: dict, target_q: dict, batch: Sequences, next_z: jax.Array, key: jax.Array) -> jax.Array:
        """``r + γ (1 − terminated) min(Q̄ᵢ, Q̄ⱼ)(z', π(z'))`` per step (H, B), ``z'`` = ``next_z``
        the encoding of the next observation."""
        policy_key, q_key = jax.random.split(key)
        action = self.policy_sample(params["policy"], next_z, policy_key)[0]
        next_value = self.q_value(target_q, next_z, action, q_key, "min")
        return jax.lax.stop_gradient(batch.reward + self.gamma * (1.0 - batch.terminated) * next_value)

    def policy_loss(self, policy: dict, q_params: dict, zs: jax.Array, reached: jax.Array, q_scale, key):
        """The policy prior's loss on the rolled-out latents ``zs`` (H + 1, B, L), and the Q scale
        updated with this batch's first latents."""
        cfg = self.config
        action_key, q_key, dropout_key = jax.random.split(key, 3)
        action, _, entropy = self.policy_sample(policy, zs, action_key)
        # the Q members in training mode, dropout on, as the reference's policy update reads them
        q = self.q_value(q_params, zs, action, q_key, "mean", dropout_key)
        low, high = jnp.percentile(jax.lax.stop_gradient(q[0]), jnp.array([5.0, 95.0]))
        spread = high - low
        q_scale = q_scale + cfg.tau * (jnp.maximum(spread, 1.0) - q_scale)
        weight = cfg.rho ** jnp.arange(cfg.horizon + 1)[:, None] * reached / cfg.batch_size
        loss = -jnp.sum(weight * (cfg.entropy_coef * entropy + q / q_scale)) / (cfg.horizon + 1)
        return loss, q_scale

    def update(self, state: TDMPC2State, key: jax.Array) -> tuple[TDMPC2State, dict]:
        """One model update, one policy-prior update and the target-Q average, on sampled sequences."""
        cfg = self.config
        sample_key, shift_key, target_key, dropout_key, policy_key = jax.random.split(key, 5)
        batch = self.sequences(self.replay.sample_sequences(state.replay, sample_key))
        obs = self.augment(batch.obs, shift_key)
        params, opt_states = state.params, dict(state.opt_states)
        # the next observations' encodings: the consistency targets and where the TD targets start
        next_z = jax.lax.stop_gradient(self.encode(params, obs[1:]))
        td_target = self.td_target(params, state.target_q, batch, next_z, target_key)
        model = {name: value for name, value in params.items() if name != "policy"}
        (_, (zs, terms)), grads = jax.value_and_grad(self.model_loss, has_aux=True)(
            model, batch, obs[0], next_z, td_target, dropout_key
        )
        updates, opt_states["model"] = self.optimizers["model"].update(grads, opt_states["model"], model)
        model = optax.apply_updates(model, updates)
        (policy_loss, q_scale), grads = jax.value_and_grad(self.policy_loss, has_aux=True)(
            params["policy"],
            jax.lax.stop_gradient(model["q"]),
            jax.lax.stop_gradient(zs),
            batch.reached,
            state.q_scale,
            policy_key,
        )
        updates, opt_states["policy"] = self.optimizers["policy"].update(grads, opt_states["policy"], params["policy"])
        params = {**model, "policy": optax.apply_updates(params["policy"], updates)}
        state = state.replace(
            params=params,
            target_q=optax.incremental_update(model["q"], state.target_q, cfg.tau),
            opt_states=opt_states,
            q_scale=q_scale,
        )
        return state, {**terms, "policy_loss": policy_loss, "q_scale": q_scale}

    # ---- the loop -----------------------------------------------------------------------------
    def init(self, key: jax.Array) -> TDMPC2State:
        """Fresh networks and envs, and a replay filled with ``seed_rounds`` uniform random steps."""
        cfg, action_dim = self.config, self.task.action_dim
        env_key, seed_key, key, *net_keys = jax.random.split(key, 9)
        env = self.env.reset(env_key)
        encoder = self.encoder.init(net_keys[0], self.observation(env)[:1])
        z = self.encoder.apply(encoder, self.observation(env)[:1])
        za = concat_action(z, jnp.zeros((1, action_dim)))
        params = {
            "encoder": encoder,
            "dynamics": self.dynamics.init(net_keys[1], za),
            "reward": self.reward_head.init(net_keys[2], za),
            "termination": self.termination_head.init(net_keys[3], z),
            "q": self.q.init(net_keys[4], za),
            "policy": self.policy_net.init(net_keys[5], z),
        }
        model = {name: value for name, value in params.items() if name != "policy"}
        state = TDMPC2State(
            params=params,
            target_q=params["q"],
            opt_states={
                "model": self.optimizers["model"].init(model),
                "policy": self.optimizers["policy"].init(params["policy"]),
            },
            q_scale=jnp.ones(()),
            env=env,
            first=jnp.ones(cfg.num_envs, bool),
            plan=self.initial_memory(cfg.num_envs),
            replay=self.replay.init(empty_step(self.observed(env)[0], action_dim)),
            episode_return=jnp.zeros(cfg.num_envs),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )
        return seed_replay(self.env, self.replay, state, self.seed_rounds, seed_key, stored=self.observed)

    def iteration(self, state: TDMPC2State) -> tuple[TDMPC2State, Metrics]:
        """One planned, exploring step of every env into the replay, then ``updates_per_iteration`` updates."""
        key, act_key, update_key = jax.random.split(state.key, 3)
        plans = jnp.where(state.first[:, None, None], 0.0, state.plan)  # a new episode plans afresh
        action, plan, std = self.act_batch(state.params, self.observation(state.env), plans, act_key, explore=True)
        state, finished = collect_into_replay(self.env, self.replay, state, action, stored=self.observed)
        state, losses = jax.lax.scan(
            self.update, state.replace(plan=plan), jax.random.split(update_key, self.config.updates_per_iteration)
        )
        logged = {name: jnp.mean(value) for name, value in losses.items()}
        logged["exploration"] = jnp.mean(std)
        metrics = Metrics(all_finite(logged), finished.sum(), state.first.sum(), logged)
        return state.replace(key=key, iteration=state.iteration + 1), metrics

    def abort_reason(self, logged: dict) -> str:
        return nan_loss_reason(logged, self.metric_names)

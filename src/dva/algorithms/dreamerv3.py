"""DreamerV3 (Hafner et al. 2023) from pixels — the paper's model-based visual baseline — or
from the state vector (``observation="state"``: its MLP encoder and decoder on the ``symlog`` of
the state, as the reference runs proprioceptive tasks). The reference is the 2023 release of
``danijar/dreamerv3`` (the paper's version; the 2024 rewrite changed the model).

One iteration collects ``collect_steps`` steps of every env with the actor acting on the RSSM's
posterior state (stored as single frames in a sequence replay), then makes ``updates`` updates,
each on ``batch_size`` replayed sequences of ``batch_length`` steps (``train_ratio`` replayed
steps per policy step):

* **world model**: the RSSM (the reference's GRU: LayerNorm on its gates, update bias −1)
  observes the sequence (its state reset at episode starts); loss = reconstruction (squared error
  summed over pixels, or over the symlog state's entries) + two-hot symlog reward + continuation
  (Bernoulli) + 0.5 · dynamics KL + 0.1 · representation KL, each KL with 1 nat free;
* **imagination**: from every posterior state, ``horizon`` steps of the prior with actions
  sampled from the actor, which reads each state through a stop-gradient, the model frozen; the
  model reads each action clipped to [−1, 1] by a stop-gradient rescaling, so that samples
  outside the box still carry gradient; step t weighs γ^t times the chance it is reached;
* **critic**: two-hot symlog regression on the λ-returns of the imagined rewards and the
  continuation head's mode (1 or 0), plus a regulariser towards its EMA (``critic_ema``);
* **actor**: the advantage ``(R − v) / max(1, S)``, S the EMA of the returns' 5th–95th
  percentile range, maximised by backpropagating through the imagined trajectory (the frozen
  model, the reward head and the critic) — the 2023 reference's gradient for continuous actions —
  or, with ``actor_gradient="reinforce"``, by REINFORCE on the same advantage; plus an entropy
  bonus. Evaluation samples the actor, as the reference's eval mode does.

Where this differs from the 2023 release (the method kept): the RSSM's initial state is zeros
rather than learned; weights start from flax's LeCun normal rather than the reference's truncated
normal over the average fan; the actor's output layer is zero-initialised like the reward and
critic heads (its first mean action is 0); the reward and continuation of a step are predicted
from the state it leads to, taken from the prior where the auto-reset hid the last frame of an
episode; replayed sequences start from a fresh state rather than the previous batch's last
latent, which the release carries over. Adam with global-norm clipping (1000 for the model, 100 for actor
and critic) is the release's own optimiser.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from dva.algorithms.base import Metrics, all_finite, nan_loss_reason
from dva.algorithms.model_based_math import (
    categorical_cross_entropy,
    kl_balance_losses,
    lambda_returns,
    normalized_advantage,
    symlog,
    symlog_bins,
    twohot,
    twohot_decode,
    unimix_logits,
    update_return_scale,
)
from dva.algorithms.off_policy import collect_into_replay, empty_step, newest_frame, seed_replay, seed_rounds
from dva.algorithms.replay import SequenceReplay, Step
from dva.envs.observations import Env, Observation
from dva.errors import DvaUsageError, check_numbers
from dva.networks import RSSM, ConvDecoder, ConvEncoder, DreamerMLP, MLPEncoder, scale_pixels
from dva.tasks.base import EnvState


@dataclasses.dataclass(frozen=True)
class DreamerV3Config:
    """Hyperparameters (the paper's DreamerV3 settings; the network sizes of the reference's "S" model)."""

    observation: Literal["pixels", "state"] = "pixels"  # what the world model encodes and reconstructs
    num_envs: int = 4
    image_size: int = 64
    frame_stack: int = 1  # the RSSM remembers: one frame per observation
    action_repeat: int = 2
    batch_size: int = 16
    batch_length: int = 64
    train_ratio: float = 512.0  # replayed steps per policy step (over all envs)
    replay_size: int = 1_000_000  # policy steps kept, over all envs
    seed_steps: int = 4000  # env steps of uniform random actions before the first update
    deter: int = 512
    stoch: int = 32
    classes: int = 32
    units: int = 512
    layers: int = 2  # hidden layers of the reward, continuation, actor and critic heads
    # the state's encoder and decoder (observation="state"): the 2023 reference's dmc_proprio config
    # sets the heads to 2 × 512 but leaves these at its defaults
    mlp_units: int = 1024
    mlp_layers: int = 5
    cnn_depth: int = 32
    unimix: float = 0.01
    free_nats: float = 1.0
    dynamics_scale: float = 0.5
    representation_scale: float = 0.1
    model_lr: float = 1e-4
    model_eps: float = 1e-8
    model_clip: float = 1000.0
    horizon: int = 15  # imagined steps
    gamma: float = 0.997
    lam: float = 0.95
    actor_lr: float = 3e-5
    critic_lr: float = 3e-5
    actor_critic_eps: float = 1e-5
    actor_critic_clip: float = 100.0
    entropy: float = 3e-4
    # continuous actions: the λ-return's gradient through the frozen model (the 2023 paper's choice
    # for continuous control), or REINFORCE (its choice for discrete actions, later for both)
    actor_gradient: Literal["backprop", "reinforce"] = "backprop"
    critic_ema: float = 0.98  # slow critic ← critic_ema · slow + (1 − critic_ema) · critic, every update
    return_decay: float = 0.99
    min_std: float = 0.1
    max_std: float = 1.0
    num_bins: int = 255
    iterations: int = 100_000  # the run's length when no budget is given

    def __post_init__(self) -> None:
        check_numbers(self)
        for name in ("num_envs", "action_repeat", "batch_size", "batch_length", "horizon"):
            if getattr(self, name) < 1:
                raise DvaUsageError(f"{name} = {getattr(self, name)!r} is not allowed; use an int ≥ 1")
        if self.frame_stack != 1:
            raise DvaUsageError(
                f"frame_stack = {self.frame_stack} is not allowed for DreamerV3; use 1 (the RSSM remembers)"
            )
        if self.observation not in ("pixels", "state"):
            raise DvaUsageError(f"observation = {self.observation!r} is not allowed; use 'pixels' or 'state'")
        if self.observation == "pixels" and self.image_size % 16:
            raise DvaUsageError(
                f"image_size = {self.image_size} is not allowed for DreamerV3's 4 stride-2 "
                "convolutions; use a multiple of 16 (e.g. 48, 64)"
            )
        if self.actor_gradient not in ("backprop", "reinforce"):
            raise DvaUsageError(
                f"actor_gradient = {self.actor_gradient!r} is not allowed; use 'backprop' or 'reinforce'"
            )
        if self.train_ratio <= 0:
            raise DvaUsageError(f"train_ratio = {self.train_ratio} is not allowed; use a number > 0")

    @property
    def replayed_per_update(self) -> int:
        return self.batch_size * self.batch_length

    @property
    def collect_steps(self) -> int:
        """Steps of every env per iteration: one update's replayed steps ÷ (ratio × envs), ≥ 1."""
        return max(1, round(self.replayed_per_update / (self.train_ratio * self.num_envs)))

    @property
    def updates(self) -> int:
        """Updates per iteration: the ones that keep ``train_ratio`` (≥ 1)."""
        return max(1, round(self.train_ratio * self.num_envs * self.collect_steps / self.replayed_per_update))


class Latent(struct.PyTreeNode):
    """The RSSM's state per env, with what the next observation step needs (the policy's memory)."""

    deter: jax.Array  # (N, deter)
    stoch: jax.Array  # (N, stoch, classes) one-hot
    action: jax.Array  # (N, A): the action taken from this state
    restart: jax.Array  # (N,) bool: the next observation starts afresh (episode start)


class DreamerState(struct.PyTreeNode):
    """Everything one iteration reads and writes."""

    params: dict  # {"model": {"encoder", "decoder", "rssm", "reward", "cont"}, "actor", "critic"}
    slow_critic: dict
    opt_states: dict  # {"model", "actor", "critic"}
    return_scale: jax.Array
    env: EnvState
    first: jax.Array  # (N,) bool: the current observation starts an episode
    latent: Latent
    replay: object
    episode_return: jax.Array
    key: jax.Array
    iteration: jax.Array


def sample_onehot(logits: jax.Array, key: jax.Array) -> jax.Array:
    """A one-hot sample of each categorical, with the straight-through gradient of its probabilities.

    Sampled by inverting the cumulative distribution: one uniform number per categorical, the
    cumulative sums as a matmul, the class as a count. ``jax.random.categorical`` draws a Gumbel
    number per class and takes an argmax, which XLA's CPU backend runs slowly: on (256, 32, 32)
    logits the whole sample takes 6.2 ms that way and 1.4 ms this way on one core
    (``benchmarks/dreamer_update.py``).
    """
    classes = logits.shape[-1]
    probs = jax.nn.softmax(logits, -1)
    cumulative = probs @ jnp.triu(jnp.ones((classes, classes), probs.dtype))
    uniform = jax.random.uniform(key, probs.shape[:-1] + (1,), probs.dtype)
    index = jnp.minimum(jnp.sum(cumulative < uniform, -1, keepdims=True), classes - 1)
    sample = (jnp.arange(classes) == index).astype(probs.dtype)
    return sample + probs - jax.lax.stop_gradient(probs)


def clip_straight_through(action: jax.Array) -> jax.Array:
    """``action`` clipped to [−1, 1] by a stop-gradient rescaling ``a / sg(max(1, |a|))``, as the
    reference feeds actions to its RSSM: the value of ``jnp.clip``, but a sample outside the box
    still passes (scaled) gradient to the actor, where ``jnp.clip`` would pass none."""
    return action / jax.lax.stop_gradient(jnp.maximum(1.0, jnp.abs(action)))


def features(deter: jax.Array, stoch: jax.Array) -> jax.Array:
    """What the heads read: ``[h, flatten(z)]``."""
    return jnp.concatenate([deter, stoch.reshape(stoch.shape[:-2] + (-1,))], axis=-1)


class DreamerV3:
    """The DreamerV3 agent (an :class:`~dva.algorithms.base.Agent` and
    :class:`~dva.algorithms.base.RecurrentAgent`); see the module docstring."""

    batch_fields = ()  # one device: its replay is not split
    metric_names = (
        "model_loss",
        "reconstruction_loss",
        "reward_loss",
        "kl",
        "actor_loss",
        "critic_loss",
        "return_scale",
        "exploration",
    )

    def __init__(self, env: Env, config: DreamerV3Config) -> None:
        self.pixels = config.observation == "pixels"
        if env.num_envs != config.num_envs or env.frame_stack != 1 or env.has_pixels != self.pixels:
            seen = "renders one frame each" if self.pixels else "renders nothing"
            raise DvaUsageError(
                f"DreamerV3 on {config.observation} needs an env wrapper of {config.num_envs} envs that {seen}"
            )
        self.env, self.task, self.config = env, env.task, config
        cfg, action_dim = config, env.task.action_dim
        if self.pixels:
            self.encoder, self.decoder = ConvEncoder(cfg.cnn_depth), ConvDecoder(cfg.cnn_depth, cfg.image_size)
        else:
            self.encoder = MLPEncoder(cfg.mlp_units, cfg.mlp_layers)
            self.decoder = DreamerMLP(cfg.mlp_units, cfg.mlp_layers, env.task.obs_dim)
        self.rssm = RSSM(cfg.deter, cfg.stoch, cfg.classes, cfg.units)
        self.reward_head = DreamerMLP(cfg.units, cfg.layers, cfg.num_bins, zero_output=True)
        self.cont_head = DreamerMLP(cfg.units, cfg.layers, 1)
        # zero-initialised too: the untrained policy's mean is 0 (noise around standing still), not a
        # constant push that ends every episode at once on tasks that stop when the robot leaves
        # its bounds (Cart-pole's rail)
        self.actor = DreamerMLP(cfg.units, cfg.layers, 2 * action_dim, zero_output=True)
        self.critic = DreamerMLP(cfg.units, cfg.layers, cfg.num_bins, zero_output=True)
        self.bins = symlog_bins(cfg.num_bins)
        self.optimizers = {
            "model": optax.chain(
                optax.clip_by_global_norm(cfg.model_clip), optax.adam(cfg.model_lr, eps=cfg.model_eps)
            ),
            "actor": optax.chain(
                optax.clip_by_global_norm(cfg.actor_critic_clip), optax.adam(cfg.actor_lr, eps=cfg.actor_critic_eps)
            ),
            "critic": optax.chain(
                optax.clip_by_global_norm(cfg.actor_critic_clip), optax.adam(cfg.critic_lr, eps=cfg.actor_critic_eps)
            ),
        }
        self.replay = SequenceReplay(cfg.num_envs, cfg.replay_size, cfg.batch_size, cfg.batch_length)

    @property
    def env_steps_per_iteration(self) -> int:
        return self.config.num_envs * self.config.action_repeat * self.config.collect_steps

    @property
    def default_iterations(self) -> int:
        return self.config.iterations

    @property
    def seed_rounds(self) -> int:
        per_round = self.config.num_envs * self.config.action_repeat
        return seed_rounds(self.config.seed_steps, per_round, self.config.batch_length)

    @property
    def prior_cost(self) -> tuple[float, int]:
        """The seed phase's env steps, taken in :meth:`init` (its time is in the run's clock)."""
        return 0.0, self.seed_rounds * self.config.num_envs * self.config.action_repeat

    # ---- the world model ----------------------------------------------------------------------
    def observed(self, env: EnvState) -> jax.Array:
        """What the model sees of each env (and the replay stores): the frame, or the state."""
        return newest_frame(env) if self.pixels else env.obs

    def encoder_input(self, observed: jax.Array) -> jax.Array:
        """The frame as it is, or the symlog state."""
        return observed if self.pixels else symlog(observed)

    def encode(self, model: dict, observed: jax.Array) -> jax.Array:
        return self.encoder.apply(model["encoder"], self.encoder_input(observed))

    def reconstruction_target(self, observed: jax.Array) -> jax.Array:
        """What the decoder predicts: pixels in the encoder's scale, or the symlog state."""
        return scale_pixels(observed) if self.pixels else symlog(observed)

    def prior(self, model: dict, deter: jax.Array) -> jax.Array:
        return unimix_logits(self.rssm.apply(model["rssm"], deter, method=RSSM.prior), self.config.unimix)

    def posterior(self, model: dict, deter: jax.Array, embedding: jax.Array) -> jax.Array:
        return unimix_logits(
            self.rssm.apply(model["rssm"], deter, embedding, method=RSSM.posterior), self.config.unimix
        )

    def transition(self, model: dict, deter: jax.Array, stoch: jax.Array, action: jax.Array) -> jax.Array:
        return self.rssm.apply(model["rssm"], deter, stoch, action, method=RSSM.transition)

    def observe(self, model: dict, latent: Latent, embedding: jax.Array, restart: jax.Array) -> tuple:
        """One observation step: ``h`` from the previous state and action (zeros where ``restart``)
        and the posterior logits of ``z`` given the image's ``embedding``. Returns ``(h_arrived, h,
        posterior_logits)``, ``h_arrived`` the transition's ``h`` before any restart."""
        arrived = self.transition(model, latent.deter, latent.stoch, latent.action)
        deter = jnp.where(restart[:, None], 0.0, arrived)
        return arrived, deter, self.posterior(model, deter, embedding)

    def observe_sequences(self, model: dict, steps: Step, key: jax.Array):
        """The RSSM along replayed sequences (B, T, …), each from a fresh state: per step the
        posterior state ``(h, z)``, the prior's and the posterior's logits of ``z``, and the
        features of the state the previous action led to (what the reward and continuation heads
        read)."""
        cfg = self.config
        batch, length = steps.first.shape
        embedding = self.encode(model, steps.frame)
        restart = steps.first.at[:, 0].set(True)  # every sequence starts from a fresh state
        prev_action = jnp.concatenate([jnp.zeros_like(steps.action[:, :1]), steps.action[:, :-1]], axis=1)

        def step(carry, inputs):
            embedding_t, restart_t, action_t, key_t = inputs
            latent = Latent(*carry, action=action_t, restart=restart_t)
            arrived, deter, posterior = self.observe(model, latent, embedding_t, restart_t)
            stoch = sample_onehot(posterior, key_t)
            return (deter, stoch), (deter, stoch, posterior, arrived)

        time_major = lambda x: jnp.swapaxes(x, 0, 1)
        initial = (jnp.zeros((batch, cfg.deter)), jnp.zeros((batch, cfg.stoch, cfg.classes)))
        sequence_key, prior_key = jax.random.split(key)
        inputs = (
            time_major(embedding),
            time_major(restart),
            time_major(prev_action),
            jax.random.split(sequence_key, length),
        )
        _, outputs = jax.lax.scan(step, initial, inputs)
        deter, stoch, posterior, arrived = map(time_major, outputs)
        # The priors need no step-by-step loop: one batched pass over all steps (faster than one
        # per step inside the scan). The state the previous action led to is this one within an
        # episode, the prior's guess where the auto-reset replaced that step's frame by the next
        # episode's first.
        prior, arrived_prior = jnp.split(self.prior(model, jnp.concatenate([deter, arrived])), 2)
        arrived_stoch = jnp.where(restart[..., None, None], sample_onehot(arrived_prior, prior_key), stoch)
        return deter, stoch, prior, posterior, features(arrived, arrived_stoch)

    def predicted_reward(self, model: dict, arrived: jax.Array) -> jax.Array:
        """The reward head's prediction for the steps that led to ``arrived`` (features)."""
        return twohot_decode(self.reward_head.apply(model["reward"], arrived), self.bins)

    def world_model_loss(self, model: dict, steps: Step, key: jax.Array):
        """The world-model loss on replayed sequences (B, T, …); also returns the posterior states
        (imagination starts there) and the loss terms."""
        cfg = self.config
        batch, length = steps.first.shape
        deter, stoch, prior, posterior, arrived = self.observe_sequences(model, steps, key)
        error = self.decoder.apply(model["decoder"], features(deter, stoch)) - self.reconstruction_target(steps.frame)
        reconstruction_loss = jnp.sum(error.reshape(batch, length, -1) ** 2, -1)
        dynamics, representation = kl_balance_losses(posterior, prior, cfg.free_nats)
        # the reward and continuation of step t are read from the state it led to (position t + 1)
        reward_logits = self.reward_head.apply(model["reward"], arrived[:, 1:])
        reward_loss = categorical_cross_entropy(reward_logits, twohot(steps.reward[:, :-1], self.bins))
        cont_logit = self.cont_head.apply(model["cont"], arrived[:, 1:])[..., 0]
        cont_loss = optax.sigmoid_binary_cross_entropy(cont_logit, 1.0 - steps.terminated[:, :-1])
        loss = jnp.mean(
            reconstruction_loss + cfg.dynamics_scale * dynamics + cfg.representation_scale * representation
        ) + jnp.mean(reward_loss + cont_loss)
        terms = {
            "reconstruction_loss": jnp.mean(reconstruction_loss),
            "reward_loss": jnp.mean(reward_loss),
            "kl": jnp.mean(dynamics),
        }
        return loss, ((deter, stoch), terms)

    # ---- acting -------------------------------------------------------------------------------
    def action_distribution(self, actor: dict, feature: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The actor's Gaussian: mean ``tanh(·)`` in (−1, 1), std in [min_std, max_std]."""
        cfg = self.config
        mean, raw_std = jnp.split(self.actor.apply(actor, feature), 2, axis=-1)
        return jnp.tanh(mean), cfg.min_std + (cfg.max_std - cfg.min_std) * jax.nn.sigmoid(raw_std + 2.0)

    def initial_memory(self, num_envs: int) -> Latent:
        cfg = self.config
        return Latent(
            deter=jnp.zeros((num_envs, cfg.deter)),
            stoch=jnp.zeros((num_envs, cfg.stoch, cfg.classes)),
            action=jnp.zeros((num_envs, self.task.action_dim)),
            restart=jnp.ones(num_envs, bool),
        )

    def step_latent(self, model: dict, latent: Latent, observed: jax.Array, key: jax.Array) -> Latent:
        """The state after seeing ``observed`` (one frame, or the state, per env): a posterior sample."""
        _, deter, posterior = self.observe(model, latent, self.encode(model, observed), latent.restart)
        return latent.replace(deter=deter, stoch=sample_onehot(posterior, key))

    def act_recurrent(
        self, policy: dict, observation: Observation, memory: Latent, key: jax.Array
    ) -> tuple[jax.Array, Latent]:
        """An action sampled from the actor on a posterior sample, as the 2023 reference evaluates
        (its eval mode samples the actor's Gaussian, as training does); the memory moves on by one
        step.

        The model and the actor only ever see sampled one-hot states and sampled actions; the
        combination of each categorical's most likely class is not such a state when the posterior
        is spread out (on Cart-pole balance, state, one trained policy scored 1102 with that mode
        and 1842 with samples)."""
        latent_key, action_key = jax.random.split(key)
        latent = self.step_latent(policy["model"], memory, observation[self.config.observation], latent_key)
        action = self.sample_action(policy["actor"], features(latent.deter, latent.stoch), action_key)
        return action, latent.replace(action=action, restart=jnp.zeros_like(latent.restart))

    def sample_action(self, actor: dict, feature: jax.Array, key: jax.Array) -> jax.Array:
        """An action from the actor's Gaussian, clipped to the action box."""
        mean, std = self.action_distribution(actor, feature)
        return jnp.clip(mean + std * jax.random.normal(key, mean.shape), -1.0, 1.0)

    def act(self, policy: dict, observation: Observation) -> jax.Array:
        """The action from a fresh memory (as at an episode's first step), with a fixed key."""
        memory = self.initial_memory(len(observation[self.config.observation]))
        return self.act_recurrent(policy, observation, memory, jax.random.PRNGKey(0))[0]

    def policy(self, state: DreamerState) -> dict:
        """The encoder and RSSM (the posterior) and the actor."""
        model = state.params["model"]
        return {"model": {"encoder": model["encoder"], "rssm": model["rssm"]}, "actor": state.params["actor"]}

    # ---- behaviour learning -------------------------------------------------------------------
    def imagine(self, model: dict, actor: dict, deter: jax.Array, stoch: jax.Array, key: jax.Array):
        """``horizon`` prior steps from each start, actions sampled from the actor (reparameterised:
        the samples, and the states they lead to, carry the actor's gradient through the frozen
        model). Returns the features of states 0…H (H + 1, M, F), the actions (H, M, A) and the
        actor's means and stds they were drawn with (H, M, A; their gradient reaches only the actor)."""

        def step(carry, key_t):
            deter, stoch = carry
            action_key, stoch_key = jax.random.split(key_t)
            feature = features(deter, stoch)
            # the actor reads the state without gradient (as the reference does): an action's
            # gradient is its effect on the future through the model, with later actions held
            mean, std = self.action_distribution(actor, jax.lax.stop_gradient(feature))
            action = mean + std * jax.random.normal(action_key, mean.shape)
            deter = self.transition(model, deter, stoch, clip_straight_through(action))
            stoch = sample_onehot(self.prior(model, deter), stoch_key)
            return (deter, stoch), (feature, action, mean, std)

        (deter, stoch), (feats, actions, mean, std) = jax.lax.scan(
            step, (deter, stoch), jax.random.split(key, self.config.horizon)
        )
        return jnp.concatenate([feats, features(deter, stoch)[None]]), actions, mean, std

    def actor_loss(
        self,
        actor: dict,
        model: dict,
        critic: dict,
        return_scale: jax.Array,
        deter: jax.Array,
        stoch: jax.Array,
        key: jax.Array,
    ):
        """The actor's loss on ``horizon`` steps imagined from ``(deter, stoch)`` with the model and
        critic frozen. Also returns what the critic learns from — the features, λ-returns and
        weights, without gradient — the updated return scale and the actor's mean std."""
        cfg = self.config
        feats, actions, mean, std = self.imagine(model, actor, deter, stoch, key)
        reward = self.predicted_reward(model, feats[1:])
        # the continuation's mode, 1 or 0 (the reference's): no gradient, so the actor cannot raise
        # its return by nudging a confident continuation probability that the values multiply
        cont = (self.cont_head.apply(model["cont"], feats[1:])[..., 0] > 0.0).astype(reward.dtype)
        value = twohot_decode(self.critic.apply(critic, feats), self.bins)
        returns = lambda_returns(reward, value, cont, cfg.gamma, cfg.lam)  # (H, M)
        # step t's weight: γ^t times the chance it is reached (the reference's cumprod(γ·cont) / γ;
        # its starts, posterior states of replayed frames, are never terminal here)
        weight = jnp.cumprod(jnp.concatenate([jnp.ones_like(cont[:1]), cfg.gamma * cont[:-1]]), axis=0)
        scale = update_return_scale(return_scale, jax.lax.stop_gradient(returns), cfg.return_decay)
        # the policy's mean and std at the imagined states, read without their gradient: as the
        # actor's own output on sg(features), which imagine already computed
        feats, actions = jax.lax.stop_gradient(feats), jax.lax.stop_gradient(actions)
        if cfg.actor_gradient == "backprop":  # the advantage's own gradient, through the model
            objective = normalized_advantage(returns, value[:-1], scale)
        else:  # REINFORCE: the log-probability of the sampled actions times the advantage
            log_prob = jnp.sum(-0.5 * ((actions - mean) / std) ** 2 - jnp.log(std) - 0.5 * jnp.log(2 * jnp.pi), -1)
            objective = jax.lax.stop_gradient(normalized_advantage(returns, value[:-1], scale)) * log_prob
        entropy = jnp.sum(jnp.log(std) + 0.5 * jnp.log(2 * jnp.pi * jnp.e), -1)
        loss = -jnp.mean(weight * (objective + cfg.entropy * entropy))
        return loss, (feats, jax.lax.stop_gradient(returns), weight, scale, jnp.mean(std))

    def critic_loss(
        self, critic: dict, slow_critic: dict, feats: jax.Array, returns: jax.Array, weight: jax.Array
    ) -> jax.Array:
        """The critic's loss on imagined states ``feats`` (H + 1, M, F; the last has no return):
        per step, weighted by ``weight``, the cross-entropy of its two-hot distribution with the
        two-hot λ-return plus the cross-entropy with the two-hot of the slow critic's value (the
        reference's regulariser towards the critic's EMA, scale 1)."""
        logits = self.critic.apply(critic, feats[:-1])
        slow_value = twohot_decode(self.critic.apply(slow_critic, feats[:-1]), self.bins)
        return jnp.mean(
            weight
            * (
                categorical_cross_entropy(logits, twohot(returns, self.bins))
                + categorical_cross_entropy(logits, twohot(slow_value, self.bins))
            )
        )

    def behaviour_update(
        self,
        params: dict,
        slow_critic: dict,
        opt_states: dict,
        return_scale: jax.Array,
        starts: tuple[jax.Array, jax.Array],
        key: jax.Array,
    ):
        """Actor and critic updates on trajectories imagined from ``starts`` (posterior states)."""
        deter, stoch = (jax.lax.stop_gradient(x.reshape((-1,) + x.shape[2:])) for x in starts)
        model = jax.lax.stop_gradient(params["model"])
        (a_loss, (feats, returns, weight, return_scale, mean_std)), actor_grads = jax.value_and_grad(
            self.actor_loss, has_aux=True
        )(params["actor"], model, params["critic"], return_scale, deter, stoch, key)
        c_loss, critic_grads = jax.value_and_grad(self.critic_loss)(
            params["critic"], slow_critic, feats, returns, weight
        )
        new = {}
        for name, grads in (("actor", actor_grads), ("critic", critic_grads)):
            updates, opt_states[name] = self.optimizers[name].update(grads, opt_states[name], params[name])
            new[name] = optax.apply_updates(params[name], updates)
        slow_critic = optax.incremental_update(new["critic"], slow_critic, 1.0 - self.config.critic_ema)
        metrics = {"actor_loss": a_loss, "critic_loss": c_loss, "return_scale": return_scale, "exploration": mean_std}
        return {**params, **new}, slow_critic, opt_states, return_scale, metrics

    def update(self, state: DreamerState, key: jax.Array) -> tuple[DreamerState, dict]:
        """One world-model update on sampled sequences, then one actor-critic update in imagination."""
        sample_key, model_key, imagine_key = jax.random.split(key, 3)
        steps = self.replay.sample_sequences(state.replay, sample_key)
        params, opt_states = state.params, dict(state.opt_states)
        (model_loss, (starts, terms)), grads = jax.value_and_grad(self.world_model_loss, has_aux=True)(
            params["model"], steps, model_key
        )
        updates, opt_states["model"] = self.optimizers["model"].update(grads, opt_states["model"], params["model"])
        params = {**params, "model": optax.apply_updates(params["model"], updates)}
        params, slow_critic, opt_states, return_scale, metrics = self.behaviour_update(
            params, state.slow_critic, opt_states, state.return_scale, starts, imagine_key
        )
        state = state.replace(params=params, slow_critic=slow_critic, opt_states=opt_states, return_scale=return_scale)
        return state, {"model_loss": model_loss, **terms, **metrics}

    # ---- the loop -----------------------------------------------------------------------------
    def init(self, key: jax.Array) -> DreamerState:
        """Fresh networks and envs, and a replay filled with ``seed_rounds`` uniform random steps."""
        cfg, action_dim = self.config, self.task.action_dim
        env_key, seed_key, key, *net_keys = jax.random.split(key, 10)
        env = self.env.reset(env_key)
        latent = self.initial_memory(cfg.num_envs)
        observed = self.observed(env)[:1]
        encoder = self.encoder.init(net_keys[0], self.encoder_input(observed))
        feature = features(latent.deter[:1], latent.stoch[:1])
        model = {
            "encoder": encoder,
            "decoder": self.decoder.init(net_keys[1], feature),
            "rssm": self.rssm.init(
                net_keys[2],
                latent.deter[:1],
                latent.stoch[:1],
                latent.action[:1],
                self.encode({"encoder": encoder}, observed),
            ),
            "reward": self.reward_head.init(net_keys[3], feature),
            "cont": self.cont_head.init(net_keys[4], feature),
        }
        params = {
            "model": model,
            "actor": self.actor.init(net_keys[5], feature),
            "critic": self.critic.init(net_keys[6], feature),
        }
        state = DreamerState(
            params=params,
            slow_critic=params["critic"],
            opt_states={name: self.optimizers[name].init(params[name]) for name in self.optimizers},
            return_scale=jnp.zeros(()),
            env=env,
            first=jnp.ones(cfg.num_envs, bool),
            latent=latent,
            replay=self.replay.init(empty_step(self.observed(env)[0], action_dim)),
            episode_return=jnp.zeros(cfg.num_envs),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

        state = seed_replay(self.env, self.replay, state, self.seed_rounds, seed_key, stored=self.observed)
        return state.replace(latent=latent)  # the actor starts from a fresh memory

    def iteration(self, state: DreamerState) -> tuple[DreamerState, Metrics]:
        """``collect_steps`` steps of every env with the actor, then ``updates`` updates."""
        key, collect_key, update_key = jax.random.split(state.key, 3)

        def collect_step(state, step_key):
            latent_key, action_key = jax.random.split(step_key)
            latent = self.step_latent(state.params["model"], state.latent, self.observed(state.env), latent_key)
            action = self.sample_action(state.params["actor"], features(latent.deter, latent.stoch), action_key)
            state, finished = collect_into_replay(self.env, self.replay, state, action, stored=self.observed)
            state = state.replace(latent=latent.replace(action=action, restart=state.first))
            return state, (finished, state.first)

        state, (finished, done) = jax.lax.scan(
            collect_step, state, jax.random.split(collect_key, self.config.collect_steps)
        )
        state, losses = jax.lax.scan(self.update, state, jax.random.split(update_key, self.config.updates))
        logged = {name: jnp.mean(value) for name, value in losses.items()}
        metrics = Metrics(all_finite(logged), finished.sum(), done.sum(), logged)
        return state.replace(key=key, iteration=state.iteration + 1), metrics

    def abort_reason(self, logged: dict) -> str:
        return nan_loss_reason(logged, self.metric_names)

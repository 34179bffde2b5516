"""Replay buffers of uint8 frames on the device: sequences for DreamerV3, n-step transitions with
frame stacks for the off-policy pixel baselines (DrQ-v2, CURL).

Built on ``flashbax``'s trajectory buffer (jittable, time-major per env, never samples unwritten
slots). Each env step stores only the newest frame, not the whole stack — a third of the memory
at 3 frames — and sampling rebuilds the stacks from the ``frame_stack − 1`` frames before, restarting
the stack at an episode's first frame exactly as :class:`~dva.envs.observations.PixelObservations` does.
Sampled n-step returns stop at the end of an episode: after a termination the return does not
bootstrap; a window that reaches a time-limit truncation is marked invalid (its next observation
was replaced by the reset), so losses weight it 0.
"""

from __future__ import annotations

import flashbax
import jax
import jax.numpy as jnp
from flax import struct

from dva.errors import DvaUsageError


class Step(struct.PyTreeNode):
    """What one env step stores (leading axes: envs, or batch × sequence when sampled)."""

    # the newest frame (H, W, 3) uint8 of the observation the action was taken in (a state-observing
    # agent's: its state vector)
    frame: jax.Array
    first: jax.Array  # bool: that observation starts an episode
    action: jax.Array  # (A,)
    reward: jax.Array  # reward of the step
    terminated: jax.Array  # bool: the step ended the episode by failure
    truncated: jax.Array  # bool: the step hit the time limit
    # the simulator's state vector of that observation, kept only for a privileged agent's
    # state-prediction loss (None: not kept, no leaves)
    state: jax.Array | None = None


class NStepBatch(struct.PyTreeNode):
    """Sampled transitions ``(o_t, a_t, Σ_{i<n} γ^i r_{t+i}, γ^n·[alive], o_{t+n})``."""

    obs: jax.Array  # (B, H, W, 3·k) uint8
    action: jax.Array  # (B, A)
    reward: jax.Array  # (B,) discounted sum of the rewards up to the episode's end
    discount: jax.Array  # (B,) γ^n if the episode runs past the window, else 0 (no bootstrap)
    next_obs: jax.Array  # (B, H, W, 3·k) uint8
    valid: jax.Array  # (B,) False where the window reaches a time-limit truncation
    state: jax.Array | None = None  # (B, obs_dim) the state of ``obs`` where the replay keeps it


def stack_at(frames: jax.Array, first: jax.Array, position: int, frame_stack: int) -> jax.Array:
    """The frame stack of the observation at ``position`` of one sampled sequence (L, H, W, 3):
    the ``frame_stack`` frames up to it, where an episode started inside that window its first
    frame repeated in place of the earlier ones."""
    window = jnp.arange(position - frame_stack + 1, position + 1)
    start = jnp.max(jnp.where(first[window], window, window[0]))  # the window's latest episode start
    return jnp.concatenate(list(frames[jnp.maximum(window, start)]), axis=-1)


class SequenceReplay:
    """``capacity`` steps over ``num_envs`` envs (``flashbax``'s trajectory buffer, time-major per
    env); samples ``batch_size`` sequences of ``length`` consecutive steps of one env."""

    def __init__(self, num_envs: int, capacity: int, batch_size: int, length: int) -> None:
        if capacity // num_envs < length:
            raise DvaUsageError(
                f"replay capacity {capacity} is too small for {num_envs} envs × {length}-step sequences"
            )
        self.sequence_length = length
        self.buffer = flashbax.make_trajectory_buffer(
            add_batch_size=num_envs,
            sample_batch_size=batch_size,
            sample_sequence_length=length,
            period=1,
            min_length_time_axis=length,
            max_length_time_axis=capacity // num_envs,
        )

    def init(self, example: Step):
        """An empty buffer for steps shaped like ``example`` (one env's step, no leading axis)."""
        return self.buffer.init(example)

    def add(self, state, step: Step):
        """Append one step of every env (leading axis: envs)."""
        return self.buffer.add(state, jax.tree.map(lambda x: x[:, None], step))

    def can_sample(self, state) -> jax.Array:
        return self.buffer.can_sample(state)

    def sample_sequences(self, state, key: jax.Array) -> Step:
        """``batch_size`` sequences: every leaf shaped (B, length, …)."""
        return self.buffer.sample(state, key).experience


class FrameReplay(SequenceReplay):
    """A :class:`SequenceReplay` of single frames that samples ``batch_size`` n-step transitions
    with their frame stacks rebuilt."""

    def __init__(
        self, num_envs: int, capacity: int, batch_size: int, frame_stack: int, n_step: int, gamma: float
    ) -> None:
        self.frame_stack, self.n_step, self.gamma = frame_stack, n_step, gamma
        super().__init__(num_envs, capacity, batch_size, frame_stack - 1 + n_step + 1)

    def sample(self, state, key: jax.Array) -> NStepBatch:
        return jax.vmap(self.transition)(self.sample_sequences(state, key))

    def transition(self, steps: Step) -> NStepBatch:
        """The n-step transition from the observation at position ``frame_stack − 1`` of one sequence."""
        t = self.frame_stack - 1
        reward, alive, valid = jnp.zeros(()), jnp.ones((), bool), jnp.ones((), bool)
        for i in range(self.n_step):
            reward = reward + jnp.where(alive, self.gamma**i * steps.reward[t + i], 0.0)
            valid = valid & ~(alive & steps.truncated[t + i])
            alive = alive & ~(steps.terminated[t + i] | steps.truncated[t + i])
        return NStepBatch(
            obs=stack_at(steps.frame, steps.first, t, self.frame_stack),
            action=steps.action[t],
            reward=reward,
            discount=jnp.where(alive, self.gamma**self.n_step, 0.0),
            next_obs=stack_at(steps.frame, steps.first, t + self.n_step, self.frame_stack),
            valid=valid,
            state=None if steps.state is None else steps.state[t],
        )

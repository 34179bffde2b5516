"""How an algorithm observes a task: the environment and renderer protocols, and the pixel-observation
wrapper that makes this project's tasks an environment.

Algorithms never call a renderer themselves. They step a :class:`PixelObservations` wrapper, which
renders after every reset and step, keeps a stack of the last ``frame_stack`` frames in
``EnvState.pixels`` and hands out observations as ``{"state": …, "pixels": …}``. Any renderer
with the :class:`Renderer` interface works: MuJoCo's Warp ray-tracer
(:class:`~dva.envs.rendering.PixelRenderer`, uint8, not differentiable) or the pure-JAX
:class:`~dva.envs.soft_rendering.SoftRenderer` (float, differentiable).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from dva.envs.rendering import push_frame, reset_frame_stack
from dva.errors import DvaUsageError
from dva.tasks.base import EnvState, Task


class Renderer(Protocol):
    """Renders a batch of ``qpos`` (num_envs, nq) from the task's pixel camera: (num_envs, H, W, 3)."""

    num_envs: int
    differentiable: bool  # whether gradients flow from the pixels back to qpos

    def __call__(self, qpos: jax.Array) -> jax.Array: ...


Observation = dict[str, jax.Array]  # {"state": (N, obs_dim), "pixels": (N, H, W, 3·k) or (N, 0)}


class TaskInfo(Protocol):
    """What an agent may read of any environment's task: its name, sizes and contact model."""

    @property
    def name(self) -> str: ...
    @property
    def obs_dim(self) -> int: ...
    @property
    def action_dim(self) -> int: ...
    @property
    def episode_length(self) -> int: ...
    @property
    def physics(self) -> str: ...


class Env(Protocol):
    """A batch of ``num_envs`` environments behind pure, jittable ``reset`` and ``step`` over an
    :class:`~dva.tasks.base.EnvState` (its ``frames`` the stack of the last ``frame_stack`` frames,
    each action held ``action_repeat`` control steps). What every agent trains in: this project's
    tasks (:class:`PixelObservations`) and dm_control's (:class:`~dva.envs.dmc.DMCEnv`) alike.
    :mod:`dva.envs.factory` makes one from a task name."""

    num_envs: int
    frame_stack: int
    action_repeat: int

    @property
    def task(self) -> TaskInfo: ...
    @property
    def episode_steps(self) -> int: ...
    @property
    def has_pixels(self) -> bool: ...
    def reset(self, key: jax.Array) -> EnvState: ...
    def step(self, env: EnvState, action: jax.Array) -> EnvState: ...
    def observe(self, env: EnvState) -> Observation: ...
    def evaluation_env(self) -> Env: ...


@runtime_checkable
class DifferentiableEnv(Env, Protocol):
    """An :class:`Env` whose ``step`` JAX can differentiate (this project's tasks on MJX), with
    the task itself (its model, for rendering and kinematics) and the renderer, if any: what the
    short-horizon actor-critic family needs. dm_control's environments are not one."""

    @property
    def task(self) -> Task: ...
    @property
    def renderer(self) -> Renderer | None: ...
    @property
    def differentiable_pixels(self) -> bool: ...


def check_stacking(frame_stack: int, action_repeat: int) -> None:
    """Frames stacked and control steps per action must be whole numbers ≥ 1."""
    for name, value in (("frame_stack", frame_stack), ("action_repeat", action_repeat)):
        if not isinstance(value, int) or value < 1:
            raise DvaUsageError(f"{name} {value!r} is not allowed; use an int ≥ 1")


class PixelObservations:
    """``num_envs`` copies of ``task`` observed through ``renderer`` with ``frame_stack`` frames,
    each action held for ``action_repeat`` control steps.

    Pure and jittable like the task itself: ``reset(key)`` and ``step(env, action)`` return an
    :class:`EnvState` whose ``pixels`` hold the frame stack (restarted, first frame tiled, where an
    episode restarts). Without a renderer the pixels are an empty (N, 0) array, so state-only and
    pixel algorithms share one code path. With ``action_repeat`` k > 1 (DrQ-v2, CURL) one step
    renders once after k control steps and its reward is their sum up to the episode's end;
    where an episode ends before the k-th, the remaining control steps run in the next episode
    (their rewards are not counted).
    """

    def __init__(
        self,
        task: Task,
        num_envs: int,
        renderer: Renderer | None = None,
        frame_stack: int = 3,
        action_repeat: int = 1,
        evaluation: PixelObservations | None = None,
    ) -> None:
        if renderer is not None and renderer.num_envs != num_envs:
            raise DvaUsageError(f"the renderer draws {renderer.num_envs} envs; this wrapper needs {num_envs}")
        check_stacking(frame_stack, action_repeat)
        self.task, self.num_envs, self.renderer = task, num_envs, renderer
        self.frame_stack, self.action_repeat = frame_stack, action_repeat
        self.evaluation = evaluation

    @property
    def episode_steps(self) -> int:
        """Steps of this wrapper in one full episode (control steps ÷ action repeat, rounded up)."""
        return -(-self.task.episode_length // self.action_repeat)

    @property
    def has_pixels(self) -> bool:
        return self.renderer is not None

    def evaluation_env(self) -> PixelObservations:
        """The env evaluations run on: ``evaluation`` if given (a batch of its own size), else this
        one (its state is the caller's, so evaluating leaves training's episodes as they were)."""
        return self.evaluation or self

    @property
    def differentiable_pixels(self) -> bool:
        return self.renderer is not None and self.renderer.differentiable

    def reset(self, key: jax.Array) -> EnvState:
        """Fresh episodes with their first frame stacks."""
        env = self.task.reset(key, self.num_envs)
        if self.renderer is None:
            return env.replace(pixels=jnp.zeros((self.num_envs, 0), jnp.uint8))
        return env.replace(pixels=reset_frame_stack(self.renderer(env.data.qpos), self.frame_stack))

    def step(self, env: EnvState, action: jax.Array) -> EnvState:
        """``action_repeat`` control steps of the task, then the new frame pushed onto the stack."""
        env = self.task.step(env, action)
        if self.action_repeat > 1:
            env = self._repeat(env, action)
        if self.renderer is None:
            return env
        return env.replace(pixels=push_frame(env.frames, self.renderer(env.data.qpos), env.done))

    def _repeat(self, env: EnvState, action: jax.Array) -> EnvState:
        """The remaining control steps of one repeated action: rewards summed and the end flags
        and final observation kept from the step where the episode ended."""
        reward, terminated, truncated = env.reward, env.terminated, env.truncated
        final_obs, final_qpos = env.final_obs, env.final_qpos
        for _ in range(self.action_repeat - 1):
            env = self.task.step(env, action)
            running = ~(terminated | truncated)
            reward = reward + jnp.where(running, env.reward, 0.0)
            final_obs = jnp.where(running[:, None], env.final_obs, final_obs)
            final_qpos = jnp.where(running[:, None], env.final_qpos, final_qpos)
            terminated, truncated = terminated | (running & env.terminated), truncated | (running & env.truncated)
        return env.replace(
            reward=reward, terminated=terminated, truncated=truncated, final_obs=final_obs, final_qpos=final_qpos
        )

    @staticmethod
    def observe(env: EnvState) -> Observation:
        """What a policy may look at."""
        return {"state": env.obs, "pixels": env.frames}

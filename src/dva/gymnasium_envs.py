"""Every task as a Gymnasium 1.x environment: ``dva/<task>-v0``, registered on ``import dva``.

``gymnasium.make_vec("dva/hopper-v0", num_envs=16)`` builds a :class:`DvaVectorEnv`: the whole
batch steps in one jitted call (physics, auto-reset, rendering and frame stack) and stays on the
device between calls; observations, rewards and flags come out as NumPy arrays, or as JAX arrays
with ``array_type="jax"``. ``gymnasium.make("dva/hopper-v0")`` is one environment of it.

Keyword arguments of both: ``obs_type`` ``"state"`` (the task's state vector, float32),
``"pixels"`` (the stacked camera frames, ``Box(0, 255, (H, W, 3·frame_stack), uint8)``) or
``"both"`` (a ``Dict`` of the two); ``image_size`` and ``frame_stack`` of the pixels; ``physics``
(the contact model, ``penalty`` or ``mujoco``); ``render_mode="rgb_array"`` with ``render_size``.
Actions are in ``[-1, 1]`` (clipped). Episodes end by termination (the task's failure test) or
truncation at the task's episode length. The vector env resets finished sub-environments in the
same step (``AutoresetMode.SAME_STEP``): the returned observation is the next episode's first,
and ``info["final_obs"]`` (valid where ``info["_final_obs"]``) is the one the step reached.
"""

from __future__ import annotations

from typing import Any, Literal

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

ObsType = Literal["state", "pixels", "both"]
OBS_TYPES: tuple[str, ...] = ("state", "pixels", "both")
ARRAY_TYPES: tuple[str, ...] = ("numpy", "jax")
# The names of dva.tasks.TASKS (a test keeps them equal), so that registering on ``import dva``
# does not import MuJoCo: the task modules load when an environment is made.
TASK_NAMES: tuple[str, ...] = (
    "cartpole_swingup",
    "cartpole_balance",
    "hopper",
    "cheetah",
    "ant",
    "humanoid",
    "quadruped",
)


def env_id(task: str) -> str:
    """The Gymnasium id of ``task``."""
    return f"dva/{task}-v0"


def register_envs() -> None:
    """Register ``dva/<task>-v0`` for every task (again-safe)."""
    for task in TASK_NAMES:
        if env_id(task) not in gymnasium.registry:
            gymnasium.register(
                id=env_id(task),
                entry_point="dva.gymnasium_envs:DvaEnv",
                vector_entry_point="dva.gymnasium_envs:DvaVectorEnv",
                kwargs={"task": task},
                disable_env_checker=True,  # the checker's NumPy probes would each compile a step
            )


class DvaVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` copies of a dva task behind Gymnasium's vector API; see the module docstring."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"], "render_fps": 60}

    def __init__(
        self,
        task: str,
        num_envs: int = 1,
        obs_type: ObsType = "state",
        image_size: int = 84,
        frame_stack: int = 3,
        physics: str | None = None,
        render_mode: str | None = None,
        render_size: int = 256,
        array_type: str = "numpy",
    ) -> None:
        if obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type {obs_type!r} is not allowed; use one of {', '.join(OBS_TYPES)}")
        if array_type not in ARRAY_TYPES:
            raise ValueError(f"array_type {array_type!r} is not allowed; use one of {', '.join(ARRAY_TYPES)}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r} is not allowed; use None or 'rgb_array'")
        from dva.envs import PixelObservations
        from dva.rendering import PixelRenderer
        from dva.tasks import make_task

        self.task = make_task(task, physics)
        renderer = None
        if obs_type != "state":
            renderer = PixelRenderer(self.task, num_envs, image_size)
        self.env = PixelObservations(self.task, num_envs, renderer, frame_stack)
        self.num_envs, self.obs_type, self.array_type = num_envs, obs_type, array_type
        self.render_mode, self.render_size = render_mode, render_size
        self._view_renderer = None

        state_space = spaces.Box(-np.inf, np.inf, (self.task.obs_dim,), np.float32)
        pixel_space = spaces.Box(0, 255, (image_size, image_size, 3 * frame_stack), np.uint8)
        self.single_observation_space = {
            "state": state_space,
            "pixels": pixel_space,
            "both": spaces.Dict({"state": state_space, "pixels": pixel_space}),
        }[obs_type]
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.task.action_dim,), np.float32)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)

        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self._step_and_observe)
        self._state = None
        self._key = None

    # ---- the jitted pieces ----------------------------------------------------------------------
    def _observation(self, state: jax.Array, pixels: jax.Array) -> Any:
        return {"state": state, "pixels": pixels, "both": {"state": state, "pixels": pixels}}[self.obs_type]

    def _step_and_observe(self, env, action):
        from dva.rendering import push_frame

        before = env.pixels
        env = self.env.step(env, action)
        final_pixels = env.pixels
        if self.env.has_pixels:
            # Where an episode ended the returned stack restarts; the one the step reached is the
            # previous stack plus a frame of the final pose, rendered only when some episode ended.
            def reached(env):
                return push_frame(before, self.env.renderer(env.final_qpos), jnp.zeros_like(env.done))

            final_pixels = jax.lax.cond(jnp.any(env.done), reached, lambda env: env.pixels, env)
        return env, self._observation(env.obs, env.pixels), self._observation(env.final_obs, final_pixels)

    # ---- Gymnasium's API ------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start every sub-environment anew: ``(obs, info)``. ``seed`` makes the episodes, and all
        the automatic resets after them, reproducible."""
        if options:
            raise ValueError(f"options {options!r} are not supported; dva envs take no reset options")
        super().reset(seed=seed)  # seeds self.np_random
        if seed is not None or self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31)) if seed is None else seed)
        self._key, key = jax.random.split(self._key)
        self._state = self._reset(key)
        return self._out(self._observation(self._state.obs, self._state.pixels)), {}

    def step(self, actions):
        """One control step of every sub-environment: ``(obs, reward, terminated, truncated, info)``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, np.float32) if self.array_type == "numpy" else jnp.asarray(actions, jnp.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions have shape {actions.shape}; this env needs {self.action_space.shape}")
        if self.array_type == "numpy" and not np.isfinite(actions).all():
            raise ValueError(f"actions contain non-finite values (NaN or inf): {actions}")
        self._state, obs, final_obs = self._step(self._state, actions)
        state = self._state
        done = np.asarray(state.done)
        info = {}
        if done.any():
            info = {"final_obs": self._out(final_obs), "_final_obs": done}
        return self._out(obs), self._out(state.reward), self._out(state.terminated), self._out(state.truncated), info

    def render(self) -> np.ndarray | None:
        """``render_mode="rgb_array"``: every sub-environment's view from the task's camera,
        ``(num_envs, render_size, render_size, 3)`` uint8."""
        if self.render_mode is None or self._state is None:
            return None
        if self._view_renderer is None:
            from dva.rendering import PixelRenderer

            self._view_renderer = PixelRenderer(self.task, self.num_envs, self.render_size)
            self._render = jax.jit(self._view_renderer.__call__)
        return np.asarray(self._render(self._state.data.qpos))

    def _out(self, tree):
        return tree if self.array_type == "jax" else jax.tree.map(np.asarray, tree)


class DvaEnv(gymnasium.Env):
    """One dva environment (``gymnasium.make("dva/<task>-v0")``): a :class:`DvaVectorEnv` of one,
    whose step returns the observation an ending step reached and leaves the reset to the caller."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 60}

    def __init__(self, task: str, **kwargs) -> None:
        self.vector = DvaVectorEnv(task, num_envs=1, **kwargs)
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space
        self.render_mode = self.vector.render_mode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)  # seeds self.np_random, as Gymnasium's contract asks
        obs, info = self.vector.reset(seed=seed, options=options)
        return _first(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.vector.step(np.asarray(action)[None])
        if "final_obs" in info:
            obs = info["final_obs"]
        return _first(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), {}

    def render(self) -> np.ndarray | None:
        frames = self.vector.render()
        return None if frames is None else frames[0]


def _first(tree):
    return jax.tree.map(lambda x: x[0], tree)

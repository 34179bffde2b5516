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
truncation at the task's episode length. ``autoreset_mode`` says what the vector env does with a
finished sub-environment, as Gymnasium defines it:

- ``NEXT_STEP`` (the default, Gymnasium's): the step that ends an episode returns the observation
  it reached; the next step resets that sub-environment instead of stepping it (its action is
  ignored) and returns the new episode's first observation with reward 0 and both flags False.
- ``SAME_STEP``: the step that ends an episode returns the next episode's first observation, and
  ``info["final_obs"]`` (valid where ``info["_final_obs"]``) is the one the step reached.
- ``DISABLED``: the step that ends an episode returns the observation it reached; the caller
  resets it with ``reset(options={"reset_mask": mask})``.

With pixels, the frame stack an ending step reached is the previous stack plus a frame of the
final pose; a new episode's stack is its first frame repeated.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from dva.errors import DvaUsageError
from dva.tasks import task_names

if TYPE_CHECKING:  # the tasks load MuJoCo: imported when an env is made, not with dva
    from dva.tasks.base import EnvState

ObsType = Literal["state", "pixels", "both"]
OBS_TYPES: tuple[str, ...] = ("state", "pixels", "both")
ARRAY_TYPES: tuple[str, ...] = ("numpy", "jax")


def autoreset_mode_of(value: AutoresetMode | str) -> AutoresetMode:
    """An :class:`AutoresetMode` from itself, its name (``"NEXT_STEP"``) or its value (``"NextStep"``)."""
    for mode in AutoresetMode:
        if value in (mode, mode.name, mode.value):
            return mode
    allowed = ", ".join(mode.name for mode in AutoresetMode)
    raise DvaUsageError(
        f"autoreset_mode {value!r} is not allowed; use one of {allowed} (gymnasium.vector.AutoresetMode)"
    )


def env_id(task: str) -> str:
    """The Gymnasium id of ``task``."""
    return f"dva/{task}-v0"


def register_envs() -> None:
    """Register ``dva/<task>-v0`` for every task, those added with :func:`dva.register_task` too
    (again-safe)."""
    for task in task_names():
        if env_id(task) not in gymnasium.registry:
            gymnasium.register(
                id=env_id(task),
                entry_point="dva.envs.gymnasium:DvaEnv",
                vector_entry_point="dva.envs.gymnasium:DvaVectorEnv",
                kwargs={"task": task},
                disable_env_checker=True,  # the checker's NumPy probes would each compile a step
            )


class DvaVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` copies of a dva task behind Gymnasium's vector API; see the module docstring."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 60}

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
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ) -> None:
        self.autoreset_mode = autoreset_mode_of(autoreset_mode)
        self.metadata = {**self.metadata, "autoreset_mode": self.autoreset_mode}
        if obs_type not in OBS_TYPES:
            raise DvaUsageError(f"obs_type {obs_type!r} is not allowed; use one of {', '.join(OBS_TYPES)}")
        if array_type not in ARRAY_TYPES:
            raise DvaUsageError(f"array_type {array_type!r} is not allowed; use one of {', '.join(ARRAY_TYPES)}")
        if render_mode not in (None, "rgb_array"):
            raise DvaUsageError(f"render_mode {render_mode!r} is not allowed; use None or 'rgb_array'")
        # MuJoCo and MJX load with the first environment made, not with `import dva`.
        from dva.envs.factory import make_env
        from dva.envs.observations import DifferentiableEnv

        env = make_env(
            task,
            num_envs,
            renderer=None if obs_type == "state" else "warp",
            image_size=image_size,
            frame_stack=frame_stack,
            physics=physics,
            evaluation_episodes=None,  # Gymnasium's users evaluate on their own
        )
        assert isinstance(env, DifferentiableEnv)  # a dva/<task>-v0 id names one of this project's tasks
        self.env, self.task = env, env.task
        self.num_envs, self.obs_type, self.array_type = num_envs, obs_type, array_type
        self.render_mode, self.render_size = render_mode, render_size
        self._render_views: Callable[[jax.Array], jax.Array] | None = None  # made on the first render()

        state_space = spaces.Box(-np.inf, np.inf, (self.task.obs_dim,), np.float32)
        pixel_space = spaces.Box(0, 255, (image_size, image_size, 3 * frame_stack), np.uint8)
        spaces_by_type: dict[str, spaces.Space] = {
            "state": state_space,
            "pixels": pixel_space,
            "both": spaces.Dict({"state": state_space, "pixels": pixel_space}),
        }
        self.single_observation_space = spaces_by_type[obs_type]
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.task.action_dim,), np.float32)
        self.observation_space = gymnasium.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(self.single_action_space, num_envs)

        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self._step_and_observe, static_argnums=3)
        self._state: EnvState | None = None
        self._key: jax.Array | None = None
        self._held = np.zeros(num_envs, bool)  # NEXT_STEP: reset on the next step instead of stepping

    # ---- the jitted pieces ----------------------------------------------------------------------
    def _observation(self, state: jax.Array, pixels: jax.Array) -> Any:
        return {"state": state, "pixels": pixels, "both": {"state": state, "pixels": pixels}}[self.obs_type]

    def _step_and_observe(self, env, action, held, return_reached: bool):
        """Step every sub-environment but the ``held`` ones (NEXT_STEP's reset step: their state
        already holds the new episode, which this step returns with reward 0 and no flags).
        Returns the state, the observation to return (with ``return_reached``, the one an ending
        step reached) and the one each step reached."""
        from dva.envs.rendering import push_frame  # loads MuJoCo: here, once an env exists

        stepped = self.env.step(env, action)
        reached_pixels = stepped.frames
        if self.env.has_pixels:
            # Where an episode ended the stack restarts; the one the step reached is the previous
            # stack plus a frame of the final pose, rendered only when some episode ended.
            def reached(stepped):
                return push_frame(env.frames, self.env.renderer(stepped.final_qpos), jnp.zeros_like(stepped.done))

            reached_pixels = jax.lax.cond(jnp.any(stepped.done), reached, lambda stepped: stepped.frames, stepped)
        unchanged = env.replace(
            reward=jnp.zeros_like(env.reward),
            terminated=jnp.zeros_like(env.terminated),
            truncated=jnp.zeros_like(env.truncated),
        )
        env = select(held, unchanged, stepped)
        obs = self._observation(env.obs, env.frames)
        final = self._observation(stepped.final_obs, reached_pixels)
        if return_reached:
            obs = select(env.done, final, obs)
        return env, obs, final

    # ---- Gymnasium's API ------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start every sub-environment anew, or with ``options={"reset_mask": mask}`` only those
        where ``mask`` is True: ``(obs, info)``. ``seed`` makes the episodes, and all the
        automatic resets after them, reproducible."""
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if options:
            raise DvaUsageError(f"reset options {sorted(options)} are not supported; use reset_mask (or none)")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != bool:
                raise DvaUsageError(
                    f"reset_mask must be a bool array of shape ({self.num_envs},); got {mask.dtype} {mask.shape}"
                )
            if self._state is None:
                raise RuntimeError("call reset() without a reset_mask first")
        super().reset(seed=seed)  # seeds self.np_random
        if seed is not None or self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31)) if seed is None else seed)
        self._key, key = jax.random.split(self._key)
        fresh = self._reset(key)
        self._state = fresh if mask is None else select(jnp.asarray(mask), fresh, self._state)
        self._held = np.zeros(self.num_envs, bool) if mask is None else self._held & ~mask
        return self._out(self._observation(self._state.obs, self._state.frames)), {}

    def step(self, actions):
        """One control step of every sub-environment: ``(obs, reward, terminated, truncated, info)``."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, np.float32) if self.array_type == "numpy" else jnp.asarray(actions, jnp.float32)
        if actions.shape != self.action_space.shape:
            raise DvaUsageError(f"actions have shape {actions.shape}; this env needs {self.action_space.shape}")
        if self.array_type == "numpy" and not np.isfinite(actions).all():
            raise DvaUsageError(f"actions contain non-finite values (NaN or inf): {actions}")
        same_step = self.autoreset_mode == AutoresetMode.SAME_STEP
        self._state, obs, final_obs = self._step(self._state, actions, jnp.asarray(self._held), not same_step)
        state = self._state
        done = np.asarray(state.done)
        info = {}
        if same_step and done.any():
            info = {"final_obs": self._out(final_obs), "_final_obs": done}
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            self._held = done
        return self._out(obs), self._out(state.reward), self._out(state.terminated), self._out(state.truncated), info

    def render(self) -> tuple[np.ndarray, ...] | None:
        """``render_mode="rgb_array"``: every sub-environment's view from the task's camera, one
        ``(render_size, render_size, 3)`` uint8 frame each (a tuple, as Gymnasium's vector envs)."""
        if self.render_mode is None or self._state is None:
            return None
        if self._render_views is None:
            from dva.envs.rendering import PixelRenderer  # MuJoCo and Warp: once an env renders

            self._render_views = jax.jit(PixelRenderer(self.task, self.num_envs, self.render_size).__call__)
        return tuple(np.asarray(self._render_views(self._state.data.qpos)))

    def _out(self, tree):
        return tree if self.array_type == "jax" else jax.tree.map(np.asarray, tree)


class DvaEnv(gymnasium.Env):
    """One dva environment (``gymnasium.make("dva/<task>-v0")``): a :class:`DvaVectorEnv` of one,
    whose step returns the observation an ending step reached and leaves the reset to the caller."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 60}

    def __init__(self, task: str, **kwargs) -> None:
        self.vector = DvaVectorEnv(task, num_envs=1, autoreset_mode=AutoresetMode.DISABLED, **kwargs)
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space
        self.render_mode = self.vector.render_mode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)  # seeds self.np_random, as Gymnasium's contract asks
        obs, info = self.vector.reset(seed=seed, options=options)
        return _first(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, _ = self.vector.step(np.asarray(action)[None])
        return _first(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), {}

    def render(self) -> np.ndarray | None:
        frames = self.vector.render()
        return None if frames is None else frames[0]


def select(mask: jax.Array, on_true, on_false):
    """Per sub-environment, ``on_true`` where ``mask`` else ``on_false`` (trees of batched arrays)."""

    def one(a, b):
        return jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b)

    return jax.tree.map(one, on_true, on_false)


def _first(tree):
    return jax.tree.map(lambda x: x[0], tree)

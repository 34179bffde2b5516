"""dm_control's own tasks for the baselines, as their authors ran them: ``dmc:<domain>-<task>``
(``dva train --task dmc:cartpole-swingup --algo drqv2``).

The ``dmc`` extra (``pip install 'dva[dmc]'``). dm_control steps its MuJoCo physics on the host
and draws its frames with MuJoCo's OpenGL renderer (EGL, headless; ``MUJOCO_GL`` overrides), so
:class:`DMCEnv` runs a batch of its environments on the host, reached from the agents' jitted
iterations through :func:`jax.experimental.io_callback`. It offers what the off-policy and
model-based agents use of :class:`~dva.envs.observations.PixelObservations` — ``reset``,
``step``, ``observe``, the frame stack and the action repeat — and keeps the frame stack on the
device as that wrapper does. The state observation is dm_control's observation dict flattened in
its order; the frame is the reference's camera (DrQ-v2's: 2 on quadruped, else 0). Episodes are
dm_control's: 1000 control steps, never terminated early.

The host environments are this process's: an evaluation runs on its own batch
(:meth:`DMCEnv.evaluation_env`), so it never disturbs the training episodes; a resumed run's first
step starts fresh episodes and marks the old ones truncated. MuJoCo 4 dropped some flex fields
that dm_control 1.0.50 still indexes; the import drops them from dm_control's index table (no
suite task has a flex).
"""

from __future__ import annotations

import atexit
import concurrent.futures
import dataclasses
import functools
import os
import queue
import threading
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from jax.experimental import io_callback

from dva.envs.observations import Observation, check_stacking
from dva.envs.rendering import push_frame, reset_frame_stack
from dva.errors import DvaUsageError
from dva.tasks.base import EnvState

EPISODE_LENGTH = 1000  # control steps: every suite task's time limit
CAMERAS = {"quadruped": 2}  # the camera each domain is seen from (DrQ-v2's choice), else 0
# The suite's 2048² shadow map is most of a small frame's cost on a CPU's software OpenGL; at 8
# shadow texels per frame pixel (at least 512) cartpole's 48² and 84² frames come out the same
# but for a few shadow-edge pixels (≈ 0.005 %), and a 16-env step at 48² takes 0.35 s, not 0.65.
SHADOW_TEXELS_PER_PIXEL, MIN_SHADOW_SIZE = 8, 512
DMC_PREFIX = "dmc:"  # dm_control's tasks are named dmc:<domain>-<task>, e.g. dmc:ball_in_cup-catch


def is_dmc(name: str) -> bool:
    """Whether ``name`` names a dm_control task."""
    return name.startswith(DMC_PREFIX)


def dmc_domain_task(name: str) -> tuple[str, str]:
    """dm_control's (domain, task) of ``dmc:<domain>-<task>`` (its task names use ``_``)."""
    domain, _, task = name.removeprefix(DMC_PREFIX).partition("-")
    return domain, task.replace("-", "_")


@functools.cache
def dm_control_suite() -> Any:
    """dm_control's suite, imported on first use with the EGL renderer unless ``MUJOCO_GL`` is set."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # read when dm_control is imported
    try:  # the 'dmc' extra, imported only for a dmc: task
        from dm_control.mujoco.wrapper.mjbindings import sizes
    except ImportError:
        raise ImportError("dm_control tasks need the 'dmc' extra: pip install 'dva[dmc]'") from None
    for struct_name, mujoco_type in (("mjmodel", mujoco.MjModel), ("mjdata", mujoco.MjData)):
        table = sizes.array_sizes[struct_name]
        for field in [field for field in table if not hasattr(mujoco_type, field)]:
            del table[field]
    from dm_control import suite  # after the table is patched: importing the suite reads it

    return suite


@dataclasses.dataclass(frozen=True)
class DMCTask:
    """What the agents read of a task, for a dm_control one."""

    name: str
    domain: str
    task: str
    obs_dim: int
    action_dim: int
    episode_length: int = EPISODE_LENGTH
    physics: str = "dm_control"

    @property
    def camera(self) -> int:
        return CAMERAS.get(self.domain, 0)

    def load(self, seed: int, image_size: int | None = None) -> Any:
        """One dm_control environment of this task, its randomness seeded with ``seed``; with
        ``image_size``, its shadow map sized for frames of that size (set before its first frame
        creates the OpenGL context that allocates it)."""
        env = dm_control_suite().load(self.domain, self.task, task_kwargs={"random": seed})
        if image_size is not None:
            quality = env.physics.model.vis.quality
            quality.shadowsize = min(quality.shadowsize, max(MIN_SHADOW_SIZE, SHADOW_TEXELS_PER_PIXEL * image_size))
        return env


@functools.cache
def make_dmc_task(name: str) -> DMCTask:
    """The dm_control task ``dmc:<domain>-<task>``; a one-line error names the tasks there are."""
    suite = dm_control_suite()
    domain, task = dmc_domain_task(name)
    if (domain, task) not in suite.ALL_TASKS:
        choices = ", ".join(f"{DMC_PREFIX}{d}-{t.replace('_', '-')}" for d, t in suite.ALL_TASKS)
        raise DvaUsageError(f"unknown dm_control task {name!r}; choose one of: {choices}")
    env = suite.load(domain, task, task_kwargs={"random": 0})
    obs_dim = sum(int(np.prod(spec.shape)) for spec in env.observation_spec().values())
    return DMCTask(name, domain, task, obs_dim, int(np.prod(env.action_spec().shape)))


def flat_observation(observation: dict) -> np.ndarray:
    """dm_control's observation dict as one float32 vector, in the dict's order."""
    return np.concatenate([np.asarray(value, np.float32).ravel() for value in observation.values()])


class HostEnvs:
    """``num_envs`` dm_control environments stepped on the host, each action held for
    ``action_repeat`` control steps (the reward summed up to the episode's end), each episode
    restarted where it ends. All their work runs on one thread of their own: an OpenGL context is
    current on one thread, and JAX calls back from whichever of its threads is free."""

    def __init__(self, task: DMCTask, num_envs: int, image_size: int | None, action_repeat: int) -> None:
        self.task, self.num_envs, self.image_size, self.action_repeat = task, num_envs, image_size, action_repeat
        self.envs: list = []
        # A daemon thread, not an executor: it must still serve the clean-up at exit.
        self.jobs: queue.Queue = queue.Queue()
        threading.Thread(target=self.serve, name="dm_control", daemon=True).start()

    def serve(self) -> None:
        while True:
            method, args, result = self.jobs.get()
            try:
                result.set_result(method(*args))
            except BaseException as error:  # noqa: BLE001 - handed to the caller, who re-raises it
                result.set_exception(error)

    def on_thread(self, method: Callable, *args) -> Any:
        """``method(*args)`` run on the environments' own thread."""
        result: concurrent.futures.Future = concurrent.futures.Future()
        self.jobs.put((method, args, result))
        return result.result()

    def frame(self, env) -> np.ndarray:
        if self.image_size is None:
            return np.zeros(0, np.uint8)
        return env.physics.render(self.image_size, self.image_size, camera_id=self.task.camera)

    def close(self) -> None:
        """Free the environments' OpenGL contexts on the thread they are current on (dm_control's
        own clean-up at exit would try from the main thread, and fail)."""
        for env in self.envs:
            env.physics.free()
        self.envs = []

    def reset(self, seed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fresh episodes, the environments' randomness seeded ``seed``, ``seed + 1``, … (as
        environments made with those seeds): their observations and frames."""
        first_reset = not self.envs
        if first_reset:
            self.envs = [self.task.load(int(seed) + i, self.image_size) for i in range(self.num_envs)]
        for i, env in enumerate(self.envs):
            env.task.random.seed(int(seed) + i)
        first = [env.reset() for env in self.envs]
        frames = np.stack([self.frame(env) for env in self.envs])
        if first_reset:  # registered after dm_control's contexts: exit runs it before their clean-up
            atexit.register(self.on_thread, self.close)
        return np.stack([flat_observation(step.observation) for step in first]), frames

    def step(self, action: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, ...]:
        """Observations after any restart, the ones reached, frames, rewards, terminated, truncated."""
        if not self.envs:  # a resumed run: its episodes are gone, so they end here
            obs, frames = self.reset(seed)
            ended = np.ones(self.num_envs, bool)
            return obs, obs, frames, np.zeros(self.num_envs, np.float32), ~ended, ended
        rows = [self._step_one(env, act) for env, act in zip(self.envs, np.asarray(action, np.float64))]
        obs, reached, frames, rewards, terminated, truncated = (np.stack(column) for column in zip(*rows))
        return obs, reached, frames, rewards.astype(np.float32), terminated, truncated

    def _step_one(self, env, action: np.ndarray) -> tuple:
        reward = 0.0
        for _ in range(self.action_repeat):
            step = env.step(action)
            reward += step.reward or 0.0
            if step.last():
                break
        reached = flat_observation(step.observation)
        terminated = bool(step.last() and step.discount == 0.0)
        truncated = bool(step.last() and not terminated)
        if step.last():
            step = env.reset()
        return flat_observation(step.observation), reached, self.frame(env), reward, terminated, truncated


class HostData(struct.PyTreeNode):
    """What a host environment's state shows of its physics: no joint positions ((N, 0))."""

    qpos: jax.Array


class DMCEnv:
    """``num_envs`` dm_control environments observed as :class:`PixelObservations` observes a
    task: the state vector, and (with ``image_size``) a stack of ``frame_stack`` frames, drawn by
    dm_control's own renderer. An :class:`~dva.envs.observations.Env`, not a differentiable one."""

    def __init__(
        self,
        task: DMCTask,
        num_envs: int,
        image_size: int | None,
        frame_stack: int = 3,
        action_repeat: int = 2,
        evaluation_episodes: int | None = None,
    ) -> None:
        check_stacking(frame_stack, action_repeat)
        self.task, self.num_envs, self.image_size = task, num_envs, image_size
        self.frame_stack, self.action_repeat = frame_stack, action_repeat
        self.evaluation_episodes = evaluation_episodes or num_envs
        self.host = HostEnvs(task, num_envs, image_size, action_repeat)
        self._evaluation: DMCEnv | None = None

    @property
    def episode_steps(self) -> int:
        return -(-self.task.episode_length // self.action_repeat)

    @property
    def has_pixels(self) -> bool:
        return self.image_size is not None

    def evaluation_env(self) -> DMCEnv:
        """The same environments on a batch of their own (``evaluation_episodes`` of them), for
        evaluations."""
        if self._evaluation is None:
            self._evaluation = DMCEnv(
                self.task, self.evaluation_episodes, self.image_size, self.frame_stack, self.action_repeat
            )
        return self._evaluation

    def _shapes(self) -> tuple[jax.ShapeDtypeStruct, jax.ShapeDtypeStruct]:
        n = self.num_envs
        frame = (n, self.image_size, self.image_size, 3) if self.image_size is not None else (n, 0)
        return jax.ShapeDtypeStruct((n, self.task.obs_dim), jnp.float32), jax.ShapeDtypeStruct(frame, jnp.uint8)

    def _stack(self, frames: jax.Array) -> jax.Array:
        return reset_frame_stack(frames, self.frame_stack) if self.image_size is not None else frames

    def reset(self, key: jax.Array) -> EnvState:
        """Fresh episodes (seeded from ``key``) with their first frame stacks."""
        seed = jax.random.randint(key, (), 0, 2**30)
        obs, frames = io_callback(
            functools.partial(self.host.on_thread, self.host.reset), self._shapes(), seed, ordered=True
        )
        n = self.num_envs
        return EnvState(
            data=HostData(qpos=jnp.zeros((n, 0))),  # type: ignore[arg-type]  # no MJX physics here
            obs=obs,
            final_obs=obs,
            final_qpos=jnp.zeros((n, 0)),
            reward=jnp.zeros(n),
            terminated=jnp.zeros(n, bool),
            truncated=jnp.zeros(n, bool),
            step_count=jnp.zeros(n, jnp.int32),
            prev_action=jnp.zeros((n, self.task.action_dim)),
            key=jax.random.split(key, n),
            pixels=self._stack(frames),
        )

    def step(self, env: EnvState, action: jax.Array) -> EnvState:
        """One agent step of every environment; the new frame pushed onto the stack."""
        obs_shape, frame_shape = self._shapes()
        n = self.num_envs
        shapes = (
            obs_shape,
            obs_shape,
            frame_shape,
            jax.ShapeDtypeStruct((n,), jnp.float32),
            jax.ShapeDtypeStruct((n,), jnp.bool_),
            jax.ShapeDtypeStruct((n,), jnp.bool_),
        )
        seed = jax.random.randint(env.key[0], (), 0, 2**30)  # only used after a resume
        obs, reached, frames, reward, terminated, truncated = io_callback(
            functools.partial(self.host.on_thread, self.host.step),
            shapes,
            action.astype(jnp.float32),
            seed,
            ordered=True,
        )
        done = terminated | truncated
        pixels = push_frame(env.frames, frames, done) if self.image_size is not None else env.frames
        return env.replace(
            obs=obs,
            final_obs=reached,
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            step_count=jnp.where(done, 0, env.step_count + 1),
            prev_action=action,
            key=jax.vmap(lambda k: jax.random.split(k)[0])(env.key),
            pixels=pixels,
        )

    @staticmethod
    def observe(env: EnvState) -> Observation:
        """What a policy may look at."""
        return {"state": env.obs, "pixels": env.frames}

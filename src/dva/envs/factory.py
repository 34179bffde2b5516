"""The one environment factory: from a task name to the environment an agent trains in.

A task name is one of this project's tasks (built in, or added with :func:`dva.register_task`),
built on MJX and differentiable, or ``dmc:<domain>-<task>``, one of dm_control's own tasks
(:mod:`dva.envs.dmc`). :func:`make_env` returns an :class:`~dva.envs.observations.Env` for either:
a :class:`~dva.envs.observations.PixelObservations` of the task with the renderer its agent asks
for (Warp's pixels, the differentiable rasteriser, or none), which is also a
:class:`~dva.envs.observations.DifferentiableEnv`, or a :class:`~dva.envs.dmc.DMCEnv`, which is not.
Nothing else in the package asks which kind a name is.
"""

from __future__ import annotations

from typing import Literal

import jax
from jax.sharding import Mesh, PartitionSpec

from dva.envs.dmc import DMCEnv, dmc_domain_task, is_dmc, make_dmc_task
from dva.envs.observations import Env, PixelObservations, Renderer
from dva.envs.rendering import PixelRenderer
from dva.envs.soft_rendering import SoftRenderer
from dva.errors import DvaUsageError
from dva.tasks import TARGET_RETURNS, check_task_name, make_task
from dva.tasks.base import Task

RendererKind = Literal["warp", "soft"] | None  # Warp's pixels, the differentiable rasteriser, or none
DATA_AXIS = "data"  # the device mesh's one axis, over which a run's environments split


def check_env_name(name: str) -> None:
    """A one-line error unless ``name`` is a task this factory makes (a ``dmc:`` name: one of
    dm_control's, which needs the ``dmc`` extra)."""
    if is_dmc(name):
        make_dmc_task(name)
    else:
        check_task_name(name)


def simulated_task(name: str, physics: str | None = None) -> Task | None:
    """This project's task behind ``name`` (its MuJoCo model: what videos and random references
    need), or None for a dm_control task."""
    return None if is_dmc(name) else make_task(name, physics)


def env_physics(name: str, physics: str | None = None) -> str:
    """The contact model the environment of ``name`` runs (``physics``, else the task's default;
    ``dm_control`` for dm_control's tasks): what ``run.json`` records."""
    task = simulated_task(name, physics)
    return make_dmc_task(name).physics if task is None else task.physics


def unit_rewards(name: str) -> bool:
    """Whether the task's rewards per step lie in [0, 1] (dm_control's, for which the pixel
    baselines were tuned); this project's tasks pay up to ≈ 10 per step."""
    return is_dmc(name)


def target_return(name: str) -> float | None:
    """The return ``dva compare`` times runs to on ``name``, if it has one."""
    return TARGET_RETURNS.get(name)


EVALUATION_EPISODES = 16
"""Episodes in every evaluation during training and in ``dva eval``, whatever the method and its
number of training envs: one per env of an evaluation batch of this size."""


def check_evaluation_episodes(episodes: int | None, flag: str | None = None) -> None:
    """An evaluation averages a whole number ≥ 1 of episodes (None: one per training env); the
    error names ``flag`` (a command-line option) where given, else the argument."""
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1):
        named = f"{flag} {episodes!r}" if flag else f"evaluation_episodes = {episodes!r}"
        raise DvaUsageError(f"{named} is not allowed; use a whole number ≥ 1")


def make_env(
    name: str,
    num_envs: int,
    *,
    renderer: RendererKind = None,
    image_size: int = 84,
    frame_stack: int = 3,
    action_repeat: int = 1,
    physics: str | None = None,
    mesh: Mesh | None = None,
    evaluation_episodes: int | None = EVALUATION_EPISODES,
) -> Env:
    """``num_envs`` environments of the task ``name``, observed through ``renderer`` at
    ``image_size``² pixels with ``frame_stack`` frames, each action held ``action_repeat`` control
    steps; ``physics``: the contact model of this project's tasks (None: the task's); ``mesh``: the
    devices a run's environments split over (each renders its share). Evaluations run
    ``evaluation_episodes`` episodes on a batch of envs of their own (None: on these envs)."""
    check_env_name(name)
    check_evaluation_episodes(evaluation_episodes)
    if is_dmc(name):
        pixels = image_size if renderer is not None else None
        return DMCEnv(make_dmc_task(name), num_envs, pixels, frame_stack, action_repeat, evaluation_episodes)
    task = make_task(name, physics)

    def observed(count: int, mesh: Mesh | None, evaluation: PixelObservations | None = None) -> PixelObservations:
        drawn = make_renderer(renderer, task, count, image_size, mesh)
        return PixelObservations(task, count, drawn, frame_stack, action_repeat, evaluation)

    if evaluation_episodes is None or (evaluation_episodes == num_envs and (mesh is None or mesh.size == 1)):
        return observed(num_envs, mesh)  # evaluations run on these envs (a pure wrapper: from fresh resets)
    return observed(num_envs, mesh, evaluation=observed(evaluation_episodes, None))


def make_renderer(
    kind: RendererKind, task: Task, num_envs: int, image_size: int, mesh: Mesh | None = None
) -> Renderer | None:
    """A renderer of ``kind`` for ``num_envs`` envs of ``task`` at ``image_size``² pixels; with a
    device ``mesh``, Warp's renders each device's share of the envs on that device."""
    if kind is None:
        return None
    if kind == "soft":
        return SoftRenderer(task, num_envs, image_size)
    if mesh is not None and mesh.size > 1:
        return SplitRenderer(lambda n, device: PixelRenderer(task, n, image_size, device=device), num_envs, mesh)
    return PixelRenderer(task, num_envs, image_size)


class SplitRenderer:
    """A renderer for ``num_envs`` envs split over ``mesh``: one renderer per device for its share
    (``make(share, device)``), each device running its own. (A renderer that is a foreign call,
    as Warp's, cannot be partitioned by XLA, and one render context serves one device.)"""

    def __init__(self, make, num_envs: int, mesh: Mesh) -> None:
        share = num_envs // mesh.size
        self.parts = [make(share, device) for device in mesh.devices.flat]
        self.num_envs, self.mesh = num_envs, mesh
        self.differentiable = self.parts[0].differentiable

    def __call__(self, qpos: jax.Array) -> jax.Array:
        def local(qpos):
            return jax.lax.switch(jax.lax.axis_index(DATA_AXIS), [part.__call__ for part in self.parts], qpos)

        split = PartitionSpec(DATA_AXIS)
        return jax.shard_map(local, mesh=self.mesh, in_specs=split, out_specs=split)(qpos)


__all__ = [
    "DATA_AXIS",
    "EVALUATION_EPISODES",
    "RendererKind",
    "SplitRenderer",
    "check_env_name",
    "check_evaluation_episodes",
    "dmc_domain_task",
    "env_physics",
    "is_dmc",
    "make_env",
    "make_renderer",
    "simulated_task",
    "target_return",
    "unit_rewards",
]

"""Data parallelism: one run's environments split over several devices.

The short-horizon actor-critic family (D.Va, SHAC, DPG on the state, visual SHAC) declares which
fields of its training state carry the environment batch (``Agent.batch_fields``). Those are split
along their first axis over a one-axis mesh (``data``); everything else — networks, optimiser
states, statistics — is replicated. The jitted iteration is the same function: XLA partitions it
from the placement of its inputs, so each device steps, renders and differentiates its share of
the environments, and the means over the batch (the actor's loss, the critic's minibatches,
the observation statistics) become all-reduces — the gradient is the one-device gradient,
averaged over all environments. Several hosts: start every process with
``jax.distributed.initialize()`` first; ``jax.devices()`` then lists every host's devices.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from dva.envs.factory import DATA_AXIS
from dva.errors import DvaUsageError


def device_mesh(devices: int | None, num_envs: int) -> Mesh:
    """A mesh over the first ``devices`` devices JAX sees (None: all of them) that ``num_envs``
    environments split over evenly."""
    available = jax.devices()
    count = len(available) if devices is None else devices
    if not isinstance(count, int) or not 1 <= count <= len(available):
        raise DvaUsageError(
            f"devices = {devices!r} is not allowed; JAX sees {len(available)} {available[0].platform} device(s): "
            f"use 1 to {len(available)}"
        )
    if num_envs % count:
        raise DvaUsageError(f"num_envs = {num_envs} does not split over {count} devices; use a multiple of {count}")
    return Mesh(np.array(available[:count]), (DATA_AXIS,))


def state_shardings(state, mesh: Mesh, batch_fields: tuple[str, ...]):
    """Per leaf of ``state``: split along the first axis for the fields in ``batch_fields``,
    replicated elsewhere."""
    replicated, split = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec(DATA_AXIS))
    shardings = jax.tree.map(lambda _: replicated, state)
    return shardings.replace(**{field: jax.tree.map(lambda _: split, getattr(state, field)) for field in batch_fields})


def place(state, mesh: Mesh, batch_fields: tuple[str, ...]):
    """``state`` on ``mesh``: its batch fields split, the rest replicated."""
    return jax.device_put(state, state_shardings(state, mesh, batch_fields))

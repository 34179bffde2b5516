"""Shared fixtures. Tasks are built once per session (float32); float64 tests build their own."""

from __future__ import annotations

import jax
import pytest

from dva.tasks import TASKS, make_task

ALL_TASKS = list(TASKS)


@pytest.fixture(params=ALL_TASKS)
def task(request: pytest.FixtureRequest):
    return make_task(request.param)


def unbatch(tree):
    """First environment of a batched pytree."""
    return jax.tree.map(lambda x: x[0], tree)

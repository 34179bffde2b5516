"""A run on disk: its spec (``run.json``, what ``--resume`` rebuilds it from), its directory's
checks, and its atomic Orbax checkpoints."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from dva.algorithms import config_from_dict, saved_algo
from dva.errors import DvaUsageError
from dva.runner.schedule import Every


@dataclasses.dataclass
class RunSpec:
    """What ``dva train`` was asked for (saved as ``run.json`` so ``--resume`` can rebuild it)."""

    task: str
    algo: str
    preset: str
    seed: int
    config: Any  # the algorithm's typed config (a dict only in run.json)
    physics: str | None = None  # the task's contact model (None: the task's default)

    @classmethod
    def read(cls, path: Path) -> RunSpec:
        """The spec saved in ``path`` (``run.json``), its config typed again (under the registry
        entry it belongs to now: :func:`~dva.algorithms.saved_algo`)."""
        values = json.loads(path.read_text())
        config = config_from_dict(values["algo"], values["config"])
        return cls(**dict(values, algo=saved_algo(values["algo"], config), config=config))

    def to_dict(self) -> dict:
        """As ``run.json`` holds it."""
        return dict(self.__dict__, config=dataclasses.asdict(self.config))


def write_spec(run_dir: Path, spec: RunSpec) -> RunSpec:
    """Save a new run's spec as ``run.json`` (what ``--resume`` rebuilds it from)."""
    (run_dir / "run.json").write_text(json.dumps(spec.to_dict(), indent=2))
    return spec


def check_run_dir(run_dir: Path) -> None:
    """The run directory must be a directory this process can create and write."""
    if run_dir.exists() and not run_dir.is_dir():
        raise DvaUsageError(f"--run-dir {run_dir} is a file, not a directory; use a new or existing directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise DvaUsageError(
            f"--run-dir {run_dir} cannot be written ({error.strerror}); use a writable directory"
        ) from None


def check_new_run_dir(run_dir: Path) -> None:
    """A new run needs a directory that holds no run and can be written."""
    if (run_dir / "run.json").exists():
        raise DvaUsageError(f"run directory {run_dir} already holds a run; pass --resume or another --run-dir")
    check_run_dir(run_dir)


def resumed_run(run_dir: Path, task: str | None, algo: str | None) -> RunSpec:
    """The spec of the run in ``run_dir`` (``run.json``), which must be a run on ``task`` and of
    ``algo`` where they are given."""
    spec_path = run_dir / "run.json"
    if not spec_path.exists():
        raise DvaUsageError(f"--resume: no run to resume in {run_dir} (missing run.json)")
    spec = RunSpec.read(spec_path)
    if task not in (None, spec.task) or algo not in (None, spec.algo):
        raise DvaUsageError(
            f"--resume: {run_dir} holds a {spec.algo} run on {spec.task}, "
            f"not {algo or spec.algo} on {task or spec.task}; "
            f"pass --task {spec.task} --algo {spec.algo}"
        )
    return spec


def checkpoint_manager(run_dir: Path) -> ocp.CheckpointManager:
    """Orbax manager writing to ``run_dir/checkpoints`` (atomic: written aside, then renamed)."""
    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp.CheckpointManager(run_dir.resolve() / "checkpoints", options=options)


def _saved_leaves(state) -> dict[str, jax.Array]:
    """The non-empty leaves of ``state`` by path (Orbax cannot store MJX's zero-size arrays)."""
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    return {jax.tree_util.keystr(path): leaf for path, leaf in leaves if leaf.size > 0}


def save(manager: ocp.CheckpointManager, state) -> None:
    """Checkpoint ``state`` under its iteration number."""
    manager.save(int(state.iteration), args=ocp.args.StandardSave(_saved_leaves(state)))


def restore(manager: ocp.CheckpointManager, like: Any, placement: Callable[[Any], Any]) -> Any:
    """The latest checkpoint, shaped like ``like`` (an agent's initial state, abstract: from
    ``jax.eval_shape``) and placed by ``placement``; a clear error when it cannot be read."""
    step = manager.latest_step()
    try:
        saved = manager.restore(step, args=ocp.args.StandardRestore(_saved_leaves(like)))
    except Exception as error:  # orbax raises many types for damaged files
        raise DvaUsageError(f"checkpoint {manager.directory}/{step} is corrupt or incompatible: {error}") from None
    paths_and_leaves, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = [
        saved.get(jax.tree_util.keystr(path), jnp.zeros(leaf.shape, leaf.dtype))  # zero-size leaves
        for path, leaf in paths_and_leaves
    ]
    return placement(jax.tree_util.tree_unflatten(treedef, leaves))


class Checkpoints:
    """Saves every ``every`` iterations if given, else every ``minutes``, and at the end."""

    def __init__(self, manager: ocp.CheckpointManager, every: int | None, minutes: float) -> None:
        self.manager, self.schedule = manager, Every(every) if every else Every(minutes=minutes)

    def save_if_due(self, state) -> None:
        if self.schedule.due(int(state.iteration)):
            save(self.manager, state)
            self.schedule.done()

    def save_final(self, state) -> None:
        if self.manager.latest_step() != int(state.iteration):
            save(self.manager, state)
        self.manager.wait_until_finished()

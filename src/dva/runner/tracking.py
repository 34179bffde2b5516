"""Experiment tracking on Weights & Biases (``dva train --track``), next to the CSV and TensorBoard
logs that every run writes anyway. ``wandb`` is the ``wandb`` extra, imported only when asked;
``WANDB_MODE=offline`` keeps the run on disk (``wandb sync`` uploads it later)."""

from __future__ import annotations

import math
import os
import secrets
from pathlib import Path
from typing import Any


class WandbTracker:
    """One W&B run per dva run: its ``run.json`` as the config, every logged row's numbers plotted
    against ``env_steps``, and the policy video. A resumed dva run continues the same W&B run."""

    def __init__(self, project: str | None = None) -> None:
        try:
            import wandb
        except ImportError:
            raise ImportError("--track needs the 'wandb' extra: pip install 'dva[wandb]'") from None
        self.wandb, self.project = wandb, project or os.environ.get("WANDB_PROJECT", "dva")
        self.run: Any = None  # a wandb Run once started

    def start(self, run_dir: Path, config: dict) -> None:
        """Open (or reopen, on resume) the W&B run of ``run_dir``."""
        id_file = run_dir / "wandb_id"
        if not id_file.exists():
            id_file.write_text(secrets.token_hex(6))
        self.run = self.wandb.init(
            project=self.project,
            name=run_dir.name,
            id=id_file.read_text().strip(),
            resume="allow",
            config=config,
            dir=str(run_dir),
        )
        self.run.define_metric("env_steps")
        self.run.define_metric("*", step_metric="env_steps")

    def log(self, row: dict, env_steps: int) -> None:
        """The row's finite numbers (not its iteration counter) at ``env_steps``."""
        values = {key: float(value) for key, value in row.items() if key != "iteration" and value != ""}
        values = {key: value for key, value in values.items() if math.isfinite(value)}
        self.run.log(dict(values, env_steps=env_steps))

    def log_video(self, path: Path) -> None:
        self.run.log({"policy": self.wandb.Video(str(path), format="mp4")})

    def finish(self) -> None:
        if self.run is not None:
            self.run.finish()
            self.run = None

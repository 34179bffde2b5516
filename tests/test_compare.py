"""``dva compare``: which runs a figure trains, with which overrides, and that a repeated or
extended comparison skips finished runs and resumes short ones (training replaced by a fake
that writes a run's files, so no compilation)."""

from __future__ import annotations

import csv
import json

import pytest

import dva.training
from dva.analysis.compare import figure_settings
from dva.cli import main


class FakeTraining:
    """Stands in for ``dva.training.train`` and ``checkpoint_manager``: logs one evaluation per
    simulated minute and leaves a checkpoint marker."""

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def train(self, task, algo, *, run_dir, minutes, resume=False, preset="cpu", seed=0, **overrides):
        self.calls.append(dict(task=task, algo=algo, run_dir=run_dir, minutes=minutes, resume=resume, **overrides))
        run_dir.mkdir(parents=True, exist_ok=True)
        if not resume:
            (run_dir / "run.json").write_text(json.dumps({"task": task, "algo": algo, "preset": preset, "seed": seed,
                                                          "config": overrides}))
            (run_dir / "progress.csv").write_text("env_steps,wall_time,eval_return,train_return\n0,0,0,nan\n")
        with (run_dir / "progress.csv").open() as f:
            rows = list(csv.DictReader(f))
        start = float(rows[-1]["wall_time"])
        bonus = 100.0 if overrides.get("use_critic", True) else 10.0
        with (run_dir / "progress.csv").open("a") as f:
            for minute in range(1, round(minutes) + 1):
                seconds = start + 60 * minute
                f.write(f"{int(seconds * 10)},{seconds},{bonus * seconds / 60},nan\n")
        (run_dir / "checkpoint").write_text("")
        return run_dir

    def checkpoint_manager(self, run_dir):
        class Manager:
            @staticmethod
            def latest_step():
                return 1 if (run_dir / "checkpoint").exists() else None
        return Manager()


@pytest.fixture
def fake(monkeypatch):
    fake = FakeTraining()
    monkeypatch.setattr(dva.training, "train", fake.train)
    monkeypatch.setattr(dva.training, "checkpoint_manager", fake.checkpoint_manager)
    return fake


def test_figures_compare_the_paper_settings():
    assert [(s.algo, s.overrides) for s in figure_settings("ablation-value", ["hopper"])] == [
        ("dva", ()), ("dva", (("use_critic", False),))]
    assert [dict(s.overrides)["frame_stack"] for s in figure_settings("ablation-frames", ["hopper"])] == [1, 2, 3, 4, 5, 6]
    assert [s.algo for s in figure_settings("fig4", ["cartpole_swingup"])] == ["dva", "drqv2", "curl", "dreamerv3"]
    assert [s.algo for s in figure_settings("fig6", ["a", "b"])] == ["dva", "dagger"] * 2
    with pytest.raises(ValueError, match="figure 'fig5' is not allowed"):
        figure_settings("fig5", ["hopper"])


def test_compare_trains_skips_and_resumes(fake, tmp_path, capsys):
    args = ["compare", "ablation-value", "--seeds", "0", "--out", str(tmp_path), "--threshold", "150"]
    main([*args, "--minutes", "2"])
    assert [(c["algo"], c.get("use_critic"), c["minutes"], c["resume"]) for c in fake.calls] == [
        ("dva", None, 2.0, False), ("dva", False, 2.0, False)]
    out = tmp_path / "ablation-value"
    summary = {row["setting"]: row for row in csv.DictReader((out / "summary.csv").open())}
    assert float(summary["D.Va on cartpole_swingup"]["final_mean"]) == 200.0
    assert summary["D.Va on cartpole_swingup"]["reached"] == "1"
    assert float(summary["D.Va without critic on cartpole_swingup"]["final_mean"]) == 20.0
    assert (out / "eval_return_vs_wall_time.png").exists() and (out / "summary.md").exists()
    assert "D.Va without critic on cartpole_swingup" in capsys.readouterr().out

    main([*args, "--minutes", "2"])  # everything already done
    assert len(fake.calls) == 2
    main([*args, "--minutes", "3"])  # one minute more each, from the checkpoints
    assert [(c["minutes"], c["resume"]) for c in fake.calls[2:]] == [(1.0, True), (1.0, True)]
    # a run that died before its first checkpoint starts again from scratch
    (out / "runs" / "cartpole_swingup_d_va_s0" / "checkpoint").unlink()
    (out / "runs" / "cartpole_swingup_d_va_s0" / "complete.json").unlink()
    main([*args, "--minutes", "3"])
    assert [(c["minutes"], c["resume"]) for c in fake.calls[4:]] == [(3.0, False)]

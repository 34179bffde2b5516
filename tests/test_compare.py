"""``dva compare``: which runs a figure trains, with which overrides, and that a repeated or
extended comparison skips finished runs and resumes short ones (training replaced by a fake
that writes a run's files, so no compilation)."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import sys
import threading
import time

import pytest

import dva.analysis.compare as compare_module
from dva.algorithms import make_config
from dva.analysis.compare import Job, cpu_groups, figure_settings, grid_settings, launch_pinned, run_parallel
from dva.cli import main
from dva.runner.logs import read_progress


class FakeTraining:
    """Stands in for ``train`` and ``checkpoint_manager`` in ``dva.analysis.compare``: logs one evaluation per
    simulated minute and leaves a checkpoint marker (the iteration it saved)."""

    HEADER = "iteration,env_steps,wall_time,eval_return,train_return"

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def train(self, task, algo, *, run_dir, minutes, resume=False, preset="cpu", seed=0, **overrides):
        self.calls.append(dict(task=task, algo=algo, run_dir=run_dir, minutes=minutes, resume=resume, **overrides))
        run_dir.mkdir(parents=True, exist_ok=True)
        if not resume:
            options = {key: value for key, value in overrides.items() if key not in ("eval_every", "eval_minutes")}
            config = dataclasses.asdict(make_config(task, algo, preset, **options))
            (run_dir / "run.json").write_text(
                json.dumps({"task": task, "algo": algo, "preset": preset, "seed": seed, "config": config})
            )
            (run_dir / "progress.csv").write_text(f"{self.HEADER}\n0,0,0,0,nan\n")
        with (run_dir / "progress.csv").open() as f:
            rows = list(csv.DictReader(f))
        if resume:  # as train() does: the rows logged after the checkpoint are dropped
            rows = [row for row in rows if int(row["iteration"]) <= int((run_dir / "checkpoint").read_text())]
        start, iteration = float(rows[-1]["wall_time"]), int(rows[-1]["iteration"])
        bonus = 100.0 if overrides.get("use_critic", True) else 10.0
        lines = [",".join(row.values()) for row in rows]
        for minute in range(1, round(minutes) + 1):  # one iteration per simulated minute
            seconds = start + 60 * minute
            lines.append(f"{iteration + minute},{int(seconds * 10)},{seconds},{bonus * seconds / 60},nan")
        (run_dir / "progress.csv").write_text("\n".join([self.HEADER, *lines]) + "\n")
        (run_dir / "checkpoint").write_text(str(iteration + round(minutes)))
        return run_dir

    def checkpoint_manager(self, run_dir):
        class Manager:
            @staticmethod
            def latest_step():
                marker = run_dir / "checkpoint"
                return int(marker.read_text()) if marker.exists() else None

        return Manager()


@pytest.fixture
def fake(monkeypatch):
    fake = FakeTraining()
    monkeypatch.setattr(compare_module, "train", fake.train)
    monkeypatch.setattr(compare_module, "checkpoint_manager", fake.checkpoint_manager)
    return fake


def test_figures_compare_the_paper_settings():
    assert [(s.algo, s.overrides) for s in figure_settings("ablation-value", ["hopper"])] == [
        ("dva", ()),
        ("dva", (("use_critic", False),)),
    ]
    # an ablation of the privileged variant: its one algo in every setting, named in every label
    privileged = figure_settings("ablation-frames", ["hopper"], frames=[1, 3], algos=["dva-privileged"])
    assert [(s.algo, s.label) for s in privileged] == [
        ("dva-privileged", "dva-privileged, 1 frame"),
        ("dva-privileged", "dva-privileged, 3 frames"),
    ]
    with pytest.raises(ValueError, match="not allowed for ablation-value; use one of: dva, dva-privileged"):
        figure_settings("ablation-value", ["hopper"], algos=["dva", "drqv2"])
    assert [dict(s.overrides)["frame_stack"] for s in figure_settings("ablation-frames", ["hopper"])] == [
        1,
        2,
        3,
        4,
        5,
        6,
    ]
    assert [s.algo for s in figure_settings("fig4", ["cartpole_swingup"])] == [
        "dva",
        "drqv2",
        "curl",
        "dreamerv3",
        "tdmpc2",
    ]
    assert [s.algo for s in figure_settings("fig6", ["a", "b"])] == ["dva", "dagger"] * 2
    assert [(s.algo, s.slug) for s in figure_settings("fig13", ["ant"])] == [
        ("shac", "ant_shac"),
        ("dpg-state", "ant_dpg_state"),
    ]
    with pytest.raises(ValueError, match="figure 'fig5' is not allowed"):
        figure_settings("fig5", ["hopper"])
    assert [s.label for s in figure_settings("ablation-frames", ["hopper"], frames=[1, 3])] == [
        "dva, 1 frame",
        "dva, 3 frames",
    ]
    for bad in ([], [0, 3], [2, 2], [1.5]):
        with pytest.raises(ValueError, match=r"frames = \[.*\] is not allowed; use distinct ints ≥ 1"):
            figure_settings("ablation-frames", ["hopper"], frames=bad)
    with pytest.raises(ValueError, match=r"frames = \[1\] is only allowed with ablation-frames, not with 'fig4'"):
        figure_settings("fig4", ["hopper"], frames=[1])
    assert [s.slug for s in figure_settings("fig4", ["hopper"], algos=["drqv2", "dva"])] == [
        "hopper_dva",
        "hopper_drqv2",
    ]
    for bad in ([], ["dva", "dva"], ["shac"]):
        with pytest.raises(
            ValueError, match=r"algos = \[.*\] is not allowed for fig4; use distinct names from: dva, drqv2"
        ):
            figure_settings("fig4", ["hopper"], algos=bad)
    # the privileged variants only where asked for, after the paper's methods
    assert [
        s.algo for s in figure_settings("fig4", ["hopper"], algos=["drqv2-privileged", "dva", "dva-privileged"])
    ] == [
        "dva",
        "drqv2-privileged",
        "dva-privileged",
    ]
    with pytest.raises(ValueError, match="not allowed for fig13"):
        figure_settings("fig13", ["hopper"], algos=["dva-privileged"])


def test_compare_refuses_a_run_folder_of_another_setting(fake, tmp_path, capsys):
    """A run trained under other settings (here: dva with the state-prediction loss, as its CPU
    preset once had it on the legged robots) is not reused as a dva run: the error names what
    differs; the same folder serves the setting it was trained for."""
    args = ["compare", "fig4", "--tasks", "hopper", "--seeds", "0", "--out", str(tmp_path), "--minutes", "1"]
    main([*args, "--algos", "dva-privileged"])
    runs = tmp_path / "fig4" / "runs"
    shutil.copytree(runs / "hopper_dva_privileged_s0", runs / "hopper_dva_s0")
    spec = json.loads((runs / "hopper_dva_s0" / "run.json").read_text())
    (runs / "hopper_dva_s0" / "run.json").write_text(json.dumps(dict(spec, algo="dva")))  # as written then
    capsys.readouterr()
    for options, expected in (
        (["--algos", "dva"], "algo dva-privileged (wanted dva), state_prediction 10.0 (wanted 0.0)"),
        (["--algos", "dva-privileged", "--preset", "paper"], "num_envs 16 (wanted 64)"),
    ):
        with pytest.raises(SystemExit):
            main([*args, *options])
        error = capsys.readouterr().err
        assert "holds a run of another setting" in error and expected in error
    calls = len(fake.calls)
    main([*args, "--algos", "dva-privileged"])  # its own setting: complete, skipped
    assert len(fake.calls) == calls


def test_compare_trains_skips_and_resumes(fake, tmp_path, capsys):
    args = ["compare", "ablation-value", "--seeds", "0", "--out", str(tmp_path), "--threshold", "150"]
    main([*args, "--minutes", "2"])
    assert [(c["algo"], c.get("use_critic"), c["minutes"], c["resume"]) for c in fake.calls] == [
        ("dva", None, 2.0, False),
        ("dva", False, 2.0, False),
    ]
    # evaluated by the clock, once a minute, whatever the setting's iteration time
    assert all((c["eval_every"], c["eval_minutes"]) == (None, 1.0) for c in fake.calls)
    out = tmp_path / "ablation-value"
    summary = {row["setting"]: row for row in csv.DictReader((out / "summary.csv").open())}
    assert float(summary["dva on cartpole_swingup"]["final_mean"]) == 200.0
    assert summary["dva on cartpole_swingup"]["reached"] == "1"
    assert float(summary["dva without critic on cartpole_swingup"]["final_mean"]) == 20.0
    assert (out / "eval_return_vs_wall_time.png").exists() and (out / "summary.md").exists()
    assert "dva without critic on cartpole_swingup" in capsys.readouterr().out

    main([*args, "--minutes", "2"])  # everything already done
    assert len(fake.calls) == 2
    main([*args, "--minutes", "3"])  # one minute more each, from the checkpoints
    assert [(c["minutes"], c["resume"]) for c in fake.calls[2:]] == [(1.0, True), (1.0, True)]
    # a run that died before its first checkpoint starts again from scratch
    (out / "runs" / "cartpole_swingup_dva_s0" / "checkpoint").unlink()
    (out / "runs" / "cartpole_swingup_dva_s0" / "complete.json").unlink()
    main([*args, "--minutes", "3"])
    assert [(c["minutes"], c["resume"]) for c in fake.calls[4:]] == [(3.0, False)]
    # a run cut short after its budget was spent (its last row at 3 min, no completion mark) is
    # marked complete, not resumed for zero minutes
    done = out / "runs" / "cartpole_swingup_dva_s0" / "complete.json"
    done.unlink()
    main([*args, "--minutes", "3"])
    assert len(fake.calls) == 5 and json.loads(done.read_text())["minutes"] == 3.0
    assert "had its minutes" in capsys.readouterr().out
    # a run killed two minutes after its last checkpoint (at 3 min): a resume drops those two
    # minutes' rows, so it trains them again — 2 more minutes for a 5-minute budget, not 0
    run_dir = out / "runs" / "cartpole_swingup_dva_s0"
    with (run_dir / "progress.csv").open("a") as f:
        f.write("4,2400,240.0,400.0,nan\n5,3000,300.0,500.0,nan\n")
    main([*args, "--minutes", "5"])
    assert [(c["run_dir"].name, c["minutes"], c["resume"]) for c in fake.calls[5:]] == [
        ("cartpole_swingup_dva_s0", 2.0, True),
        ("cartpole_swingup_dva_without_critic_s0", 2.0, True),
    ]
    assert read_progress(run_dir)[-1]["wall_time"] == "300.0"  # 5 minutes logged, as budgeted


def test_compare_evaluates_at_the_interval_asked_for(fake, tmp_path, capsys):
    args = ["compare", "ablation-value", "--seeds", "0", "--out", str(tmp_path), "--minutes", "2"]
    main([*args, "--eval-minutes", "3"])  # a method whose evaluation costs minutes
    assert [(c["eval_every"], c["eval_minutes"]) for c in fake.calls] == [(None, 3.0), (None, 3.0)]
    job = Job(figure_settings("fig4", ["hopper"])[0], 0, 2.0, "cpu", "out/runs/x_s0", eval_minutes=3.0)
    assert Job.from_json(job.to_json()) == job  # what a child process or a Ray task receives
    with pytest.raises(SystemExit):
        main(["sweep", "--algo", "dva", "--grid", "horizon=8", "--out", str(tmp_path), "--eval-minutes", "0"])
    assert "--eval-minutes 0.0 is not allowed; use a number of minutes > 0" in capsys.readouterr().err
    assert len(fake.calls) == 2  # nothing trained


def test_compare_times_each_task_to_its_own_target_return(fake, tmp_path, monkeypatch):
    from dva.tasks import TARGET_RETURNS

    monkeypatch.delitem(TARGET_RETURNS, "quadruped")  # a task without a target is not timed
    tasks = ["--tasks", "cartpole_swingup", "hopper", "quadruped"]
    main(["compare", "ablation-value", *tasks, "--seeds", "0", "--minutes", "6", "--out", str(tmp_path)])
    out = tmp_path / "ablation-value"
    summary = {row["setting"]: row for row in csv.DictReader((out / "summary.csv").open())}
    cartpole, hopper = summary["dva on cartpole_swingup"], summary["dva on hopper"]
    # the fake's D.Va earns 100 per minute: 550 first reached at 6 minutes, 3000 never
    assert (float(cartpole["threshold"]), cartpole["reached"], float(cartpole["minutes_to_threshold"])) == (
        550.0,
        "1",
        6.0,
    )
    assert (float(hopper["threshold"]), hopper["reached"]) == (3000.0, "0")
    assert summary["dva on quadruped"]["threshold"] == "" and summary["dva on quadruped"]["reached"] == ""
    markdown = (out / "summary.md").read_text()
    assert "| threshold | seeds reaching it |" in markdown
    assert [line for line in markdown.splitlines() if line.startswith("| dva on quadruped ")][0].endswith(
        "| – | – | – | – |"
    )


def test_compare_frames_trains_only_the_stacks_asked_for(fake, tmp_path):
    main(
        [
            "compare",
            "ablation-frames",
            "--tasks",
            "hopper",
            "--seeds",
            "0",
            "--minutes",
            "1",
            "--frames",
            "1",
            "3",
            "--out",
            str(tmp_path),
        ]
    )
    assert [(c["task"], c["frame_stack"]) for c in fake.calls] == [("hopper", 1), ("hopper", 3)]
    assert sorted(p.name for p in (tmp_path / "ablation-frames" / "runs").iterdir()) == [
        "hopper_dva_1_frame_s0",
        "hopper_dva_3_frames_s0",
    ]


def test_cpu_groups_are_disjoint_and_equal():
    assert cpu_groups([4, 0, 3, 1, 2], 2) == [(0, 1), (2, 3)]  # the fifth CPU stays unused
    assert cpu_groups([1, 0], 1) == [(0, 1)]
    for bad in (0, 3, 1.5):
        with pytest.raises(ValueError, match=f"workers = {bad!r} is not allowed; use an int from 1 to the 2 CPUs"):
            cpu_groups([0, 1], bad)


def test_parallel_runs_never_share_cpus_and_all_run_despite_a_failure():
    setting = figure_settings("fig4", ["cartpole_swingup"])[0]
    jobs = [Job(setting, seed, 1.0, "cpu", f"run{seed}") for seed in range(5)]
    spans: list[tuple[int, tuple[int, ...], float, float]] = []
    lock = threading.Lock()

    def launch(job, cpus):
        start = time.perf_counter()
        time.sleep(0.05)
        with lock:
            spans.append((job.seed, cpus, start, time.perf_counter()))
        if job.seed == 1:
            raise RuntimeError("run1 failed")
        return f"done on {cpus}"

    with pytest.raises(RuntimeError, match="run1 failed"):
        run_parallel(jobs, [(0,), (1,)], launch)
    assert sorted(seed for seed, *_ in spans) == [0, 1, 2, 3, 4]  # the failure stopped nothing
    for a in spans:
        for b in spans:
            if a is not b and a[2] < b[3] and b[2] < a[3]:  # ran at the same time
                assert a[1] != b[1]
    assert len({cpus for _, cpus, *_ in spans}) == 2


def test_a_job_survives_its_trip_to_a_child_process():
    setting = figure_settings("ablation-value", ["cartpole_swingup"])[1]
    job = Job(setting, 1, 2.0, "cpu", "out/runs/x_s1")
    assert Job.from_json(job.to_json()) == job
    setting = grid_settings("dva", ["hopper"], ["actor_hidden=[64,32]", "actor_lr=1e-3"])[0]
    job = Job(setting, 0, 2.0, "cpu", "out/runs/y_s0")
    assert Job.from_json(job.to_json()) == job  # the tuple-valued override comes back a tuple
    assert dict(job.setting.overrides) == {"actor_hidden": (64, 32), "actor_lr": 0.001}


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU pinning is Linux-only")
def test_launch_pinned_child_runs_on_its_cpus_and_its_failure_names_the_log(tmp_path, monkeypatch):
    """A stand-in for the Python child records the CPUs it may run on (after a pause: the parent
    pins it just after it starts) and exits with the code it is told."""
    child = tmp_path / "child.sh"
    child.write_text('#!/bin/sh\nsleep 1\ngrep Cpus_allowed_list /proc/self/status\nexit "$EXIT_CODE"\n')
    child.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(child))
    cpu = sorted(os.sched_getaffinity(0))[-1]
    setting = figure_settings("ablation-value", ["cartpole_swingup"])[0]
    job = Job(setting, 0, 1.0, "cpu", str(tmp_path / "runs" / "x_s0"))
    monkeypatch.setenv("EXIT_CODE", "0")
    assert "ran on CPUs" in launch_pinned(job, (cpu,))
    assert (tmp_path / "runs" / "x_s0.log").read_text().split()[-1] == str(cpu)
    monkeypatch.setenv("EXIT_CODE", "3")
    with pytest.raises(RuntimeError, match=r"x_s0 failed \(exit 3\); its output is in .*x_s0\.log"):
        launch_pinned(job, (cpu,))


def test_compare_with_workers_runs_every_job_once(fake, tmp_path, monkeypatch, capsys):
    launched = []

    def launch(job, cpus):  # in a thread instead of a pinned child: the fake training is in-process
        launched.append(cpus)
        return job.run()

    monkeypatch.setattr(compare_module, "launch_pinned", launch)
    monkeypatch.setattr(compare_module, "available_cpus", lambda: [0, 1])
    args = [
        "compare",
        "ablation-value",
        "--seeds",
        "0",
        "1",
        "--minutes",
        "2",
        "--out",
        str(tmp_path),
        "--workers",
        "2",
    ]
    main(args)
    assert sorted((c["run_dir"].name, c["minutes"]) for c in fake.calls) == [
        ("cartpole_swingup_dva_s0", 2.0),
        ("cartpole_swingup_dva_s1", 2.0),
        ("cartpole_swingup_dva_without_critic_s0", 2.0),
        ("cartpole_swingup_dva_without_critic_s1", 2.0),
    ]
    assert set(launched) <= {(0,), (1,)}
    summary = {row["setting"]: row for row in csv.DictReader((tmp_path / "ablation-value" / "summary.csv").open())}
    assert summary["dva on cartpole_swingup"]["seeds"] == "2"
    main(args)  # all complete: nothing launched again
    assert len(fake.calls) == 4 and "skipped (complete)" in capsys.readouterr().out


def test_a_sweep_on_rays_embedded_cluster_trains_skips_and_resumes(tmp_path, capsys):
    """Two runs of a grid as Ray tasks on the cluster Ray starts here: one interrupted before (a
    checkpoint, no completion mark) resumes, the other trains; called again, both are skipped."""
    import ray

    from dva.analysis.compare import run_settings
    from dva.runner.logs import read_progress
    from dva.runner.training import train

    small = ["num_envs=4", "horizon=8", "critic_minibatches=2", "actor_hidden=[16]", "critic_hidden=[16]"]
    grid = ["actor_lr=1e-3,2e-3", *small]
    settings = grid_settings("shac", ["cartpole_swingup"], grid)
    assert len(settings) == 2
    interrupted = tmp_path / "runs" / f"{settings[0].slug}_s0"
    train(
        "cartpole_swingup", "shac", iterations=1, run_dir=interrupted, checkpoint_every=1, **dict(settings[0].overrides)
    )
    # Its clock as if interrupted one second in, however long this machine took to compile it.
    progress = interrupted / "progress.csv"
    logged = list(csv.DictReader(progress.open()))
    with progress.open("w", newline="") as f:
        out = csv.DictWriter(f, fieldnames=list(logged[0]))
        out.writeheader()
        out.writerows([dict(row, wall_time=str(min(float(row["wall_time"]), 1.0))) for row in logged])
    try:
        run_settings(settings, tmp_path, seeds=[0], minutes=0.5, backend="ray")
        first = capsys.readouterr().out
        run_settings(settings, tmp_path, seeds=[0], minutes=0.5, backend="ray")
        second = capsys.readouterr().out
    finally:
        ray.shutdown()
    assert "actor_lr=0.001" in first and ": resumed" in first and ": trained" in first, first
    assert second.count("skipped (complete)") == 2, second
    for setting in settings:  # a budget of half a minute can be all compilation: the untrained row at least
        assert (tmp_path / "runs" / f"{setting.slug}_s0" / "complete.json").exists()
    assert [row["iteration"] for row in read_progress(interrupted)][:2] == ["0", "1"]  # kept what it had
    assert (tmp_path / "summary.md").exists()
    with pytest.raises(ValueError, match="grid entry 'lr=1' is not allowed; use FIELD=V1,V2 with a field of shac"):
        grid_settings("shac", ["cartpole_swingup"], ["lr=1"])

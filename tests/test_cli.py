"""The ``dva`` command line end to end."""

from __future__ import annotations

import csv

import imageio.v3 as iio
import numpy as np
import pytest

import dva.cli
from dva.cli import main
from dva.runner.compiled import compiled, load_run


def test_tasks_lists_every_task_with_sizes(capsys):
    main(["tasks"])
    out = capsys.readouterr().out
    assert "ant" in out and "37" in out and "humanoid" in out and "76" in out
    assert "cartpole_swingup" in out and "240" in out
    rows = {line.split()[0]: line.split() for line in out.splitlines()[1:]}
    assert rows["quadruped"][1:7] == ["49", "12", "1000", "2000", "penalty", "16"]
    assert [rows[task][4] for task in ("hopper", "ant", "humanoid")] == ["3000", "1500", "1000"]  # Fig 4's
    assert "20000 / 1000 / 1000 / 0.9" in " ".join(rows["hopper"])  # the paper's hopper
    assert rows["cartpole_swingup"][7] == "none"  # nothing touches the floor


def test_help_describes_every_command(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for command in ("tasks", "render", "train", "eval", "plot", "compare", "analyze"):
        assert f"• {command}" in out
    assert "analyses behind the method" in out and "Union" not in out  # not typing.Union's docstring


def test_render_writes_grid_and_video(tmp_path):
    main(
        [
            "render",
            "--task",
            "cartpole_swingup",
            "--num-envs",
            "4",
            "--out",
            str(tmp_path),
            "--steps",
            "20",
            "--video-size",
            "96",
        ]
    )
    grid = iio.imread(tmp_path / "cartpole_swingup_observations.png")
    assert grid.shape == (2 * 86 + 2, 2 * 86 + 2, 3)
    frames = iio.imread(tmp_path / "cartpole_swingup_random.mp4")
    assert frames.shape[0] == 20 and frames.shape[-1] == 3
    assert frames.std(axis=0).max() > 10  # the video shows motion


def test_unknown_task_is_one_line_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--task", "walker"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "dva: error: unknown task 'walker'; choose one of: cartpole_swingup, cartpole_balance, hopper, cheetah, ant, humanoid, "  # noqa: E501
        "quadruped, or dmc:<domain>-<task>"
    )


def test_unknown_physics_is_one_line_error(capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--task", "hopper", "--physics", "rigid", "--run-dir", str(tmp_path / "run")])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == "dva: error: unknown physics 'rigid'; choose one of: penalty, mujoco"
    assert not (tmp_path / "run").exists()


def test_bad_image_size_is_one_line_error(capsys):
    with pytest.raises(SystemExit):
        main(["render", "--task", "cartpole_swingup", "--image-size", "5"])
    assert "image width 5 is not allowed" in capsys.readouterr().err


BAD_INPUT = [  # (arguments, what the one-line message says); RUN is a fresh run directory
    (["train", "--minutes", "-3", "--run-dir", "RUN"], "--minutes -3.0 is not allowed; use a number > 0"),
    (["train", "--iterations", "0", "--run-dir", "RUN"], "--iterations 0 is not allowed; use a whole number > 0"),
    (["train", "--eval-episodes", "0", "--run-dir", "RUN"], "--eval-episodes 0 is not allowed; use a whole number ≥ 1"),
    (["compare", "fig4", "--minutes", "0", "--out", "RUN"], "--minutes 0.0 is not allowed"),
    (["train", "--iterations", "1", "--run-dir", "FILE"], "is a file, not a directory"),
    (["train", "--iterations", "1", "--run-dir", "FILE/run"], "cannot be written (Not a directory)"),
    (["train", "--resume", "--run-dir", "RUN"], "--resume: no run to resume in"),
    (  # without --task a resume is the run's own task; with it, it must be the run's
        ["train", "--task", "cartpole_swingup", "--resume", "--run-dir", "SHAC_RUN", "--algo", "shac"],
        "holds a shac run on hopper, not shac on cartpole_swingup; pass --task hopper --algo shac",
    ),
    (
        ["train", "--task", "cartpole_swingup", "--algo", "dva", "--resume", "--run-dir", "SHAC_RUN"],
        "holds a shac run on hopper, not dva on cartpole_swingup; pass --task hopper --algo shac",
    ),
    (  # without --algo a resume is the run's own algorithm, not the default dva
        ["train", "--task", "cartpole_swingup", "--resume", "--run-dir", "SHAC_RUN"],
        "holds a shac run on hopper, not shac on cartpole_swingup; pass --task hopper --algo shac",
    ),
    (
        ["train", "--task", "hopper", "--resume", "--run-dir", "SHAC_RUN", "--shac.horizon", "8"],
        "--shac.* flags (horizon): --resume keeps the run's own config",
    ),
    (["train", "--shac.horizon", "0", "--run-dir", "RUN"], "horizon = 0 is not allowed; use a whole number > 0"),
    (["train", "--shac.actor-lr", "nan", "--run-dir", "RUN"], "actor_lr = nan is not allowed; use a number > 0"),
    (["train", "--shac.actor-lr", "-1", "--run-dir", "RUN"], "actor_lr = -1.0 is not allowed; use a number > 0"),
    (["train", "--shac.gamma", "1.5", "--run-dir", "RUN"], "gamma = 1.5 is not allowed; use a number in (0, 1]"),
    (
        ["train", "--algo", "dva-privileged", "--shac.state-prediction=-2", "--run-dir", "RUN"],
        "state_prediction = -2.0 is not allowed; use a number ≥ 0",
    ),
    (["train", "--algo", "drqv2", "--drqv2.target-tau", "inf", "--run-dir", "RUN"], "target_tau = inf is not allowed"),
    (
        ["train", "--algo", "dreamerv3", "--dreamerv3.model-lr", "0", "--run-dir", "RUN"],
        "model_lr = 0.0 is not allowed",
    ),
    (["report", "--stamp", "fig4_hopper"], "--stamp needs --commit"),
    (["eval", "RUN", "--strip", "FILE", "--strip-frames", "0"], "--strip-frames 0 is not allowed; use a number ≥ 1"),
    (["eval", "RUN", "--episodes", "0"], "--episodes 0 is not allowed; use a number ≥ 1"),
]


@pytest.mark.parametrize(("arguments", "message"), BAD_INPUT, ids=[" ".join(a[:3]) for a, _ in BAD_INPUT])
def test_bad_input_is_one_line_naming_the_value(tmp_path, capsys, arguments, message):
    (tmp_path / "file").write_text("")
    shac_run = tmp_path / "shac_run"
    shac_run.mkdir()
    (shac_run / "run.json").write_text('{"task": "hopper", "algo": "shac", "preset": "cpu", "seed": 0, "config": {}}')
    places = {"RUN": tmp_path / "run", "FILE": tmp_path / "file", "SHAC_RUN": shac_run}
    arguments = [
        str(places[a.split("/")[0]]) + a[len(a.split("/")[0]) :] if a.split("/")[0] in places else a for a in arguments
    ]
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and err.startswith("dva: error: ") and "\n" not in err, err
    assert message in err


def test_a_bug_keeps_its_traceback(monkeypatch):
    """Only bad input becomes a one-line message: any other error (here a ValueError from deep
    inside) propagates with its traceback."""

    def broken(*args, **kwargs):
        raise ValueError("an internal inconsistency")

    monkeypatch.setattr(dva.cli, "train", broken)
    with pytest.raises(ValueError, match="an internal inconsistency"):
        main(["train", "--iterations", "1"])


def test_train_eval_plot_end_to_end_from_pixels(tmp_path, capsys):
    """A tiny D.Va run (pixels, decoupled) through the CLI: train (with its report: plots and a
    policy video) → plot → eval."""
    run_dir = tmp_path / "run"
    main(
        [
            "train",
            "--task",
            "cartpole_swingup",
            "--algo",
            "dva",
            "--iterations",
            "2",
            "--run-dir",
            str(run_dir),
            "--eval-every",
            "2",
            "--shac.num-envs",
            "4",
            "--shac.horizon",
            "8",
            "--shac.image-size",
            "24",
            "--video-size",
            "64",
        ]
    )
    log = (run_dir / "progress.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in log[1:]] == ["0", "1", "2"]  # iteration 0 = untrained policy
    assert "dva on cartpole_swingup: return" in capsys.readouterr().out
    frames = iio.imread(run_dir / "policy.mp4")
    # 240 steps; per env the 24-px camera view upscaled to 64 next to the 64-px view, 4 envs stacked.
    assert frames.shape == (240, 4 * 64 + 5 * 2, 2 * 64 + 2 * 2, 3)
    camera, view = frames[:, 2:66, 2:66], frames[:, 2:66, 66:130]
    assert camera.std(axis=0).max() > 10 and view.std(axis=0).max() > 10  # both panels move
    main(["plot", str(run_dir), str(run_dir), "--out", str(tmp_path / "plots")])
    for name in ("eval_return_vs_env_steps.png", "eval_return_vs_wall_time.png"):
        assert iio.imread(tmp_path / "plots" / name).ndim == 3
        assert (run_dir / name).exists()
    strip = tmp_path / "strip.png"
    main(["eval", str(run_dir), "--seed", "3", "--strip", str(strip), "--strip-frames", "3", "--video-size", "32"])
    assert "over 16 episodes" in capsys.readouterr().out and not (tmp_path / "policy.mp4").exists()
    image = iio.imread(strip)
    assert image.shape == (32 + 2 * 2, 3 * 32 + 4 * 2, 3)  # three 32-px views in a row
    first, last = image[2:34, 2:34], image[2:34, -34:-2]
    assert np.abs(first.astype(int) - last).max() > 30  # the cart-pole moved between them
    # dva eval reused the recorded evaluation the training report compiled (tens of seconds on a CPU)
    assert compiled(load_run(run_dir)[1]).evaluate_recorded._cache_size() == 1


def test_plot_averages_seeds_and_rejects_bad_input(tmp_path):
    from dva.analysis.plots import mean_and_std, past_shortest, plot_runs

    a = {"env_steps": np.array([0.0, 10.0, 20.0]), "eval_return": np.array([0.0, 10.0, 20.0])}
    b = {"env_steps": np.array([0.0, 5.0, 15.0]), "eval_return": np.array([0.0, 15.0, 45.0])}
    x, mean, std = mean_and_std([a, b], "env_steps", "eval_return")
    assert x[0] == 0.0 and x[-1] == 15.0  # up to the shortest run
    np.testing.assert_allclose(mean[-1], (15.0 + 45.0) / 2)
    np.testing.assert_allclose(std[-1], 15.0)
    # the longer seed goes on alone past 15, from its last point at or before it
    ((seed_x, seed_y),) = past_shortest([a, b], "env_steps", "eval_return", x[-1])
    np.testing.assert_array_equal(seed_x, [10.0, 20.0])
    np.testing.assert_array_equal(seed_y, [10.0, 20.0])
    assert past_shortest([a, a], "env_steps", "eval_return", 20.0) == []
    with pytest.raises(ValueError, match="metric 'loss' is not allowed"):
        plot_runs([tmp_path], tmp_path, "loss")
    with pytest.raises(ValueError, match="has no progress.csv"):
        plot_runs([tmp_path], tmp_path)


def test_plot_summary_reports_final_late_best_and_time_to_threshold(tmp_path, monkeypatch):
    import json

    import dva.analysis.plots
    from dva.analysis.plots import write_summary

    monkeypatch.setattr(dva.analysis.plots, "LATE_POINTS", 3)  # the median of each run's last three

    def fake_run(name, algo, seed, rows):
        run_dir = tmp_path / name
        run_dir.mkdir()
        (run_dir / "run.json").write_text(
            json.dumps({"algo": algo, "task": "cartpole_balance", "preset": "cpu", "seed": seed, "config": {}})
        )
        lines = ["env_steps,wall_time,eval_return,train_return"]
        lines += [f"{steps},{seconds},{value},nan" for steps, seconds, value in rows]
        (run_dir / "progress.csv").write_text("\n".join(lines) + "\n")
        return run_dir

    runs = [
        fake_run("a0", "dva", 0, [(0, 0, 100), (500, 30, 50), (1000, 60, 2500), (2000, 120, 2000)]),
        fake_run("a1", "dva", 1, [(0, 0, 100), (1000, 60, 900), (3000, 240, 2200)]),
        fake_run("b0", "curl", 0, [(0, 0, 50), (500, 600, 300)]),
    ]
    path, markdown = write_summary(runs, tmp_path / "out", threshold=2092.0)
    rows = {row["setting"]: row for row in csv.DictReader(path.open())}
    dva, curl = rows["dva on cartpole_balance (cpu preset)"], rows["curl on cartpole_balance (cpu preset)"]
    # Sample stds (ddof 1): finals 2000 and 2200 → 100·√2; late medians 2000 and 900 → 550·√2.
    assert float(dva["final_mean"]) == 2100.0 and float(dva["final_std"]) == pytest.approx(100.0 * 2**0.5)
    assert float(dva["late_mean"]) == 1450.0 and float(dva["late_std"]) == pytest.approx(550.0 * 2**0.5)
    # Two seeds resampled 10,000 times: a quarter of the means are each seed's alone (900, 2000).
    assert (float(dva["late_low"]), float(dva["late_high"])) == (900.0, 2000.0)
    assert float(dva["best_mean"]) == 2350.0 and dva["reached"] == "2"
    assert float(dva["minutes_to_threshold"]) == 2.5  # median of 1 and 4 minutes
    assert float(dva["env_steps_to_threshold"]) == 2000.0
    assert curl["reached"] == "0" and curl["minutes_to_threshold"] == "nan"
    assert "| dva on cartpole_balance (cpu preset) | 2 | 2100 ± 141 | 1450 ± 778 | [900, 2000] | 2350 |" in markdown
    # One seed: its values alone, and no interval (all its resamples are that seed).
    assert (
        "| curl on cartpole_balance (cpu preset) | 1 | 300 | 175 | – | 300 | 10.0 | 500 "
        "| 2092 | 0 / 1 | nan | nan |" in markdown
    )
    assert markdown.endswith("Highest median of the last 3 (mean over seeds): dva on cartpole_balance (cpu preset)\n")
    assert (tmp_path / "out" / "summary.md").read_text() == markdown


def test_diverged_training_exits_with_a_message(tmp_path, monkeypatch, capsys):
    from dva.runner.training import TrainingDiverged

    def diverge(*args, **kwargs):
        raise TrainingDiverged("actor gradient norm 5e+09 is NaN or above 1e+08 at iteration 59", 59, {})

    monkeypatch.setattr(dva.cli, "train", diverge)
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--task", "cartpole_swingup", "--run-dir", str(tmp_path / "run")])
    assert exit_info.value.code == 3
    message = capsys.readouterr().err
    assert "training stopped: actor gradient norm 5e+09 is NaN or above 1e+08 at iteration 59" in message
    assert "--shac.state-grad-clip" in message
    # Each algorithm's hint names its own flags: a CURL run is not told about --shac.*.
    with pytest.raises(SystemExit):
        main(["train", "--task", "cartpole_swingup", "--algo", "curl", "--run-dir", str(tmp_path / "curl")])
    message = capsys.readouterr().err
    assert "--curl.lr" in message and "--shac." not in message


def test_plot_labels_keep_clipped_runs_apart(tmp_path):
    import json

    from dva.analysis.plots import run_label

    spec = {"algo": "shac", "task": "humanoid", "preset": "cpu", "config": {"state_grad_clip": None}}
    (tmp_path / "run.json").write_text(json.dumps(spec))
    exact = run_label(tmp_path)
    spec["config"]["state_grad_clip"] = 100.0
    (tmp_path / "run.json").write_text(json.dumps(spec))
    assert exact == "shac on humanoid (cpu preset)"
    assert run_label(tmp_path) == "shac on humanoid (cpu preset, state grad clip 100)"


def test_analyze_gradients_writes_table_and_figure(tmp_path, capsys):
    main(
        [
            "analyze",
            "gradients",
            "--task",
            "cartpole_swingup",
            "--iterations",
            "4",
            "--every",
            "2",
            "--num-envs",
            "4",
            "--horizon",
            "8",
            "--out",
            str(tmp_path),
        ]
    )
    out_dir = tmp_path / "gradients_cartpole_swingup"
    lines = (out_dir / "apg_vs_dpg.csv").read_text().splitlines()
    assert lines[0] == "iteration,cosine,apg_norm,dpg_norm,train_return" and len(lines) == 1 + 3  # its 0, 2, 4
    for line in lines[1:]:
        _, cosine, apg_norm, dpg_norm, _ = map(float, line.split(","))
        assert -1.0 <= cosine <= 1.0 and apg_norm > 0 and dpg_norm > 0
        assert cosine < 1.0 - 1e-6  # different gradients: the observation path contributes
    assert iio.imread(out_dir / "apg_vs_dpg.png").ndim == 3


def test_train_flags_reach_every_config_field_of_the_chosen_algorithm_only():
    import tyro

    from dva.cli import TrainCommand

    command = tyro.cli(
        TrainCommand, args=["--algo", "dagger", "--teacher", "runs/teacher", "--dagger.batch-size", "64"]
    )
    assert command.config_overrides() == {"teacher": "runs/teacher", "batch_size": 64}
    command = tyro.cli(TrainCommand, args=["--algo", "drqv2", "--drqv2.hidden", "32", "32", "--drqv2.n-step", "5"])
    assert command.config_overrides() == {"hidden": (32, 32), "n_step": 5}
    command = tyro.cli(TrainCommand, args=["--algo", "curl", "--shac.horizon", "8"])
    with pytest.raises(ValueError, match=r"--shac.\* flags \(horizon\) do not apply to --algo curl"):
        command.config_overrides()


def test_a_new_algorithm_is_one_registry_entry(monkeypatch):
    """Registering an algorithm is all it takes: its config's flags appear under its own group in
    `dva train`, its preset and defining values reach its config."""
    import dataclasses
    import importlib

    import dva.algorithms as algorithms
    import dva.cli

    @dataclasses.dataclass(frozen=True)
    class ToyConfig:
        """A toy algorithm's hyperparameters."""

        num_envs: int = 4
        image_size: int = 48
        frame_stack: int = 1
        step_size: float = 0.1
        variant: str = "plain"

    entry = dataclasses.replace(
        algorithms.ALGORITHMS["drqv2"],
        config_type=ToyConfig,
        preset=lambda task, preset: dict(num_envs=8),
        defining=dict(variant="toy"),
        flag_group="toy",
        divergence_hint="a smaller step (--toy.step-size)",
    )
    monkeypatch.setitem(algorithms.ALGORITHMS, "toy", entry)
    cli = importlib.reload(dva.cli)
    try:
        command = cli.TrainCommand(algo="toy", toy=cli.OVERRIDES["toy"](step_size=0.5))
        assert command.config_overrides() == {"step_size": 0.5}
        assert "variant" not in {field.name for field in dataclasses.fields(cli.OVERRIDES["toy"])}
        config = algorithms.make_config("cartpole_swingup", "toy", "cpu", step_size=0.5)
        assert config == ToyConfig(num_envs=8, step_size=0.5, variant="toy")
    finally:
        monkeypatch.undo()
        importlib.reload(dva.cli)

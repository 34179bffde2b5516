"""The analyses behind ``dva analyze``: their arithmetic on hand-made numbers, and each command
end to end on a tiny configuration (the same one as the CLI training test, so compiles are shared)."""

from __future__ import annotations

import csv

import imageio.v3 as iio
import numpy as np
import pytest

from dva.analysis import profile
from dva.analysis.cost import measure_costs, ratios, write_cost_report
from dva.analysis.profile import encoder_flops, per_million_steps
from dva.cli import main
from dva.runner.runtime import cpu_model

TINY = ["--num-envs", "4", "--horizon", "8", "--image-size", "24"]


def read_rows(path):
    with path.open() as f:
        return list(csv.DictReader(f))


def test_per_million_steps_splits_the_iteration_by_hand():
    times = {
        "rollout_forward": 0.5,
        "render": 0.2,
        "actor_forward": 0.1,
        "rollout_backward": 0.3,
        "actor_backward": 0.4,
        "critic": 0.05,
        "iteration": 1.6,
    }
    parts = per_million_steps(times, num_envs=10, horizon=100)  # 1000 steps per iteration → × 1000
    assert parts == pytest.approx(
        {
            "simulation forward": 200.0,
            "simulation backward": 300.0,
            "rendering": 200.0,
            "actor forward": 100.0,
            "actor backward": 400.0,
            "critic fitting": 50.0,
            "other": 350.0,
        }
    )  # 1.6 − 1.25 s
    fused = per_million_steps({**times, "iteration": 1.0}, num_envs=10, horizon=100)
    assert fused["other"] == 0.0  # faster than its parts: nothing left over, never negative


def test_encoder_flops_count_the_drqv2_encoder_by_hand():
    """48² × 9 → 23² (stride 2), 21², 19², 17² × 32 channels, then 17² × 32 → 64: 2 × multiply-adds."""
    conv = [2 * 23**2 * 32 * 9 * 9, 2 * 21**2 * 32 * 9 * 32, 2 * 19**2 * 32 * 9 * 32, 2 * 17**2 * 32 * 9 * 32]
    projection = 2 * 17**2 * 32 * 64
    flops = encoder_flops(48, 9, trunk=64)
    assert flops["forward"] == sum(conv) + projection == 24_035_392
    # weight gradients of every layer, input gradients of all but the first (pixels need none)
    assert flops["backward"] == sum(conv) + sum(conv[1:]) + 2 * projection == 45_328_448


def test_blas_rate_is_a_matmuls_flops_over_its_fastest_repeat(monkeypatch):
    """A clock that makes the three repeats last 4, 2 and 3 s: the rate is 2 · size³ over the 2 s."""
    ticks = iter([0.0, 4.0, 10.0, 12.0, 20.0, 23.0])
    monkeypatch.setattr("time.perf_counter", lambda: next(ticks))
    assert profile.blas_flops_per_s(size=8, repeats=3) == 2 * 8**3 / 2.0


def test_matmul_rates_keep_xlas_best_repeat_beside_the_blas(monkeypatch):
    """The bound's two rates: the best of XLA's repeats, and the BLAS's on the CPU; off it, no BLAS."""
    xla = iter([3e9, 5e9, 4e9, 3e9, 5e9, 4e9])
    monkeypatch.setattr(profile.jax, "default_backend", lambda: "cpu")
    monkeypatch.setattr(profile, "matmul_flops_per_s", lambda: next(xla))
    monkeypatch.setattr(profile, "blas_flops_per_s", lambda repeats: 7e9 + repeats)
    assert profile.matmul_rates(repeats=3) == (5e9, 7e9 + 3)
    monkeypatch.setattr(profile.jax, "default_backend", lambda: "gpu")
    assert profile.matmul_rates(repeats=3) == (5e9, 0.0)


def test_cost_ratios_divide_visual_shac_by_dva():
    rows = [
        {"task": "hopper", "algo": "dva", "variant": "dva", "backward_s": 0.2, "peak_memory_mb": 100.0},
        {"task": "hopper", "algo": "dva", "variant": "dva, chunk 4", "backward_s": 0.25, "peak_memory_mb": 50.0},
        {"task": "hopper", "algo": "shac-pixels", "variant": "shac-pixels", "backward_s": 0.5, "peak_memory_mb": 400.0},
        {"task": "cheetah", "algo": "dva", "variant": "dva", "backward_s": 1.0, "peak_memory_mb": 10.0},
        {"task": "cheetah", "algo": "shac-pixels", "variant": "shac-pixels", "backward_s": 3.0, "peak_memory_mb": 20.0},
    ]
    hopper, hopper_chunked, cheetah = ratios(rows)
    assert hopper == pytest.approx(
        {
            "task": "hopper",
            "variant": "dva",
            "backward_ratio": 2.5,
            "memory_ratio": 4.0,
            "paper_backward_ratio": 0.51 / 0.19,
        }
    )
    assert hopper_chunked["variant"] == "dva, chunk 4" and hopper_chunked["memory_ratio"] == pytest.approx(8.0)
    assert hopper_chunked["backward_ratio"] == pytest.approx(2.0)
    assert cheetah["task"] == "cheetah" and cheetah["backward_ratio"] == pytest.approx(3.0)
    assert np.isnan(cheetah["paper_backward_ratio"])  # not in the paper's Table 1


def test_analyze_cost_end_to_end(tmp_path, capsys):
    # Without the kept-backward variant (one compile less; both gradients are checked in test_shac
    # and a second D.Va row in test_cost_ratios_divide_visual_shac_by_dva).
    main(["analyze", "cost", "--tasks", "cartpole_swingup", *TINY, "--chunk", "2", "--out", str(tmp_path)])
    costs = read_rows(tmp_path / "cost" / "cost.csv")
    assert [r["variant"] for r in costs] == ["dva, chunk 2", "shac-pixels"]
    dva_row, visual_row = costs
    # at this size D.Va's backward is within timing noise of zero; visual SHAC's, through the
    # rasteriser and every step's encoder, is not
    assert float(visual_row["backward_s"]) > max(float(dva_row["backward_s"]), 0.0)
    assert float(dva_row["forward_s"]) > 0 and np.isfinite(float(dva_row["backward_s"]))
    for row in costs:
        # at least the 8 × 4 stacked 24² frames (uint8) the rollout keeps for the backward pass
        assert float(row["peak_memory_mb"]) * 2**20 > 8 * 4 * 24 * 24 * 9
    assert "| cartpole_swingup |" in capsys.readouterr().out
    assert iio.imread(tmp_path / "cost" / "cost.png").ndim == 3
    # --no-timing compiles the same gradients from shapes alone: the same memory, no times.
    memory_only = measure_costs(["cartpole_swingup"], num_envs=4, horizon=8, image_size=24, chunk=2, timing=False)
    for row, timed_row in zip(memory_only, costs, strict=True):
        assert row["peak_memory_mb"] == pytest.approx(float(timed_row["peak_memory_mb"]), rel=1e-6)
        assert np.isnan(row["backward_s"]) and np.isnan(row["forward_s"])
    _, markdown = write_cost_report(memory_only, tmp_path / "memory_only", "memory only")
    assert "| cartpole_swingup | dva, chunk 2 |" in markdown
    assert iio.imread(tmp_path / "memory_only" / "cost.png").ndim == 3


@pytest.mark.slow  # ≈ 6 min of compiling on 2 cores
def test_analyze_breakdown_and_gradnorm_end_to_end(tmp_path, capsys):
    main(["analyze", "breakdown", "--task", "cartpole_swingup", *TINY, "--out", str(tmp_path)])
    parts = read_rows(tmp_path / "breakdown_cartpole_swingup" / "breakdown.csv")
    assert [p["part"] for p in parts][:3] == ["simulation forward", "simulation backward", "rendering"]
    assert sum(float(p["share"]) for p in parts) == pytest.approx(1.0)
    assert all(float(p["seconds_per_million_steps"]) > 0 for p in parts if p["part"] in ("rendering", "actor backward"))

    main(["analyze", "gradnorm", "--tasks", "cartpole_swingup", "--iterations", "2", *TINY, "--out", str(tmp_path)])
    norms = read_rows(tmp_path / "gradnorm" / "gradnorm.csv")
    assert [(r["algo"], r["iteration"]) for r in norms] == [
        ("dva", "1"),
        ("dva", "2"),
        ("shac-pixels", "1"),
        ("shac-pixels", "2"),
    ]
    assert all(np.isfinite(float(r["actor_grad_norm"])) and float(r["actor_grad_norm"]) > 0 for r in norms)
    assert iio.imread(tmp_path / "gradnorm" / "gradnorm.png").ndim == 3

    # Asked for more iterations, the analysis continues its runs from their checkpoints.
    main(["analyze", "gradnorm", "--tasks", "cartpole_swingup", "--iterations", "3", *TINY, "--out", str(tmp_path)])
    longer = read_rows(tmp_path / "gradnorm" / "gradnorm.csv")
    assert [r["iteration"] for r in longer if r["algo"] == "dva"] == ["1", "2", "3"]
    kept = [(r["algo"], r["iteration"], r["actor_grad_norm"]) for r in longer if r["iteration"] != "3"]
    assert kept == [(r["algo"], r["iteration"], r["actor_grad_norm"]) for r in norms]
    # A run of another configuration in the same folder is refused, not overwritten.
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["analyze", "gradnorm", "--tasks", "cartpole_swingup", "--iterations", "3", *TINY[:2], "--horizon", "4",
              "--image-size", "24", "--out", str(tmp_path)])  # fmt: skip
    assert "holds a run of another setting" in capsys.readouterr().err


def test_analyze_rejects_unknown_task(capsys):
    with pytest.raises(SystemExit):
        main(["analyze", "cost", "--tasks", "cartpole_swingup", "walker"])
    assert "unknown task 'walker'" in capsys.readouterr().err


def test_cpu_model_names_the_first_processors_model_family_and_number(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    first = "processor\t: 0\ncpu family\t: 26\nmodel\t\t: 2\nmodel name\t: AMD EPYC\n"
    cpuinfo.write_text(first + "\nprocessor\t: 1\ncpu family\t: 25\nmodel\t\t: 1\nmodel name\t: other\n")
    assert cpu_model(cpuinfo) == "AMD EPYC, family 26 model 2"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: Some CPU\n")  # no family (other architectures)
    assert cpu_model(cpuinfo) == "Some CPU"
    assert cpu_model(tmp_path / "absent")  # no /proc/cpuinfo: the platform's answer, or "unknown CPU"

"""End-to-end learning checks (slow: minutes each; run with ``pytest -m slow``).

They train with the CPU preset exactly as ``dva train`` does and compare the deterministic
evaluation return with a uniform-random policy's on the same task. Each budget is in iterations
(the iterations the measured runs of docs/results.md had made after the minutes each docstring
names), so a slower machine takes longer but judges the same training.
"""

from __future__ import annotations

import csv

import jax
import numpy as np
import pytest

from dva.runner.evaluation import random_policy_returns
from dva.runner.training import train
from dva.tasks import make_task

pytestmark = pytest.mark.slow


END_EVALUATIONS = 5


def end_eval_return(run_dir) -> float:
    """Where the run ended: the median of its last five evaluations. A run that learns and then
    forgets fails; one dip (a fall in one episode) among good evaluations does not decide it."""
    with (run_dir / "progress.csv").open() as f:
        returns = [float(r["eval_return"]) for r in csv.DictReader(f) if r["eval_return"] != ""]
    assert len(returns) > END_EVALUATIONS, f"only {len(returns)} evaluations"
    return float(np.median(returns[-END_EVALUATIONS:]))


def random_return(task_name: str) -> float:
    return float(np.mean(random_policy_returns(make_task(task_name), jax.random.PRNGKey(0), 64)))


def test_shac_on_cartpole_state_learns(tmp_path):
    """SHAC (state observations): about 2 minutes."""
    run_dir = train("cartpole_swingup", "shac", preset="cpu", iterations=400, run_dir=tmp_path / "run", eval_every=50)
    assert end_eval_return(run_dir) > 3 * random_return("cartpole_swingup")


def test_shac_on_hopper_state_learns_to_hop(tmp_path):
    """SHAC on Hopper with penalty contacts, CPU preset: about 7 minutes. The run in
    docs/results.md ended at 4596, the median of its last ten 4316; 2000 leaves room for a less
    lucky seed."""
    run_dir = train("hopper", "shac", preset="cpu", iterations=1500, run_dir=tmp_path / "run", eval_every=50)
    assert end_eval_return(run_dir) > 2000


def test_dva_on_cartpole_pixels_beats_random_by_a_wide_margin(tmp_path):
    """D.Va from pixels, the README's main job: 2500 iterations, the main job's 15 minutes on 2 cores."""
    run_dir = train("cartpole_swingup", "dva", preset="cpu", iterations=2500, run_dir=tmp_path / "run", eval_every=50)
    assert end_eval_return(run_dir) > 3 * random_return("cartpole_swingup")


def test_dva_privileged_on_hopper_pixels_learns_to_hop(tmp_path):
    """dva-privileged (D.Va with the state-prediction loss) from 48² pixels on Hopper, CPU preset:
    1300 iterations, 20 minutes on one core. Fig 4's two runs (docs/results.md) passed 3000 at
    14 and 16 minutes (under 1100 iterations) and held above it."""
    run_dir = train("hopper", "dva-privileged", preset="cpu", iterations=1300, run_dir=tmp_path / "run", eval_every=100)
    assert end_eval_return(run_dir) > 2000


@pytest.mark.parametrize(("algo", "iterations"), [("drqv2", 3850), ("curl", 6950)])
def test_pixel_baselines_learn_cartpole_balance(tmp_path, algo, iterations):
    """DrQ-v2 and CURL from pixels, CPU preset (seed phase included), for the iterations each
    made in 60 minutes alone on 2 cores (docs/results.md): the median of their last ten
    evaluations then 2388 (DrQ-v2) and 2356 (CURL) of 2400."""
    run_dir = train(
        "cartpole_balance", algo, preset="cpu", iterations=iterations, run_dir=tmp_path / "run", eval_every=100
    )
    assert end_eval_return(run_dir) > 2 * random_return("cartpole_balance")


def test_dreamerv3_on_the_state_learns_to_balance(tmp_path):
    """DreamerV3 on Cart-pole's state vector, CPU preset: 1500 iterations (15 minutes on one core). A
    random policy already earns almost half the maximum on balance (≈ 1040 of 2400: the pole starts
    upright and takes a while to fall), so "learned" is holding it up for most of each episode at
    the end of the run: the median of the last evaluations above 1.5× random (≈ 1570). The runs in
    docs/results.md, one core each, ended with medians of their last ten at 1778 and 1905 (seeds 0 /
    1); their evaluations, which sample the actor, swing between ≈ 1300 and 2300 after the fifth
    minute. With the actor's learning rate at 8e-5 instead of the preset's 2e-4 this seed fell back
    below the bar in its last minutes. (From pixels, DreamerV3 stays below 2× random after two CPU
    hours.)"""
    run_dir = train(
        "cartpole_balance", "dreamerv3-state", preset="cpu", iterations=1500, run_dir=tmp_path / "run", eval_every=25
    )
    assert end_eval_return(run_dir) > 1.5 * random_return("cartpole_balance")


def test_tdmpc2_on_the_state_learns_to_balance(tmp_path):
    """TD-MPC2 on Cart-pole's state vector, CPU preset: 2600 iterations (11.5 minutes on a shared core),
    the bar DreamerV3's test sets (the median of the last evaluations above 1.5× random). The run in
    docs/results.md, on a core shared with two other processes, first reached 1.9× random at 7.3
    minutes and ended with a median of its last ten at 2063 (2.0×)."""
    run_dir = train(
        "cartpole_balance", "tdmpc2-state", preset="cpu", iterations=2600, run_dir=tmp_path / "run", eval_every=200
    )
    assert end_eval_return(run_dir) > 1.5 * random_return("cartpole_balance")

"""End-to-end learning checks (slow: minutes each; run with ``pytest -m slow``).

They train with the CPU preset exactly as ``dva train`` does and compare the deterministic
evaluation return with a uniform-random policy's on the same task.
"""

from __future__ import annotations

import csv

import jax
import numpy as np
import pytest

from dva.evaluation import random_policy_returns
from dva.tasks import make_task
from dva.training import train

pytestmark = pytest.mark.slow


def late_eval_return(run_dir) -> float:
    """The best of the last three evaluations: the policy still dips now and then (a bad
    evaluation among good ones), and one dip should not decide the check."""
    with (run_dir / "progress.csv").open() as f:
        returns = [float(r["eval_return"]) for r in csv.DictReader(f) if r["eval_return"] != ""]
    return max(returns[-3:])


def random_return(task_name: str) -> float:
    return float(np.mean(random_policy_returns(make_task(task_name), jax.random.PRNGKey(0), 64)))


def test_shac_on_cartpole_state_learns(tmp_path):
    """SHAC (state observations): about 2 minutes."""
    run_dir = train("cartpole_swingup", "shac", preset="cpu", iterations=400, run_dir=tmp_path / "run", eval_every=50)
    assert late_eval_return(run_dir) > 3 * random_return("cartpole_swingup")


def test_shac_on_hopper_state_learns_to_hop(tmp_path):
    """SHAC on Hopper with penalty contacts, CPU preset: about 7 minutes. The two 30-minute runs
    on the previous Hopper model had their best of the evaluations at 1400–1500 iterations at 4546
    and 6851 (random actions: ≈ −140); 2000 leaves room for a less lucky seed."""
    run_dir = train("hopper", "shac", preset="cpu", iterations=1500, run_dir=tmp_path / "run", eval_every=50)
    assert late_eval_return(run_dir) > 2000


def test_dva_on_cartpole_pixels_beats_random_by_a_wide_margin(tmp_path):
    """D.Va from pixels, the README's main job: about 15 minutes."""
    run_dir = train("cartpole_swingup", "dva", preset="cpu", minutes=15, run_dir=tmp_path / "run", eval_every=50)
    assert late_eval_return(run_dir) > 3 * random_return("cartpole_swingup")


def test_dva_on_hopper_pixels_learns_to_hop(tmp_path):
    """D.Va from 48² pixels on Hopper, CPU preset (state-prediction loss on): 20 minutes. Two runs
    on one core each (docs/results.md) first passed 3000 at 17.1 and 10.6 minutes, their best of
    the last three evaluations by 20 minutes 3624 and 3913 (random actions: ≈ −140)."""
    run_dir = train("hopper", "dva", preset="cpu", minutes=20, run_dir=tmp_path / "run", eval_every=100)
    assert late_eval_return(run_dir) > 2000


@pytest.mark.parametrize(("algo", "minutes"), [("drqv2", 60), ("curl", 60)])
def test_pixel_baselines_learn_cartpole_balance(tmp_path, algo, minutes):
    """DrQ-v2 and CURL from pixels, CPU preset (seed phase included). DrQ-v2 alone on
    2 cores (docs/results.md): best of the last three evaluations 1710 / 2090 / 2358 at
    20 / 40 / 50 minutes, above 2× random for good from 49 minutes, 2384 at 60. CURL alone: 18 of
    its 26 evaluations over minutes 48–58 above 2× random, the best of the last three 2371."""
    run_dir = train("cartpole_balance", algo, preset="cpu", minutes=minutes, run_dir=tmp_path / "run", eval_every=100)
    assert late_eval_return(run_dir) > 2 * random_return("cartpole_balance")


def best_eval_return(run_dir) -> float:
    with (run_dir / "progress.csv").open() as f:
        return max(float(r["eval_return"]) for r in csv.DictReader(f) if r["eval_return"] != "")


def test_dreamerv3_on_the_state_learns_to_balance(tmp_path):
    """DreamerV3 on Cart-pole's state vector, CPU preset: 15 minutes. A random policy already earns
    almost half the maximum on balance (≈ 1040 of 2400: the pole starts upright and takes a while
    to fall), so "learned" is holding it up for whole episodes: an evaluation at 1.9× random
    (≈ 1980). The run in docs/results.md, alone on one core, first reached it at 3.3 minutes
    (325 updates) and 10 of its 61 evaluations did; they swing between ≈ 1200 and 2180, so the
    check reads the best evaluation, not the last ones. (From pixels, DreamerV3 stays below 2×
    random after two CPU hours: docs/results.md.)"""
    run_dir = train(
        "cartpole_balance", "dreamerv3-state", preset="cpu", minutes=15, run_dir=tmp_path / "run", eval_every=25
    )
    assert best_eval_return(run_dir) > 1.9 * random_return("cartpole_balance")


def test_tdmpc2_on_the_state_learns_to_balance(tmp_path):
    """TD-MPC2 on Cart-pole's state vector, CPU preset: 12 minutes, the bar DreamerV3's test sets
    (an evaluation at 1.9× random: the pole held up for whole episodes). The run in
    docs/results.md, on a core shared with two other processes, first reached it at 7.3 minutes
    and scored 2395 of the 2400 maximum at 10 minutes."""
    run_dir = train(
        "cartpole_balance", "tdmpc2-state", preset="cpu", minutes=12, run_dir=tmp_path / "run", eval_every=200
    )
    assert best_eval_return(run_dir) > 1.9 * random_return("cartpole_balance")

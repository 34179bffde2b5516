"""The examples in examples/ run and do what their docs say."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_ppo_through_gymnasium_learns_cartpole_swingup_from_the_state():
    """CleanRL-style PPO on gymnasium.make_vec("dva/cartpole_swingup-v0"): the first rollouts'
    episodes score ≈ 150 (random actions ≈ 300); after 65k env steps it swings the pole up
    (≈ 1300 measured; 1900 after 400k)."""
    ppo = load("ppo_gymnasium")
    curve = ppo.main(ppo.Args(total_steps=65_536))
    first, last = curve[0][1], curve[-1][1]
    assert first < 500 and last > 1000, curve

"""The random policy's evaluation return per task: the reference the results judge a policy by
("2× random").

    python benchmarks/random_returns.py [--tasks cartpole_swingup hopper] [--episodes 64] [--csv random.csv]

Uniform random actions in [−1, 1], one full episode per env from a fresh reset, exactly as a
trained policy is evaluated (:func:`dva.runner.evaluation.random_policy_returns`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np

import dva
from dva.analysis.bench import write_csv
from dva.runner.evaluation import random_policy_returns
from dva.tasks import BUILTIN_TASKS, make_task


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(BUILTIN_TASKS), choices=list(BUILTIN_TASKS))
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--csv", type=Path, help="also write the rows to this CSV file")
    args = parser.parse_args()
    rows = []
    print("| task | episodes | mean | std |\n|---|---|---|---|")
    for name in args.tasks:
        returns = np.asarray(random_policy_returns(make_task(name), jax.random.PRNGKey(args.seed), args.episodes))
        rows.append(dict(task=name, episodes=args.episodes, mean=returns.mean(), std=returns.std()))
        print(f"| {name} | {args.episodes} | {returns.mean():.0f} | {returns.std():.0f} |", flush=True)
    if args.csv:
        print(f"wrote {write_csv(args.csv, rows)}")


if __name__ == "__main__":
    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

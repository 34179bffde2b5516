"""Env steps/s through the Gymnasium vector env against the task's own jitted step.

    python benchmarks/gymnasium_overhead.py [--tasks cartpole_swingup hopper] [--num-envs 16 256]
                                            [--steps 200]

"task.step" calls the jitted ``task.step`` once per control step with the batch on the device
(no copies); "gymnasium" steps ``gymnasium.make_vec("dva/<task>-v0")`` with NumPy actions in and
NumPy observations, rewards and flags out, as a Gymnasium training loop does. Both state-only.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium
import jax
import numpy as np

import dva


def steps_per_second(step, steps: int) -> float:
    step()  # compile
    start = time.perf_counter()
    for _ in range(steps):
        out = step()
    jax.block_until_ready(out)
    return steps / (time.perf_counter() - start)


def measure(task_name: str, num_envs: int, steps: int) -> tuple[float, float]:
    envs = gymnasium.make_vec(f"dva/{task_name}-v0", num_envs=num_envs)
    envs.reset(seed=0)
    actions = np.zeros(envs.action_space.shape, np.float32)
    wrapped = steps_per_second(lambda: envs.step(actions)[1], steps)

    task = envs.unwrapped.task
    state = [jax.jit(task.reset, static_argnums=1)(jax.random.PRNGKey(0), num_envs)]
    step, device_actions = jax.jit(task.step), jax.numpy.asarray(actions)

    def raw():
        state[0] = step(state[0], device_actions)
        return state[0].reward

    return steps_per_second(raw, steps) * num_envs, wrapped * num_envs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["cartpole_swingup", "hopper"])
    parser.add_argument("--num-envs", nargs="+", type=int, default=[16, 256])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--csv", type=Path, help="also write the rows to this CSV file")
    args = parser.parse_args()
    records = []
    print(f"device: {jax.devices()[0].device_kind}")
    print("| task | envs | task.step env steps/s | gymnasium env steps/s | gymnasium / task.step |")
    print("|---|---|---|---|---|")
    for task in args.tasks:
        for num_envs in args.num_envs:
            raw, wrapped = measure(task, num_envs, args.steps)
            print(f"| {task} | {num_envs} | {raw:,.0f} | {wrapped:,.0f} | {wrapped / raw:.2f} |", flush=True)
            records.append(dict(task=task, num_envs=num_envs, task_step=raw, gymnasium=wrapped, ratio=wrapped / raw))
    if args.csv:
        from dva.analysis.bench import write_csv

        print(f"wrote {write_csv(args.csv, records)}")


if __name__ == "__main__":
    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

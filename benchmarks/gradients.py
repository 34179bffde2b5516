"""Gradient norm of the return versus horizon, per task, with the contact parameters used.

    python benchmarks/gradients.py [--tasks ant humanoid] [--num-envs 16]

For each horizon h in 1, 2, 4 … 32 it differentiates the h-step return (sum of rewards, from a
state reached after 60 random steps so the robots stand on the floor) with respect to all actions
and prints the mean per-env gradient norm. Exploding contacts show as norms that grow by orders
of magnitude with h; bounded ones grow roughly linearly (more actions, more reward terms).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from dva.analysis.bench import machine_description, markdown_table
from dva.tasks import PHYSICS, TASKS, make_task

HORIZONS = (1, 2, 4, 8, 16, 32)


def gradient_norms(name: str, physics: str, num_envs: int, seed: int = 0) -> list[float]:
    task = make_task(name, physics)
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    max_h = max(HORIZONS)

    @jax.jit
    def warm_state(key):
        state = task.reset(key, num_envs)
        actions = jax.random.uniform(keys[1], (60, num_envs, task.action_dim), minval=-0.5, maxval=0.5)
        return jax.lax.scan(lambda s, a: (task.step(s, a), None), state, actions)[0]

    def horizon_return(actions, state, horizon):
        def one(carry, inputs):
            state, total = carry
            t, action = inputs
            state = task.step(state, action)
            return (state, total + jnp.where(t < horizon, state.reward, 0.0)), None

        (_, total), _ = jax.lax.scan(one, (state, jnp.zeros(num_envs)), (jnp.arange(max_h), actions))
        return total.sum()

    grad = jax.jit(jax.grad(horizon_return))
    state = warm_state(keys[0])
    actions = jax.random.uniform(keys[2], (max_h, num_envs, task.action_dim), minval=-0.5, maxval=0.5)
    norms = []
    for horizon in HORIZONS:
        g = np.asarray(grad(actions, state, horizon))  # (T, N, A); per-env norm over its actions
        norms.append(float(np.sqrt((g**2).sum(axis=(0, 2))).mean()))
    return norms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--physics", nargs="+", default=list(PHYSICS), choices=list(PHYSICS))
    parser.add_argument("--num-envs", type=int, default=16)
    args = parser.parse_args()
    rows = []
    for name in args.tasks:
        for physics in args.physics:
            task = make_task(name, physics)
            norms = gradient_norms(name, physics, args.num_envs)
            growth = norms[-1] / norms[0]
            rows.append([name, physics, *(f"{n:.3g}" for n in norms), f"{growth:.3g}", task.substeps])
            print(f"{name} {physics}: done", flush=True)
    print(f"\nGradient norm of the h-step return w.r.t. the actions (mean over {args.num_envs} envs); {machine_description()}\n")
    print(markdown_table(["task", "physics", *(f"h={h}" for h in HORIZONS), "h=32 / h=1", "substeps"], rows))


if __name__ == "__main__":
    main()

"""Gradient norm of the return versus horizon, per task and contact model, for random actions
and for trained policies.

    python benchmarks/gradients.py [--tasks ant humanoid] [--physics penalty mujoco] [--num-envs 16]
    python benchmarks/gradients.py --runs runs/hopper_shac_s0 …   # trained (state) policies

For each horizon h in 1, 2, 4 … 32 it differentiates the h-step return (sum of rewards, from a
state reached after 60 steps, so the legged robots stand or lie on the floor) with respect to all
actions and prints the mean per-env gradient norm, and the median env's own h=32 / h=1 (a mean
can be one env's). Random actions are open loop, uniform in
[−0.5, 0.5]; a trained policy acts in closed loop (``a_t = π(s_t) + δ_t``, the gradient is with
respect to the offsets δ and runs through the policy too, as SHAC's does).

How to read it: bounded physics still makes the norm grow polynomially with h — a reward on a
velocity (momentum carries an action's effect forward) gives h=32 / h=1 ≈ 100, a reward on a
position (integrated twice) ≈ 2600 — so the last column, growth from h=16 to h=32, separates
the two: ≤ 2^2.5 ≈ 5.7 is polynomial, larger is explosion.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dva.analysis.bench import machine_description, markdown_table
from dva.tasks import BUILTIN_TASKS, make_task
from dva.tasks.physics import PHYSICS

HORIZONS = (1, 2, 4, 8, 16, 32)
WARM_UP_STEPS = 60


def gradient_norms(
    name: str, physics: str, num_envs: int, seed: int = 0, policy: Callable[[jax.Array], jax.Array] | None = None
) -> np.ndarray:
    """Per-env norms of ∇_actions (h-step return), shape (len(HORIZONS), num_envs).

    ``policy`` maps state observations (N, obs_dim) to actions in [−1, 1]; None: random actions.
    """
    task = make_task(name, physics)
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    max_h = max(HORIZONS)

    def act(state, offset):
        return offset if policy is None else policy(state.obs) + offset

    @jax.jit
    def warm_state(key):
        state = task.reset(key, num_envs)
        noise = jax.random.uniform(keys[1], (WARM_UP_STEPS, num_envs, task.action_dim), minval=-0.5, maxval=0.5)
        noise = noise if policy is None else 0.0 * noise
        return jax.lax.scan(lambda s, a: (task.step(s, act(s, a)), None), state, noise)[0]

    def horizon_return(offsets, state, horizon):
        def one(carry, inputs):
            state, total = carry
            t, offset = inputs
            state = task.step(state, act(state, offset))
            return (state, total + jnp.where(t < horizon, state.reward, 0.0)), None

        (_, total), _ = jax.lax.scan(one, (state, jnp.zeros(num_envs)), (jnp.arange(max_h), offsets))
        return total.sum()

    grad = jax.jit(jax.grad(horizon_return))
    state = warm_state(keys[0])
    offsets = jax.random.uniform(keys[2], (max_h, num_envs, task.action_dim), minval=-0.5, maxval=0.5)
    if policy is not None:
        offsets = jnp.zeros_like(offsets)
    norms = []
    for horizon in HORIZONS:
        g = np.asarray(grad(offsets, state, horizon))  # (T, N, A); per-env norm over its actions
        norms.append(np.sqrt((g**2).sum(axis=(0, 2))))
    return np.stack(norms)


def trained_policy(run_dir: Path) -> tuple[str, str, Callable[[jax.Array], jax.Array]]:
    """(task, physics, deterministic policy) of a state-observation run's latest checkpoint."""
    from dva.runner.compiled import load_run

    spec, agent, state = load_run(run_dir)
    if agent.config.observation != "state":
        raise ValueError(f"{run_dir} learned from pixels; --runs takes state-observation runs (shac, dpg-state)")

    def policy(obs: jax.Array) -> jax.Array:
        return jnp.tanh(agent.pre_tanh_action(state.actor_params, state.obs_stats.normalize(obs), None))

    return spec.task, make_task(spec.task, spec.physics).physics, policy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(BUILTIN_TASKS), choices=list(BUILTIN_TASKS))
    parser.add_argument("--physics", nargs="+", default=list(PHYSICS), choices=list(PHYSICS))
    parser.add_argument("--runs", nargs="+", type=Path, default=[], help="trained state-policy runs (replaces --tasks)")
    parser.add_argument("--num-envs", type=int, default=16)
    args = parser.parse_args()
    cases = [(run.name, *trained_policy(run)) for run in args.runs] or [
        ("random", name, physics, None) for name in args.tasks for physics in args.physics
    ]
    rows = []
    for label, name, physics, policy in cases:
        per_env = gradient_norms(name, physics, args.num_envs, policy=policy)
        norms = per_env.mean(axis=1)
        # The mean can be one env's: the median env's own h=32 / h=1 says whether growth is typical.
        median_ratio = np.median(per_env[-1] / per_env[0])
        rows.append(
            [
                name,
                physics,
                label,
                *(f"{n:.3g}" for n in norms),
                f"{norms[-1] / norms[0]:.3g}",
                f"{median_ratio:.3g}",
                f"{norms[-1] / norms[-2]:.2g}",
                make_task(name, physics).substeps,
            ]
        )
        print(f"{name} {physics} {label}: done", flush=True)
    print(
        f"\nGradient norm of the h-step return w.r.t. the actions (mean over {args.num_envs} envs); {machine_description()}\n"  # noqa: E501
    )
    print(
        markdown_table(
            [
                "task",
                "physics",
                "policy",
                *(f"h={h}" for h in HORIZONS),
                "h=32 / h=1",
                "median env's h=32 / h=1",
                "h=32 / h=16",
                "substeps",
            ],
            rows,
        )
    )


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

"""Where do trained SHAC / D.Va policies sit on their tanh? Pre-tanh action statistics.

    python benchmarks/saturation.py runs/ant_dva_s0 [runs/… …] [--steps 300]

Replays each run's deterministic policy (``a = tanh(μ)``, pixels or state, whichever it trained
on) for ``--steps`` control steps over its training batch of envs and prints, per run: the median
and 90th percentile of ``|μ|``, the share of action components with ``|tanh μ| > 0.95`` (where
``tanh′ < 0.1``: the return's gradient barely reaches μ and the exploration noise ``σε`` barely
reaches the env), how much each action varies over time (the std over steps, averaged over
envs and joints: ≈ 0 for an open-loop posture, ≈ 1 for a bang-bang gait), the mean log σ and
the mean reward per step.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dva.analysis.bench import machine_description, markdown_table
from dva.runner.compiled import load_run


def saturation(run_dir: Path, steps: int) -> list:
    spec, agent, state = load_run(run_dir)
    actor_params, obs_stats = agent.policy(state)
    env = agent.env

    def step(env_state, _):
        observation = env.observe(env_state)
        mean = agent.pre_tanh_action(actor_params, agent.actor_input(observation, obs_stats), None)
        env_state = env.step(env_state, jnp.tanh(mean))
        return env_state, (mean, env_state.reward)

    @jax.jit
    def replay(key):
        return jax.lax.scan(step, env.reset(key), None, length=steps)[1]

    mean, reward = map(np.asarray, replay(jax.random.PRNGKey(1)))
    action = np.tanh(mean)
    log_std = np.mean(np.asarray(actor_params["params"]["log_std"]))
    return [
        f"{spec.task} {spec.algo} ({run_dir.name})",
        f"{np.median(np.abs(mean)):.2f}",
        f"{np.percentile(np.abs(mean), 90):.2f}",
        f"{np.mean(np.abs(action) > 0.95):.2f}",
        f"{action.std(axis=0).mean():.3f}",
        f"{log_std:.2f}",
        f"{reward.mean():.2f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    header = [
        "run",
        "median abs(μ)",
        "90th pct abs(μ)",
        "share abs(tanh μ) > 0.95",
        "std of tanh μ over time",
        "mean log σ",
        "reward / step",
    ]
    print(machine_description())
    print(markdown_table(header, [saturation(run, args.steps) for run in args.runs]))


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

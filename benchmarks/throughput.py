"""Per-task throughput: physics steps/s, forward and backward of a 32-step rollout, rendered
frames/s, peak memory. CPU by default; the same script uses a GPU when JAX sees one.

    python benchmarks/throughput.py [--tasks cartpole_swingup hopper] [--physics penalty mujoco]
                                    [--num-envs 64] [--no-render] [--csv throughput.csv]

The backward is the gradient of the rollout's summed reward with respect to its actions, less the
forward; "bwd / fwd" is their ratio. ``--no-render`` times the physics alone.

Each task runs in its own process so that the peak memory column is that task's alone.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HORIZON = 32


def measure(name: str, physics: str, num_envs: int, render: bool) -> dict[str, float]:
    import jax

    from dva.analysis.bench import peak_memory_mb, timed
    from dva.tasks import make_task

    task = make_task(name, physics)
    state = jax.jit(task.reset, static_argnums=1)(jax.random.PRNGKey(0), num_envs)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (HORIZON, num_envs, task.action_dim), minval=-1, maxval=1)

    def rollout_return(actions, state):
        def one(state, action):
            state = task.step(state, action)
            return state, state.reward

        state, rewards = jax.lax.scan(one, state, actions)
        return rewards.sum(), state

    forward = jax.jit(rollout_return)
    compile_fwd, fwd, _ = timed(forward, actions, state)
    backward = jax.jit(jax.grad(lambda a, s: rollout_return(a, s)[0]))
    compile_bwd, fwd_bwd, _ = timed(backward, actions, state)
    render_time = float("nan")
    if render:
        from dva.envs.rendering import PixelRenderer

        renderer = PixelRenderer(task, num_envs)
        _, render_time, _ = timed(jax.jit(renderer.__call__), state.data.qpos)
    return {
        "steps_per_s": HORIZON * num_envs / fwd,
        "rollout_s": fwd,
        "rollout_fwd_bwd_s": fwd_bwd,
        "frames_per_s": num_envs / render_time,
        "compile_s": compile_fwd + compile_bwd,
        "peak_mb": peak_memory_mb(),
    }


def main() -> None:
    from dva.tasks import BUILTIN_TASKS
    from dva.tasks.physics import PHYSICS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(BUILTIN_TASKS), choices=list(BUILTIN_TASKS))
    parser.add_argument("--physics", nargs="+", default=list(PHYSICS), choices=list(PHYSICS))
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--render", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--csv", type=Path, help="also write the rows (unrounded) to this CSV file")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: measure one task, print JSON
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.one, args.physics[0], args.num_envs, args.render)))
        return

    from dva.analysis.bench import machine_description, markdown_table, write_csv

    rows, records = [], []
    for name, physics in [(name, physics) for name in args.tasks for physics in args.physics]:
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--one",
                name,
                "--physics",
                physics,
                "--num-envs",
                str(args.num_envs),
                "--render" if args.render else "--no-render",
            ],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        backward = r["rollout_fwd_bwd_s"] - r["rollout_s"]
        records.append(
            dict(
                task=name,
                physics=physics,
                num_envs=args.num_envs,
                steps_per_s=r["steps_per_s"],
                forward_s=r["rollout_s"],
                backward_s=backward,
                backward_over_forward=backward / r["rollout_s"],
                frames_per_s=r["frames_per_s"],
                peak_mb=r["peak_mb"],
                compile_s=r["compile_s"],
            )
        )
        rows.append(
            [
                name,
                physics,
                f"{r['steps_per_s']:.0f}",
                f"{r['rollout_s']:.3f}",
                f"{backward:.3f}",
                f"{backward / r['rollout_s']:.1f}",
                f"{r['frames_per_s']:.0f}",
                f"{r['peak_mb']:.0f}",
                f"{r['compile_s']:.0f}",
            ]
        )
        print(f"{name} {physics}: done", flush=True)
    print(f"\n{args.num_envs} envs, {HORIZON}-step rollouts; {machine_description()}\n")
    print(
        markdown_table(
            [
                "task",
                "physics",
                "env steps/s (fwd)",
                f"{HORIZON}-step rollout fwd s",
                "bwd s",
                "bwd / fwd",
                "rendered frames/s (84²)",
                "peak MB",
                "compile s",
            ],
            rows,
        )
    )
    if args.csv:  # the device named only now: JAX in this process would take GPU memory from the tasks'
        device = machine_description()
        print(f"wrote {write_csv(args.csv, [dict(record, device=device) for record in records])}")


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

"""D.Va's paper-size iteration on whatever device JAX sees (meant for a GPU), part by part, beside
the paper's seconds per iteration on an RTX 4080.

    python benchmarks/gpu_check.py [--tasks humanoid hopper] [--csv gpu_check.csv] [--num-envs N]

For each task, `dva` under the paper preset (64 envs × 32 steps, 84² × 3 frames): the physics'
forward and backward, rendering, the actor's forward (its pixel encoder) and backward, the critic,
their sum and the jitted iteration (:func:`dva.analysis.breakdown.measure_iteration`), with the
compile-and-first-run time of the whole check. Where Warp (the ``pixels`` extra) cannot be
imported, a constant image stands in for the renderer, so the other parts are still timed and
rendering reads "not measured". Prints a markdown table and writes the rows to ``--csv``. Nothing in
the tests or CI runs it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

# Seconds per D.Va iteration in the paper's setting on an RTX 4080: the Humanoid's ≈ 1.5 s; the
# Hopper's 400 iterations in ≈ 4 minutes (the authors' web page) ≈ 0.6 s.
PAPER_ITERATION_SECONDS = {"humanoid": 1.5, "hopper": 0.6}
PARTS = {
    "physics forward": lambda t: t["rollout_forward"] - t["render"] - t["actor_forward"],
    "physics backward": lambda t: t["rollout_backward"],
    "rendering": lambda t: t["render"],
    "actor forward": lambda t: t["actor_forward"],
    "actor backward": lambda t: t["actor_backward"],
    "critic": lambda t: t["critic"],
}


class ConstantRenderer:
    """What stands in for Warp where it cannot be imported: a grey image per env (the renderer
    protocol: ``num_envs``, ``differentiable``, ``__call__(qpos)``)."""

    differentiable = False

    def __init__(self, num_envs: int, size: int) -> None:
        self.num_envs, self.size = num_envs, size

    def __call__(self, qpos):
        import jax.numpy as jnp

        return jnp.full((self.num_envs, self.size, self.size, 3), 128, jnp.uint8)


def warp_available() -> bool:
    try:
        import mujoco_warp  # noqa: F401
    except ImportError:
        return False
    return True


def measure(task: str, num_envs: int | None) -> tuple[dict[str, float], bool]:
    """The parts of ``task``'s paper-size D.Va iteration, and whether rendering was Warp's."""
    import jax

    from dva.algorithms import make_config
    from dva.algorithms.shac import SHAC
    from dva.analysis.breakdown import measure_iteration
    from dva.analysis.profile import iteration_breakdown
    from dva.envs.observations import PixelObservations
    from dva.tasks import make_task

    if warp_available():
        return measure_iteration(task, "dva", "paper", num_envs=num_envs)[1], True
    config = make_config(task, "dva", "paper", num_envs=num_envs)
    renderer = ConstantRenderer(config.num_envs, config.image_size)
    agent = SHAC(PixelObservations(make_task(task), config.num_envs, renderer, config.frame_stack), config)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    state, _ = jax.jit(agent.iteration)(state)
    return iteration_breakdown(agent, state), False


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["humanoid", "hopper"])
    parser.add_argument("--num-envs", type=int, help="override the paper's 64 envs (a quick try on a CPU)")
    parser.add_argument("--csv", type=Path, default=Path("gpu_check.csv"))
    args = parser.parse_args()

    from dva.analysis.bench import machine_description, markdown_table, write_csv

    began, rows, records = time.perf_counter(), [], []
    for task in args.tasks:
        times, rendered = measure(task, args.num_envs)
        parts = {part: max(seconds(times), 0.0) for part, seconds in PARTS.items()}
        paper = PAPER_ITERATION_SECONDS.get(task)
        for part, value in parts.items():
            shown = f"{value:.3f}" if rendered or part != "rendering" else "not measured"
            rows.append((task, part, shown, f"{value / times['iteration']:.0%}"))
            records.append(dict(task=task, part=part, seconds=value if rendered or part != "rendering" else ""))
        rows.append((task, "sum of the parts", f"{sum(parts.values()):.3f}", ""))
        rows.append((task, "iteration (jitted whole)", f"{times['iteration']:.3f}", "100%"))
        rows.append((task, "paper, RTX 4080", f"{paper:.1f}" if paper else "–", ""))
        records += [
            dict(task=task, part="sum of the parts", seconds=sum(parts.values())),
            dict(task=task, part="iteration", seconds=times["iteration"]),
            dict(task=task, part="paper iteration (RTX 4080)", seconds=paper or ""),
        ]
    print(machine_description() + f"; Warp rendering: {'yes' if warp_available() else 'no (constant images)'}")
    print(markdown_table(["task", "part", "seconds", "share of the iteration"], rows))
    device = machine_description()
    write_csv(args.csv, [dict(record, device=device) for record in records])
    print(f"wrote {args.csv}; the whole check took {time.perf_counter() - began:.0f} s with compilation")


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the compile caches (and, on a CPU, its convolution flags)
    main()

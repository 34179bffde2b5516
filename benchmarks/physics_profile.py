"""Where the physics' reverse pass goes: one control step of a task (its substeps, the mass matrix
factored once) for a batch of envs, forward alone and forward + reverse (the gradient of the
summed next state w.r.t. the state and the action), compiled and profiled kernel by kernel.

    python benchmarks/physics_profile.py [--task humanoid] [--envs 64] [--top 12]

Prints per pass: its time, how many kernels XLA runs (fusions, matrix products, library calls)
and how many of them scatter, then the kernels that take the most time with the JAX operation
each comes from (XLA's metadata: ``transpose(...)`` marks the reverse pass).
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import re
import tempfile
import time


def jax_origins(hlo: str) -> dict[str, str]:
    """Each HLO instruction's JAX operation (XLA's ``op_name`` metadata), by instruction name."""
    origin = {}
    for line in hlo.splitlines():
        match = re.match(r"\s*(?:ROOT )?%?([\w.-]+) = ", line)
        if match:
            op_name = re.search(r'op_name="([^"]+)"', line)
            origin[match[1]] = op_name[1] if op_name else ""
    return origin


def profile(compiled, args, repeats: int) -> tuple[collections.Counter, collections.Counter]:
    """Microseconds and launches per call of each kernel, from a perfetto trace of ``repeats`` calls."""
    import jax

    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            for _ in range(repeats):
                jax.block_until_ready(compiled(*args))
        path = sorted(glob.glob(f"{folder}/**/*.trace.json.gz", recursive=True))[-1]
        trace = json.load(gzip.open(path))
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    micros: collections.Counter = collections.Counter()
    launches: collections.Counter = collections.Counter()
    for event in events:
        if event.get("ph") == "X" and "dur" in event:
            micros[event["name"]] += event["dur"] / repeats
            launches[event["name"]] += 1 / repeats
    return micros, launches


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="humanoid")
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--top", type=int, default=12, help="kernels listed per pass")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()

    import dva

    dva.configure()
    import jax
    import jax.numpy as jnp

    from dva.analysis.bench import machine_description
    from dva.tasks import make_task

    task = make_task(args.task)
    env = task.reset(jax.random.PRNGKey(0), args.envs)
    action = jnp.zeros((args.envs, task.action_dim))
    step = jax.vmap(task.physics_step)

    def forward(qpos, qvel, action):
        data = step(env.data.replace(qpos=qpos, qvel=qvel), action)
        return jnp.sum(data.qpos) + jnp.sum(data.qvel)

    passes = {"forward": jax.jit(forward), "forward + reverse": jax.jit(jax.grad(forward, argnums=(0, 1, 2)))}
    inputs = (env.data.qpos, env.data.qvel, action)
    print(f"{args.task}, {args.envs} envs, one control step ({task.substeps} substeps); {machine_description()}")
    for label, fn in passes.items():
        compiled = fn.lower(*inputs).compile()
        origin = jax_origins(compiled.as_text())
        jax.block_until_ready(compiled(*inputs))
        began = time.perf_counter()
        for _ in range(args.repeats):
            jax.block_until_ready(compiled(*inputs))
        seconds = (time.perf_counter() - began) / args.repeats
        micros, launches = profile(compiled, inputs, args.repeats)
        # a loop's own event spans its body's kernels: count those
        kernel_names = [name for name in micros if name in origin and not name.startswith(("while", "call"))]
        launched = sum(launches[name] for name in kernel_names)
        scattering = sum(launches[name] for name in kernel_names if "scatter" in name)
        in_kernels = sum(micros[name] for name in kernel_names)
        print(
            f"\n{label}: {seconds * 1e3:.2f} ms; {launched:.0f} kernel launches ({scattering:.0f} scatters) "
            f"taking {in_kernels / 1e3:.2f} ms under the profiler"
        )
        for name in sorted(kernel_names, key=micros.__getitem__, reverse=True)[: args.top]:
            print(f"  {micros[name]:8.1f} µs  ×{launches[name]:<5.0f} {name:<30} {origin[name][:100]}")


if __name__ == "__main__":
    main()

"""`dva analyze cost --tasks TASK`, one variant at a time, printing each row (with the
compile and measure seconds) as soon as it is measured, so a run cut off by the device's time
limit still reports D.Va's row. Writes the usual cost.csv / cost.md / cost.png to argv[1];
argv[2] names the task (humanoid unless given)."""

import sys
import time
from pathlib import Path

import jax

from dva.algorithms import build_agent, make_config
from dva.analysis.bench import machine_description
from dva.analysis.cost import gradient_cost, write_cost_report

out = Path(sys.argv[1])
task = sys.argv[2] if len(sys.argv) > 2 else "humanoid"
rows = []
for algo, overrides, variant in (("dva", {"actor_backward_chunk": 1}, "dva, chunk 1"), ("shac-pixels", {}, "shac-pixels")):
    start = time.perf_counter()
    config = make_config(task, algo, "paper", num_envs=32, horizon=32, image_size=84, **overrides)
    agent = build_agent(task, algo, config)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    row = {"task": task, "algo": algo, "variant": variant,
           "actor_backward_chunk": overrides.get("actor_backward_chunk", ""), **gradient_cost(agent, state)}
    rows.append(row)
    print(f"{row}  ({time.perf_counter() - start:.0f} s with compiling)", flush=True)
print(jax.devices()[0].memory_stats())
files, markdown = write_cost_report(rows, out, f"one actor gradient, 32 envs × 32 steps, 84² pixels; {machine_description()}")
print(markdown)

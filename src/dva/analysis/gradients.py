"""Paper Fig 3: along a SHAC training run with state observations, how the full analytic policy
gradient (APG, through the observations) compares with the decoupled one (DPG) at the same
parameters, state and noise — cosine similarity and norms."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed
from tqdm import tqdm

from dva.algorithms import make_config
from dva.algorithms.shac import SHAC
from dva.analysis.bench import write_csv
from dva.analysis.profile import build_shac

FIELDS = ["iteration", "cosine", "apg_norm", "dpg_norm", "train_return"]


def compare_gradients(
    task_name: str, iterations: int, every: int, seed: int = 0, preset: str = "cpu", **overrides
) -> list[dict[str, float]]:
    """Train SHAC (state, full gradient) for ``iterations``; every ``every`` iterations record the
    cosine similarity and norms of APG and DPG at the current parameters."""
    config = make_config(task_name, "shac", preset, **overrides)
    full = build_shac(task_name, "shac", config)
    decoupled, task = SHAC(full.env, dataclasses.replace(config, gradient="decoupled")), full.task

    @jax.jit
    def both_gradients(state, key):
        noise = jax.random.normal(key, (config.horizon, config.num_envs, task.action_dim))
        apg = ravel_pytree(full.actor_gradient(state.actor_params, state, noise)[2])[0]
        dpg = ravel_pytree(decoupled.actor_gradient(state.actor_params, state, noise)[2])[0]
        apg_norm, dpg_norm = jnp.linalg.norm(apg), jnp.linalg.norm(dpg)
        return {"cosine": apg @ dpg / (apg_norm * dpg_norm + 1e-30), "apg_norm": apg_norm, "dpg_norm": dpg_norm}

    state = jax.jit(full.init)(jax.random.PRNGKey(seed))
    step = jax.jit(full.iteration, donate_argnums=0)
    rows, train_return = [], float("nan")
    for i in tqdm(range(iterations + 1), desc=f"APG vs DPG on {task_name}", dynamic_ncols=True):
        if i % every == 0:
            measured = jax.device_get(both_gradients(state, jax.random.PRNGKey(seed * 100_003 + i)))
            rows.append({"iteration": i, **{k: float(v) for k, v in measured.items()}, "train_return": train_return})
        if i < iterations:
            state, metrics = step(state)
            if metrics.finished_episodes > 0:
                train_return = float(metrics.finished_return_sum / metrics.finished_episodes)
    return rows


def write_gradient_report(rows: list[dict[str, float]], out_dir: Path, title: str) -> list[Path]:
    """``apg_vs_dpg.csv`` and ``apg_vs_dpg.png`` (cosine similarity; both norms, log scale)."""
    table = write_csv(out_dir / "apg_vs_dpg.csv", [{key: row[key] for key in FIELDS} for row in rows])
    iterations = [r["iteration"] for r in rows]
    fig = Figure(figsize=(6, 5.5), dpi=120)
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(iterations, [r["cosine"] for r in rows], marker=".")
    top.axhline(0.0, color="grey", lw=0.8)
    top.set_ylabel("cosine(APG, DPG)")
    top.set_ylim(-1.05, 1.05)
    top.set_title(title, fontsize=9)
    bottom.semilogy(iterations, [r["apg_norm"] for r in rows], label="APG (full, SHAC)")
    bottom.semilogy(iterations, [r["dpg_norm"] for r in rows], label="DPG (decoupled)")
    bottom.set_xlabel("SHAC iteration")
    bottom.set_ylabel("gradient norm")
    bottom.legend(fontsize=8)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    figure = out_dir / "apg_vs_dpg.png"
    fig.savefig(figure)
    return [table, figure]

"""Paper Fig 5: where D.Va's time goes per 1M environment steps — simulation (forward and
backward), rendering, actor forward/backward, critic fitting."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
from matplotlib.figure import Figure  # no pyplot: no global state, no display needed

from dva.algorithms import make_config
from dva.algorithms.shac import SHACConfig
from dva.analysis.bench import markdown_table, write_csv
from dva.analysis.profile import build_shac, iteration_breakdown, per_million_steps


def measure_iteration(
    task: str, algo: str = "dva", preset: str = "cpu", seed: int = 0, **overrides
) -> tuple[SHACConfig, dict[str, float]]:
    """The configuration and :func:`iteration_breakdown` of ``algo`` on ``task``, timed after one
    iteration (so the state is a realistic one, not the reset)."""
    config = make_config(task, algo, preset, **overrides)
    agent = build_shac(task, algo, config)
    state = jax.jit(agent.init)(jax.random.PRNGKey(seed))
    state, _ = jax.jit(agent.iteration)(state)
    return config, iteration_breakdown(agent, state)


def write_breakdown_report(
    config: SHACConfig, times: dict[str, float], out_dir: Path, title: str
) -> tuple[list[Path], str]:
    """``breakdown.csv``, ``breakdown.md`` and ``breakdown.png`` (one stacked bar, seconds per 1M steps)."""
    per_million = per_million_steps(times, config.num_envs, config.horizon)
    total = sum(per_million.values())
    rows: list[dict[str, Any]] = [
        {"part": part, "seconds_per_million_steps": seconds, "share": seconds / total}
        for part, seconds in per_million.items()
    ]
    table = write_csv(out_dir / "breakdown.csv", rows)
    markdown = markdown_table(
        ["part", "s per 1M steps", "share"],
        [(r["part"], f"{r['seconds_per_million_steps']:.0f}", f"{r['share']:.0%}") for r in rows]
        + [("total", f"{total:.0f}", "100%")],
    )
    (out_dir / "breakdown.md").write_text(f"{title}\n\n{markdown}\n")
    fig = Figure(figsize=(8, 2.6), dpi=120)
    ax = fig.subplots()
    left = 0.0
    for row in rows:
        ax.barh([0], [row["seconds_per_million_steps"]], left=left, label=f"{row['part']} ({row['share']:.0%})")
        left += row["seconds_per_million_steps"]
    ax.set_yticks([])
    ax.set_xlabel("seconds per 1M environment steps")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.35))
    fig.tight_layout()
    figure = out_dir / "breakdown.png"
    fig.savefig(figure, bbox_inches="tight")
    return [table, out_dir / "breakdown.md", figure], markdown

"""Where a training iteration's time goes, and what the pixel encoder costs at best.

:func:`iteration_breakdown` times each part of :meth:`SHAC.iteration` as its own jitted function
(steady state, compile excluded). :func:`encoder_flops` counts the DrQ-v2 encoder's arithmetic so
its measured time can be compared with the machine's matrix-multiply rate (the compute bound).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dva.algorithms import build_agent
from dva.algorithms.shac import SHAC, SHACConfig, TrainState
from dva.analysis.bench import timed


def build_shac(task: str, algo: str, config: SHACConfig) -> SHAC:
    """:func:`~dva.algorithms.build_agent` for the SHAC family (dva, shac, shac-pixels, dpg),
    whose trainer these analyses take apart."""
    agent = build_agent(task, algo, config)
    if not isinstance(agent, SHAC):
        raise TypeError(f"{algo} is not of the SHAC family; these analyses need its trainer")
    return agent


def iteration_breakdown(agent: SHAC, state: TrainState) -> dict[str, float]:
    """Seconds per part of one iteration at ``state``.

    ``rollout_forward``: physics, rendering, frame stack, actor forward, critic bootstrap (one
    compile that also returns the observations and the critic's trajectory for the parts below).
    ``actor_forward``: the actor alone on the rollout's h × N observations, one batch per step.
    ``rollout_backward``: reverse pass of the rollout (for D.Va: the physics only, giving the
    open-loop action gradient), i.e. value-and-gradient minus the forward.
    ``actor_backward``: D.Va's :meth:`~dva.algorithms.shac.SHAC.actor_backward` over the h × N
    observations as configured (chunks with their forward recomputed, or the rollout's kept
    backward passes; 0 for 'full').
    ``critic``: TD-λ targets and all critic minibatch steps. ``render``: rendering alone, h
    batches of N frames (part of the rollout forward); ``render_with_actor``: see
    :func:`render_beside_actor`. ``iteration``: the whole jitted step.
    """
    cfg = agent.config
    noise = jax.random.normal(jax.random.PRNGKey(1), (cfg.horizon, cfg.num_envs, agent.task.action_dim))
    params = state.actor_params
    times: dict[str, float] = {}

    def forward(p, s, n):  # the loss, plus what the actor and critic timings below take as input
        loss, aux = agent.rollout(p, s, n)
        return loss, aux.taken["observations"], aux.trajectory

    _, times["rollout_forward"], (_, observations, trajectory) = timed(jax.jit(forward), params, state, noise)
    actor_forward = jax.jit(lambda p, obs: jax.lax.map(lambda o: agent.actor.apply(p, o)[0].sum(), obs))
    times["actor_forward"] = timed(actor_forward, params, observations)[1]
    if cfg.gradient == "full":
        grad = jax.jit(lambda p, s, n: jax.value_and_grad(agent.rollout, has_aux=True)(p, s, n)[1])
        times["rollout_backward"] = timed(grad, params, state, noise)[1] - times["rollout_forward"]
        times["actor_backward"] = 0.0
    else:
        offsets = jnp.zeros_like(noise)
        action_grad = jax.jit(
            lambda p, s, n, w: jax.value_and_grad(lambda w: agent.rollout(p, s, n, w), has_aux=True)(w)
        )
        _, physics_time, ((_, aux), grad) = timed(action_grad, params, state, noise, offsets)
        times["rollout_backward"] = physics_time - times["rollout_forward"]
        times["actor_backward"] = timed(jax.jit(agent.actor_backward), params, aux.taken, noise, grad)[1]
    critic = jax.jit(agent.critic_update)
    times["critic"] = timed(critic, state, trajectory, jax.random.PRNGKey(2))[1]
    if agent.env.renderer is not None:
        times.update(render_beside_actor(agent, params, state.env.data.qpos, observations))
    else:
        times["render"] = 0.0
    iteration = jax.jit(agent.iteration)
    times["iteration"] = timed(iteration, state)[1]
    return times


def render_beside_actor(agent: SHAC, params, qpos: jax.Array, observations) -> dict[str, float]:
    """``render``: h batches of N frames; ``render_with_actor``: the same h batches each in one
    loop body with an actor forward on that step's N observations, the two independent of each
    other — what rendering the next frame while the actor runs could at best achieve (compare with
    ``render + actor_forward``). Each step's pose is nudged by its index so that XLA cannot hoist
    the render out of the loop."""
    steps = jnp.arange(agent.config.horizon)

    def frame(q, i):
        return agent.env.renderer(q + 1e-6 * i).sum(dtype=jnp.int32)

    render = jax.jit(lambda q: jax.lax.map(lambda i: frame(q, i), steps))
    together = jax.jit(
        lambda p, q, obs: jax.lax.map(lambda x: (frame(q, x[0]), agent.actor.apply(p, x[1])[0].sum()), (steps, obs))
    )
    return {"render": timed(render, qpos)[1], "render_with_actor": timed(together, params, qpos, observations)[1]}


def encoder_flops(image_size: int, channels_in: int, channels: int = 32, trunk: int = 64) -> dict[str, float]:
    """Multiply-adds × 2 of the DrQ-v2 encoder + trunk projection for one image.

    ``forward``; ``backward`` = weight gradients of every layer + input gradients of every layer
    but the first (the pixels need none), i.e. about twice the forward.
    """
    size, c_in, conv = image_size, channels_in, []
    for stride in (2, 1, 1, 1):
        size = (size - 3) // stride + 1
        conv.append(2 * size * size * channels * 9 * c_in)
        c_in = channels
    projection = 2 * size * size * channels * trunk
    forward = sum(conv) + projection
    backward = sum(conv) + projection + sum(conv[1:]) + projection
    return {"forward": float(forward), "backward": float(backward)}


def matmul_flops_per_s(size: int = 2048) -> float:
    """The float32 matrix-multiply rate XLA's own dot reaches on this device."""
    a = jax.random.normal(jax.random.PRNGKey(0), (size, size))
    _, seconds, _ = timed(jax.jit(lambda a: a @ a), a)
    return 2.0 * size**3 / seconds


def blas_flops_per_s(size: int = 2048, repeats: int = 5) -> float:
    """The float32 matrix-multiply rate NumPy's BLAS reaches on the cores this process may use
    (best of ``repeats``). On the CPU the compute bound takes the better of this and
    :func:`matmul_flops_per_s`: XLA's dot can be far from what the core can do (41 against 96
    GFLOP/s on one Zen 3 core)."""
    import time

    import numpy as np

    a = np.random.default_rng(0).standard_normal((size, size), dtype=np.float32)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ a
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best


def matmul_rates(repeats: int = 5) -> tuple[float, float]:
    """(XLA's dot, NumPy's BLAS) float32 matmul rates, each the best of ``repeats``; BLAS is 0
    off the CPU. The compute bound divides by the larger."""
    xla = max(matmul_flops_per_s() for _ in range(repeats))
    return xla, blas_flops_per_s(repeats=repeats) if jax.default_backend() == "cpu" else 0.0


def per_million_steps(times: dict[str, float], num_envs: int, horizon: int) -> dict[str, float]:
    """Paper Fig 5: seconds per 1M env steps in each part of an iteration, from
    :func:`iteration_breakdown`'s ``times``. The parts were timed separately; ``other`` is what
    the whole iteration took beyond their sum (0 when fusion made it faster than the parts)."""
    parts = {
        "simulation forward": max(times["rollout_forward"] - times["render"] - times["actor_forward"], 0.0),
        "simulation backward": times["rollout_backward"],
        "rendering": times["render"],
        "actor forward": times["actor_forward"],
        "actor backward": times["actor_backward"],
        "critic fitting": times["critic"],
    }
    parts["other"] = max(times["iteration"] - sum(parts.values()), 0.0)
    iterations_per_million = 1e6 / (num_envs * horizon)
    return {part: seconds * iterations_per_million for part, seconds in parts.items()}

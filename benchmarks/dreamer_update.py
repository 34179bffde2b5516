"""Where one DreamerV3 update's time goes, against the machine's compute bound.

For each piece of one update (the world model's forward + backward and, within it, the encoder,
the decoder and the RSSM along the sequences; imagination; the actor's forward + backward through
it; the whole update) it prints the best time of ``--repeats`` runs, XLA's count of its floating
point operations, the rate that makes, and the time those operations would take at the peak rate
of a large matmul on this machine (the compute bound). Also: the one-hot sampler the RSSM draws
with against ``jax.random.categorical``, and, with ``--convolutions xla``, the same table with
XLA's strided and input-dilated convolutions in place of the 2×2 block ones (the default). CPU by
default; the same script uses a GPU when JAX sees one.

    python benchmarks/dreamer_update.py [--algo dreamerv3 dreamerv3-state] [--task cartpole_balance]
                                        [--preset cpu] [--repeats 5] [--convolutions blocks|xla]
"""

from __future__ import annotations

import argparse
import contextlib
import functools


def xla_strided_conv4(x, kernel):
    import jax

    return jax.lax.conv_general_dilated(x, kernel, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))


def xla_strided_conv4_transpose(x, kernel):
    import jax

    return jax.lax.conv_transpose(x, kernel, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))


@contextlib.contextmanager
def convolutions(form: str):
    """Trace the DreamerV3 conv stacks with ``form``'s convolutions ("blocks": ours, "xla")."""
    import dva.networks.dreamer as networks

    ours = networks.strided_conv4, networks.strided_conv4_transpose
    if form == "xla":
        networks.strided_conv4, networks.strided_conv4_transpose = xla_strided_conv4, xla_strided_conv4_transpose
    try:
        yield
    finally:
        networks.strided_conv4, networks.strided_conv4_transpose = ours


@contextlib.contextmanager
def unrolled_scans():
    """Trace every ``jax.lax.scan`` fully unrolled. XLA's cost analysis counts a loop's body once,
    whatever its trip count, so only an unrolled trace counts every step's operations."""
    import jax

    scan = jax.lax.scan
    jax.lax.scan = functools.partial(scan, unroll=True)
    try:
        yield
    finally:
        jax.lax.scan = scan


def profile(fn, *args, repeats: int) -> tuple[float, float]:
    """(best seconds, GFLOP) of ``jax.jit(fn)(*args)``: timed as it runs (scans as loops), its
    operations counted by XLA's cost analysis of the same function with its scans unrolled."""
    import jax

    from dva.analysis.bench import timed

    with unrolled_scans():
        cost = jax.jit(fn).lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return timed(jax.jit(fn), *args, repeats=repeats)[1], float(cost.get("flops", 0.0)) / 1e9


def peak_gflops(repeats: int) -> float:
    """The best float32 matmul rate this process reaches (XLA's dot or NumPy's BLAS)."""
    from dva.analysis.profile import matmul_rates

    return max(matmul_rates(repeats)) / 1e9


def update_pieces(algo: str, task: str, preset: str):
    """(name, function, arguments) of each piece of one update of ``algo``'s CPU-preset agent."""
    import jax
    import jax.numpy as jnp

    from dva.algorithms import build_agent, make_config
    from dva.runner.compiled import initial_state

    config = make_config(task, algo, preset)
    agent = build_agent(task, algo, config)
    state = jax.jit(functools.partial(initial_state, agent))(jax.random.PRNGKey(0))
    key, params = jax.random.PRNGKey(1), state.params
    model, actor, critic = params["model"], params["actor"], params["critic"]
    steps = jax.jit(agent.replay.sample_sequences)(state.replay, key)
    deter, stoch, *_ = jax.jit(agent.observe_sequences)(model, steps, key)
    starts = deter.reshape(-1, deter.shape[-1]), stoch.reshape((-1,) + stoch.shape[2:])
    feats = jnp.concatenate([deter, stoch.reshape(stoch.shape[:2] + (-1,))], -1)
    squares = lambda tree: sum(jnp.sum(x**2) for x in jax.tree.leaves(tree))
    actor_loss = lambda a: agent.actor_loss(a, model, critic, state.return_scale, *starts, key)[0]
    return [
        ("world model, forward + backward", jax.grad(lambda m: agent.world_model_loss(m, steps, key)[0]), (model,)),
        ("  encoder", jax.grad(lambda m: squares(agent.encode(m, steps.frame))), (model,)),
        ("  decoder", jax.grad(lambda d: squares(agent.decoder.apply(d, feats))), (model["decoder"],)),
        ("  RSSM along the sequences", jax.grad(lambda m: squares(agent.observe_sequences(m, steps, key))), (model,)),
        ("imagination, forward", lambda a: agent.imagine(model, a, *starts, key), (actor,)),
        ("actor, forward + backward", jax.grad(actor_loss), (actor,)),
        ("one update", agent.update, (state, key)),
    ]


def sampler_times(repeats: int) -> tuple[float, float]:
    """Seconds of a one-hot sample of (256, 32, 32) logits with straight-through gradient: the
    inverse-CDF sampler against one built on ``jax.random.categorical``."""
    import jax

    from dva.algorithms.dreamerv3 import sample_onehot

    def categorical(logits, key):
        probs = jax.nn.softmax(logits, -1)
        sample = jax.nn.one_hot(jax.random.categorical(key, logits), logits.shape[-1])
        return sample + probs - jax.lax.stop_gradient(probs)

    logits, key = jax.random.normal(jax.random.PRNGKey(0), (256, 32, 32)), jax.random.PRNGKey(1)
    return tuple(profile(fn, logits, key, repeats=repeats)[0] for fn in (sample_onehot, categorical))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", nargs="+", default=["dreamerv3", "dreamerv3-state"])
    parser.add_argument("--task", default="cartpole_balance")
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs after the compile; the best is kept")
    parser.add_argument("--convolutions", default="blocks", choices=["blocks", "xla"])
    args = parser.parse_args()

    from dva.analysis.bench import machine_description, markdown_table

    print(machine_description())
    peak = peak_gflops(args.repeats)
    print(f"compute bound: a 2048² matmul runs at {peak:.0f} GFLOP/s")
    ours, categorical = sampler_times(args.repeats)
    print(
        f"one-hot sample of (256, 32, 32): inverse CDF {1e3 * ours:.2f} ms, "
        f"jax.random.categorical {1e3 * categorical:.2f} ms ({categorical / ours:.1f}×)"
    )
    for algo in args.algo:
        with convolutions(args.convolutions):
            rows = []
            for name, fn, fn_args in update_pieces(algo, args.task, args.preset):
                seconds, gflop = profile(fn, *fn_args, repeats=args.repeats)
                bound = gflop / peak
                rows.append(
                    (
                        name,
                        f"{1e3 * seconds:.1f}",
                        f"{gflop:.2f}",
                        f"{gflop / seconds:.1f}",
                        f"{1e3 * bound:.1f}",
                        f"{seconds / bound:.1f}×",
                    )
                )
        print(f"\n{algo} on {args.task}, preset {args.preset}, {args.convolutions} convolutions")
        header = ["piece", "ms", "GFLOP", "GFLOP/s", "ms at the bound", "time / bound"]
        print(markdown_table(header, rows))


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

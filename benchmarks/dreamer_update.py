"""Seconds per DreamerV3 update (world model, imagination, actor and critic) and per pass of its
conv encoder + decoder alone, with the 4×4 stride-2 convolutions as 2×2 convolutions over 2×2
pixel blocks (ours, the default) against XLA's strided and input-dilated convolutions (what Flax's
``nn.Conv`` / ``nn.ConvTranspose`` run), and the ratio. CPU by default; the same script uses a
GPU when JAX sees one.

    python benchmarks/dreamer_update.py [--task cartpole_balance] [--preset cpu] [--repeats 5]
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


def measure(task: str, preset: str, form: str, repeats: int) -> dict[str, float]:
    import jax
    import jax.numpy as jnp

    from dva.algorithms import build_agent, make_config
    from dva.analysis.bench import timed
    from dva.networks import scale_pixels
    from dva.training import initial_state

    config = make_config(task, "dreamerv3", preset)
    agent = build_agent(task, "dreamerv3", config)
    with convolutions(form):
        state = jax.jit(functools.partial(initial_state, agent))(jax.random.PRNGKey(0))
        model = state.params["model"]
        frames = jax.random.randint(
            jax.random.PRNGKey(1),
            (config.batch_size * config.batch_length, config.image_size, config.image_size, 3),
            0,
            256,
        ).astype(jnp.uint8)
        features = jax.random.normal(jax.random.PRNGKey(2), (len(frames), config.deter + config.stoch * config.classes))

        def reconstruction_loss(encoder, decoder):  # the encoder and decoder passes one update makes
            embedding = agent.encoder.apply(encoder, frames)
            reconstruction = agent.decoder.apply(decoder, features)
            return jnp.sum(embedding**2) + jnp.sum((reconstruction - scale_pixels(frames)) ** 2)

        conv_grad = jax.jit(jax.grad(reconstruction_loss, argnums=(0, 1)))
        compile_conv, conv_s, _ = timed(conv_grad, model["encoder"], model["decoder"], repeats=repeats)
        update = jax.jit(agent.update)
        compile_update, update_s, _ = timed(update, state, jax.random.PRNGKey(3), repeats=repeats)
    return {"update_s": update_s, "conv_s": conv_s, "compile_s": compile_conv + compile_update}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cartpole_balance")
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs after the compile; the best is kept")
    args = parser.parse_args()

    from dva.algorithms import make_config
    from dva.analysis.bench import machine_description, markdown_table

    config = make_config(args.task, "dreamerv3", args.preset)
    print(
        f"DreamerV3 on {args.task}, preset {args.preset}: {config.batch_size} × {config.batch_length} replayed "
        f"steps of {config.image_size}² per update, CNN depth {config.cnn_depth}, deter {config.deter}"
    )
    print(machine_description())
    times = {form: measure(args.task, args.preset, form, args.repeats) for form in ("xla", "blocks")}
    rows = [
        (
            label,
            f"{times['xla'][key]:.3f}",
            f"{times['blocks'][key]:.3f}",
            f"{times['xla'][key] / times['blocks'][key]:.2f}×",
        )
        for key, label in (
            ("update_s", "one update (s)"),
            ("conv_s", "encoder + decoder, forward + backward (s)"),
            ("compile_s", "compile + first run (s)"),
        )
    ]
    print(
        markdown_table(
            ["best of the timed runs", "XLA convolutions", "2×2 block convolutions (default)", "speed-up"], rows
        )
    )


if __name__ == "__main__":
    main()

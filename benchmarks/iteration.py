"""Seconds per training iteration and where they go (rollout forward / backward / actor backward /
critic / rendering), plus the pixel encoder's analytic compute bound.

    python benchmarks/iteration.py [--task cartpole_swingup] [--algo dva] [--preset cpu]
                                   [--num-envs N] [--image-size S] [--chunk C]
                                   [--csv FILE --label LABEL]

Prints a markdown table; ``--csv`` also appends the parts' seconds as one row of FILE (several
tasks, algorithms or code versions measured into one table). The encoder bound is its arithmetic
(forward + backward over all h × N frames) divided by the float32 matmul rate this machine
reaches. For pixel actors it also times the reference measurement — the encoder + trunk's forward
and parameter gradient over 512 images of 84² × 9 — next to PyTorch's 1.55 s on a comparable
2-core CPU, and states the actor backward's rate per FLOP against PyTorch's on that measurement.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

# The reference measurement: the DrQ-v2 encoder + 64-wide trunk, forward + backward w.r.t. its parameters, on
# (images, size, channels) uint8 pixels, PyTorch 2.13 on a comparable 2-core CPU: seconds.
PYTORCH_ENCODER_GRADIENT = {"images": 512, "image_size": 84, "channels_in": 9, "seconds": 1.55}


def encoder_gradient_seconds(images: int, image_size: int, channels_in: int, trunk: int = 64) -> float:
    """Best steady-state seconds of the DrQ-v2 encoder + trunk projection's forward and its
    gradient w.r.t. the parameters over ``images`` random uint8 images, jitted at the top level
    (the reference measurement)."""
    import jax
    import jax.numpy as jnp

    from dva.analysis.bench import timed
    from dva.networks import PixelEncoder

    def loss(params, pixels):
        encoder, projection = params
        return jnp.sum(jnp.tanh(PixelEncoder().apply(encoder, pixels) @ projection))

    key = jax.random.PRNGKey(0)
    pixels = jax.random.randint(key, (images, image_size, image_size, channels_in), 0, 256).astype(jnp.uint8)
    encoder = PixelEncoder().init(key, pixels[:1])
    projection = 0.01 * jax.random.normal(key, (PixelEncoder().apply(encoder, pixels[:1]).shape[-1], trunk))
    return timed(jax.jit(jax.grad(loss)), (encoder, projection), pixels)[1]


def append_row(path: Path, row: dict) -> None:
    """``row`` appended to the CSV file ``path`` (its header written when the file is new)."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cartpole_swingup")
    parser.add_argument("--algo", default="dva")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--num-envs", type=int)
    parser.add_argument("--image-size", type=int)
    parser.add_argument("--chunk", type=int, default=1, help="D.Va's actor_backward_chunk (0: the kept passes)")
    parser.add_argument("--csv", type=Path, help="append this measurement as one row to this CSV file")
    parser.add_argument("--label", default="", help="the row's label in --csv (e.g. the code version)")
    args = parser.parse_args()

    from dva.analysis.bench import machine_description, markdown_table
    from dva.analysis.breakdown import measure_iteration
    from dva.analysis.profile import encoder_flops, matmul_flops_per_s

    config, times = measure_iteration(
        args.task,
        args.algo,
        args.preset,
        num_envs=args.num_envs,
        image_size=args.image_size,
        actor_backward_chunk=args.chunk,
    )
    print(
        f"{args.algo} on {args.task}, preset {args.preset}: {config.num_envs} envs × {config.horizon} steps"
        + (f", {config.image_size}² × {config.frame_stack} frames" if config.observation == "pixels" else "")
    )
    print(machine_description())
    rows = [
        (part, f"{seconds:.3f}", f"{seconds / times['iteration']:.0%}")
        for part, seconds in times.items()
        if part != "render_with_actor"
    ]
    print(markdown_table(["part", "seconds", "share of iteration"], rows))
    if args.csv:
        append_row(
            args.csv,
            dict(
                label=args.label,
                task=args.task,
                algo=args.algo,
                num_envs=config.num_envs,
                horizon=config.horizon,
                **{f"{part}_s": seconds for part, seconds in times.items() if part != "render_with_actor"},
                rollout_backward_share=times["rollout_backward"] / times["iteration"],
                device=machine_description(),
            ),
        )
    if "render_with_actor" in times:
        apart = times["render"] + times["actor_forward"]
        print(
            f"\nrendering and the actor forward side by side in one loop (no dependence): "
            f"{times['render_with_actor']:.3f} s vs {apart:.3f} s one after the other "
            f"({1 - times['render_with_actor'] / apart:+.0%}): the most that rendering the next frame "
            f"while the actor runs could save per iteration"
        )
    if config.observation == "pixels":
        images = config.num_envs * config.horizon
        flops = encoder_flops(config.image_size, 3 * config.frame_stack, trunk=config.trunk)
        rate = matmul_flops_per_s()
        # Chunks recompute the encoder's forward; the kept backward passes (chunk 0) do not.
        recomputed = config.actor_backward_chunk > 0
        bound = images * (flops["forward"] * recomputed + flops["backward"]) / rate
        print(
            f"\nencoder: {flops['forward'] / 1e6:.1f} MFLOP forward + {flops['backward'] / 1e6:.1f} MFLOP backward "
            f"per image; matmul rate {rate / 1e9:.0f} GFLOP/s → bound {bound:.3f} s for {images} images "
            f"({'forward + backward: chunks of ' + str(config.actor_backward_chunk) if recomputed else 'backward: kept passes'}); "  # noqa: E501
            f"measured actor backward {times['actor_backward']:.3f} s = {times['actor_backward'] / bound:.1f}× the bound"  # noqa: E501
        )
        reference = PYTORCH_ENCODER_GRADIENT
        ours = encoder_gradient_seconds(reference["images"], reference["image_size"], reference["channels_in"])
        reference_flops = encoder_flops(reference["image_size"], reference["channels_in"])
        reference_rate = reference["images"] * sum(reference_flops.values()) / reference["seconds"]
        actor_rate = bound * rate / times["actor_backward"]
        print(
            f"reference measurement (encoder + trunk, forward + parameter gradient, {reference['images']} × "
            f"{reference['image_size']}² × {reference['channels_in']}): {ours:.3f} s here vs PyTorch's "
            f"{reference['seconds']} s = {ours / reference['seconds']:.2f}×; actor backward "
            f"{actor_rate / 1e9:.0f} GFLOP/s vs PyTorch's {reference_rate / 1e9:.0f} on that measurement "
            f"= {reference_rate / actor_rate:.2f}× its time per FLOP"
        )


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

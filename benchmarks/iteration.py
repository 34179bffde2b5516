"""Seconds per training iteration and where they go (rollout forward / backward / actor backward /
critic / rendering), plus the pixel encoder's analytic compute bound.

    python benchmarks/iteration.py [--task cartpole_swingup] [--algo dva] [--preset cpu]
                                   [--num-envs N] [--image-size S] [--chunk C]
                                   [--pytorch PYTHON] [--csv FILE --label LABEL]

Prints a markdown table; ``--csv`` also appends the parts' seconds as one row of FILE (several
tasks, algorithms or code versions measured into one table). The encoder bound is its arithmetic
(forward + backward over all h × N frames) divided by the float32 matmul rate this process
reaches on the cores it may use, on the CPU the better of XLA's dot and NumPy's BLAS (``taskset``
decides: pin it to one core for a one-core bound).
For pixel actors it also times the reference measurement — the encoder + trunk's forward and
parameter gradient over 512 images of 84² × 9 — and, given ``--pytorch`` (an interpreter with
PyTorch), the same work in PyTorch on the same cores (``benchmarks/pytorch_encoder.py``), for the
reference and for this iteration's images.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
from pathlib import Path

# The reference measurement: the DrQ-v2 encoder + 64-wide trunk, forward + backward w.r.t. its
# parameters, on (images, size, channels) uint8 pixels.
REFERENCE = {"images": 512, "image_size": 84, "channels_in": 9}


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


def usable_cores() -> int:
    """The cores this process may run on (what ``taskset`` gave it): the bound's and PyTorch's."""
    return len(os.sched_getaffinity(0))


def pytorch_gradient_seconds(python: str, images: int, image_size: int, channels_in: int) -> float:
    """:func:`encoder_gradient_seconds`'s work in PyTorch (``benchmarks/pytorch_encoder.py`` run by
    the interpreter ``python``), on as many threads as this process has cores."""
    script = Path(__file__).with_name("pytorch_encoder.py")
    arguments = ["--images", images, "--image-size", image_size, "--channels", channels_in]
    arguments += ["--threads", usable_cores()]
    printed = subprocess.run(
        [python, str(script), *map(str, arguments)], check=True, capture_output=True, text=True
    ).stdout
    return float(re.search(r": ([0-9.]+) s \(best of 5\)", printed).group(1))


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
    parser.add_argument("--pytorch", help="an interpreter with PyTorch: also time the encoder's gradient there")
    parser.add_argument("--csv", type=Path, help="append this measurement as one row to this CSV file")
    parser.add_argument("--label", default="", help="the row's label in --csv (e.g. the code version)")
    args = parser.parse_args()

    from dva.analysis.bench import machine_description, markdown_table
    from dva.analysis.breakdown import measure_iteration

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
    if "render_with_actor" in times:
        apart = times["render"] + times["actor_forward"]
        print(
            f"\nrendering and the actor forward side by side in one loop (no dependence): "
            f"{times['render_with_actor']:.3f} s vs {apart:.3f} s one after the other "
            f"({1 - times['render_with_actor'] / apart:+.0%}): the most that rendering the next frame "
            f"while the actor runs could save per iteration"
        )
    encoder = encoder_report(config, times, args.pytorch) if config.observation == "pixels" else {}
    if args.csv:
        append_row(
            args.csv,
            dict(
                label=args.label,
                task=args.task,
                algo=args.algo,
                num_envs=config.num_envs,
                horizon=config.horizon,
                image_size=config.image_size if config.observation == "pixels" else "",
                **{f"{part}_s": seconds for part, seconds in times.items()},
                rollout_backward_share=times["rollout_backward"] / times["iteration"],
                **encoder,
                cores=usable_cores(),
                device=machine_description(),
            ),
        )


def encoder_report(config, times: dict[str, float], pytorch: str | None) -> dict[str, float | str]:
    """Prints the actor backward against the encoder's matmul bound, and the reference measurement
    (with PyTorch's where ``pytorch`` names an interpreter); returns those numbers."""
    from dva.analysis.profile import encoder_flops, matmul_rates

    images = config.num_envs * config.horizon
    channels = 3 * config.frame_stack
    flops = encoder_flops(config.image_size, channels, trunk=config.trunk)
    xla_rate, blas_rate = matmul_rates()
    rate = max(xla_rate, blas_rate)
    # Chunks recompute the encoder's forward; the kept backward passes (chunk 0) do not.
    recomputed = config.actor_backward_chunk > 0
    bound = images * (flops["forward"] * recomputed + flops["backward"]) / rate
    passes = f"forward + backward: chunks of {config.actor_backward_chunk}" if recomputed else "backward: kept passes"
    render_ms_per_frame = 1e3 * times["render"] / images
    print(
        f"\nencoder: {flops['forward'] / 1e6:.1f} MFLOP forward + {flops['backward'] / 1e6:.1f} MFLOP backward "
        f"per image; matmul rate {rate / 1e9:.0f} GFLOP/s (XLA {xla_rate / 1e9:.0f}, BLAS {blas_rate / 1e9:.0f}) "
        f"on {usable_cores()} core(s) → bound {bound:.3f} s for "
        f"{images} images ({passes}); measured actor backward {times['actor_backward']:.3f} s = "
        f"{times['actor_backward'] / bound:.2f}× the bound; rendering {render_ms_per_frame:.2f} ms per frame"
    )
    ours = encoder_gradient_seconds(**REFERENCE)
    at_size = encoder_gradient_seconds(images, config.image_size, channels)
    numbers: dict[str, float | str] = {
        "matmul_gflops": xla_rate / 1e9,
        "blas_gflops": blas_rate / 1e9,
        "bound_s": bound,
        "bound_ratio": times["actor_backward"] / bound,
        "render_ms_per_frame": render_ms_per_frame,
        "reference_s": ours,
        "encoder_gradient_s": at_size,
        "pytorch_reference_s": "",
        "pytorch_encoder_gradient_s": "",
    }
    shape = f"{REFERENCE['images']} × {REFERENCE['image_size']}² × {REFERENCE['channels_in']}"
    line = f"encoder + trunk, forward + parameter gradient: {shape} {ours:.3f} s; {images} × {config.image_size}² × {channels} {at_size:.3f} s"  # noqa: E501
    if pytorch:
        theirs = pytorch_gradient_seconds(pytorch, **REFERENCE)
        theirs_at_size = pytorch_gradient_seconds(pytorch, images, config.image_size, channels)
        numbers.update(pytorch_reference_s=theirs, pytorch_encoder_gradient_s=theirs_at_size)
        line += f" (PyTorch on the same cores: {theirs:.3f} s and {theirs_at_size:.3f} s)"
    print(line)
    return numbers


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

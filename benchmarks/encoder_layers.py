"""Where the pixel encoder's time goes, layer by layer: the forward, kernel-gradient and
input-gradient convolutions of the DrQ-v2 encoder at one D.Va actor-backward chunk (N images),
each jitted alone, against this machine's float32 matmul rate (the better of XLA's dot and NumPy's
BLAS on the CPU).

    python benchmarks/encoder_layers.py [--images 16] [--image-size 48] [--channels-in 9] [--no-configure]

Prints a markdown table (ms and GFLOP/s per convolution) and the sum over one chunk against the
compute bound (the first layer's input gradient is not counted: the pixels need none).
"""

from __future__ import annotations

import argparse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=16, help="images per chunk (the CPU preset's 16 envs)")
    parser.add_argument("--image-size", type=int, default=48)
    parser.add_argument("--channels-in", type=int, default=9, help="3 × stacked frames")
    parser.add_argument(
        "--no-configure", action="store_true", help="skip dva.configure(): JAX's default CPU convolutions"
    )
    args = parser.parse_args()
    if not args.no_configure:
        import dva

        dva.configure()  # before JAX computes: the CPU convolution flags, compile caches

    import jax

    from dva.analysis.bench import machine_description, markdown_table, timed
    from dva.analysis.profile import matmul_rates
    from dva.networks import conv_valid

    xla_rate, blas_rate = matmul_rates()
    rate = max(xla_rate, blas_rate)
    best_seconds = lambda fn, *a: timed(fn, *a, repeats=20)[1]
    key = jax.random.PRNGKey(0)
    size, channels_in, rows, total_s, total_flops = args.image_size, args.channels_in, [], 0.0, 0.0
    for layer, stride in enumerate((2, 1, 1, 1)):  # DrQ-v2's encoder: 3×3, 32 channels
        out = (size - 3) // stride + 1
        x = jax.random.normal(key, (args.images, size, size, channels_in))
        kernel = 0.1 * jax.random.normal(key, (3, 3, channels_in, 32))
        out_grad = jax.random.normal(key, (args.images, out, out, 32))
        flops = 2.0 * args.images * out * out * 32 * 9 * channels_in
        # each gradient alone: XLA drops the unused forward and the other gradient
        parts = {
            "forward": best_seconds(jax.jit(lambda x, k: conv_valid(x, k, stride)), x, kernel),
            "kernel gradient": best_seconds(
                jax.jit(lambda x, k, g: jax.vjp(lambda k: conv_valid(x, k, stride), k)[1](g)[0]), x, kernel, out_grad
            ),
            "input gradient": best_seconds(
                jax.jit(lambda x, k, g: jax.vjp(lambda x: conv_valid(x, k, stride), x)[1](g)[0]), x, kernel, out_grad
            ),
        }
        for part, seconds in parts.items():
            counted = layer > 0 or part != "input gradient"
            total_s, total_flops = total_s + seconds * counted, total_flops + flops * counted
            rows.append(
                (
                    f"{layer} ({size}² × {channels_in} → {out}² × 32, stride {stride})",
                    part,
                    f"{seconds * 1e3:.2f}",
                    f"{flops / seconds / 1e9:.0f}",
                    "" if counted else "not needed",
                )
            )
        size, channels_in = out, 32
    setup = "JAX's default XLA flags" if args.no_configure else "dva.configure()"
    print(f"{args.images} images of {args.image_size}² × {args.channels_in}, {setup}; {machine_description()}")
    print(markdown_table(["layer", "convolution", "ms", "GFLOP/s", ""], rows))
    bound = total_flops / rate
    print(
        f"\none chunk: {total_s * 1e3:.2f} ms for {total_flops / 1e6:.0f} MFLOP = {total_flops / total_s / 1e9:.0f} "
        f"GFLOP/s; matmul rate {rate / 1e9:.0f} GFLOP/s "
        f"(XLA {xla_rate / 1e9:.0f}, BLAS {blas_rate / 1e9:.0f}) → bound {bound * 1e3:.2f} ms, "
        f"{total_s / bound:.2f}× the bound"
    )


if __name__ == "__main__":
    main()

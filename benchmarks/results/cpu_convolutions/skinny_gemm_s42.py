"""Session 42: the float32 GEMM rate at the shapes of the encoder's kernel gradients (one D.Va chunk),
with the patch matrix stored along the contraction (M × K) or the other way (K × M), against a 2048² matmul.
Run: .venv/bin/python benchmarks/results/cpu_convolutions/skinny_gemm_s42.py"""
import jax, jax.numpy as jnp
import dva  # XLA flags
from dva.analysis.bench import timed
from dva.analysis.profile import matmul_flops_per_s
key = jax.random.PRNGKey(0)
print("square 2048 matmul GFLOP/s", matmul_flops_per_s() / 1e9)
# kernel-gradient GEMM shapes of one D.Va chunk (16 images): K = 16·Ho·Wo, output 9·ci × co
for name, m, k, n in [("layer1 kgrad", 288, 16 * 21 * 21, 32), ("layer2 kgrad", 288, 16 * 19 * 19, 32),
                      ("layer0 kgrad", 81, 16 * 23 * 23, 32), ("layer1 fwd (patch)", 16 * 21 * 21, 288, 32),
                      ("layer1 kgrad x4 chunk", 288, 64 * 21 * 21, 32)]:
    a = jax.random.normal(key, (m, k)); b = jax.random.normal(key, (k, n))
    f = jax.jit(lambda a, b: a @ b)
    if m < k:  # A is stored as its transpose in practice: patches (K × M)
        at = a.T
        g = jax.jit(lambda at, b: at.T @ b)
        s2 = timed(g, at, b, repeats=30)[1]
    else:
        s2 = float("nan")
    s = timed(f, a, b, repeats=30)[1]
    fl = 2 * m * k * n
    print(f"{name}: {m}x{k} @ {k}x{n}: {s*1e3:.3f} ms {fl/s/1e9:.0f} GFLOP/s; from K-major A {fl/s2/1e9:.0f} GFLOP/s")

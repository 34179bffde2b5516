"""Session 42: the 3×3 kernel gradient at one D.Va chunk (16 images) as ONE GEMM over a flat image
plane with shifted copies (of G or of X) instead of XLA's convolution, and the parts of that form.
Run: .venv/bin/python benchmarks/results/cpu_convolutions/kernel_gradient_shifted_s42.py"""
import jax, jax.numpy as jnp, numpy as np
import dva
from dva.analysis.bench import timed
from dva.networks import conv_valid

def kgrad_xla(x, k, g):
    return jax.vjp(lambda k: conv_valid(x, k, 1), k)[1](g)[0]

def kgrad_shift(x, k, g):
    n, H, W, ci = x.shape; _, Ho, Wo, co = g.shape; kh, kw = k.shape[:2]
    L = n * H * W
    xt = x.transpose(3, 0, 1, 2).reshape(ci, L)
    gp = jnp.pad(g, ((0, 0), (0, H - Ho), (0, W - Wo), (0, 0))).reshape(L, co)
    offs = [a * W + b for a in range(kh) for b in range(kw)]
    big = jnp.pad(gp, ((max(offs), 0), (0, 0)))
    b = jnp.concatenate([big[max(offs) - o: max(offs) - o + L] for o in offs], axis=1)  # (L, taps·co)
    return (xt @ b).reshape(ci, kh, kw, co).transpose(1, 2, 0, 3)

def kgrad_shiftx(x, k, g):
    """Shift X instead (taps on the M side): (taps·ci, L) @ (L, co)."""
    n, H, W, ci = x.shape; _, Ho, Wo, co = g.shape; kh, kw = k.shape[:2]
    L = n * H * W
    xt = x.transpose(3, 0, 1, 2).reshape(ci, L)
    xt = jnp.pad(xt, ((0, 0), (0, 2 * W + 2)))
    gp = jnp.pad(g, ((0, 0), (0, H - Ho), (0, W - Wo), (0, 0))).reshape(L, co)
    offs = [a * W + b for a in range(kh) for b in range(kw)]
    a = jnp.concatenate([xt[:, o:o + L] for o in offs], axis=0)  # (taps·ci, L)
    return (a @ gp).reshape(kh, kw, ci, co)

key = jax.random.PRNGKey(0)
for size in (23, 21, 19):
    x = jax.random.normal(key, (16, size, size, 32)); k = jax.random.normal(key, (3, 3, 32, 32))
    g = jax.random.normal(jax.random.PRNGKey(1), (16, size - 2, size - 2, 32))
    ref = jax.jit(kgrad_xla)(x, k, g)
    fl = 2 * 16 * (size - 2) ** 2 * 32 * 9 * 32
    for name, fn in (("xla conv", kgrad_xla), ("shift G", kgrad_shift), ("shift X", kgrad_shiftx)):
        f = jax.jit(fn)
        err = float(jnp.max(jnp.abs(f(x, k, g) - ref)) / jnp.max(jnp.abs(ref)))
        s = timed(f, x, k, g, repeats=40)[1]
        print(f"{size}²: {name:9s} {s*1e3:.3f} ms {fl/s/1e9:.0f} GFLOP/s  rel err {err:.1e}")
print("parts at 23²")
x = jax.random.normal(key, (16, 23, 23, 32)); g = jax.random.normal(key, (16, 21, 21, 32))
L = 16 * 23 * 23
a = jax.random.normal(key, (32, L)); b = jax.random.normal(key, (L, 288)); a2 = jax.random.normal(key, (288, L)); b2 = jax.random.normal(key, (L, 32))
for name, f, args in (("dot 32xL @ Lx288", lambda a, b: a @ b, (a, b)), ("dot 288xL @ Lx32", lambda a, b: a @ b, (a2, b2)),
                      ("transpose x", lambda x: x.transpose(3, 0, 1, 2).reshape(32, L) + 0, (x,)),
                      ("build shifted G", lambda g: jnp.concatenate([jnp.pad(jnp.pad(g, ((0,0),(0,2),(0,2),(0,0))).reshape(L, 32), ((48,0),(0,0)))[48-o:48-o+L] for o in range(9)], 1), (g,))):
    s = timed(jax.jit(f), *args, repeats=40)[1]
    print(f"{name}: {s*1e3:.3f} ms")

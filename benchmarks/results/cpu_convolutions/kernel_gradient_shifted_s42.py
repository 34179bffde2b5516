"""Session 42: the 3×3 kernel gradient at one D.Va chunk (16 images) as ONE GEMM over a flat image
plane with shifted copies (of G or of X) instead of XLA's convolution, and the parts of that form.
Run: .venv/bin/python benchmarks/results/cpu_convolutions/kernel_gradient_shifted_s42.py"""
import jax, jax.numpy as jnp
import dva
from dva.analysis.bench import timed
from dva.networks import conv_valid

def kgrad_xla(x, k, g):
    return jax.vjp(lambda k: conv_valid(x, k, 1), k)[1](g)[0]

def flat_planes(x, g, taps):
    """x as one flat plane per input channel (ci, L), g zero-padded to x's grid and flattened
    (L, co), and each tap's offset in the flat plane (L = n·H·W)."""
    n, H, W, ci = x.shape; _, Ho, Wo, _ = g.shape
    xt = x.transpose(3, 0, 1, 2).reshape(ci, n * H * W)
    gp = jnp.pad(g, ((0, 0), (0, H - Ho), (0, W - Wo), (0, 0))).reshape(n * H * W, -1)
    return xt, gp, [a * W + b for a in range(taps[0]) for b in range(taps[1])]

def shifted_g(gp, offs):
    """(L, taps·co): g shifted down by each tap's offset."""
    big = jnp.pad(gp, ((max(offs), 0), (0, 0)))
    return jnp.concatenate([big[max(offs) - o: max(offs) - o + len(gp)] for o in offs], axis=1)

def kgrad_shift(x, k, g):
    xt, gp, offs = flat_planes(x, g, k.shape[:2])
    return (xt @ shifted_g(gp, offs)).reshape(x.shape[-1], *k.shape[:2], -1).transpose(1, 2, 0, 3)

def kgrad_shiftx(x, k, g):
    """Shift X instead (taps on the M side): (taps·ci, L) @ (L, co)."""
    xt, gp, offs = flat_planes(x, g, k.shape[:2])
    xt = jnp.pad(xt, ((0, 0), (0, max(offs))))
    a = jnp.concatenate([xt[:, o:o + len(gp)] for o in offs], axis=0)  # (taps·ci, L)
    return (a @ gp).reshape(*k.shape[:3], -1)

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
                      ("transpose x", lambda x: flat_planes(x, g, (3, 3))[0] + 0, (x,)),
                      ("build shifted G", lambda g: shifted_g(*flat_planes(x, g, (3, 3))[1:]), (g,))):
    s = timed(jax.jit(f), *args, repeats=40)[1]
    print(f"{name}: {s*1e3:.3f} ms")

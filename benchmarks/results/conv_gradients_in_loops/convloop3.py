import time, sys, os
import dva
import jax, jax.numpy as jnp
from jax import lax
DN = ("NHWC", "HWIO", "NHWC")
key = jax.random.PRNGKey(0)
def conv(x, k, s=1, lhs_dil=1, rhs_dil=1, pad="VALID"):
    return lax.conv_general_dilated(x, k, (s, s), pad, lhs_dilation=(lhs_dil,)*2, rhs_dilation=(rhs_dil,)*2, dimension_numbers=DN)

def kgrad_xla(x, k, dy, s):
    return jax.vjp(lambda k: conv(x, k, s), k)[1](dy)[0]
def kgrad_conv(x, k, dy, s):
    # dK[i,j,c,o] = sum_n,y,x X[n, s*y+i, s*x+j, c] dY[n,y,x,o]
    kh = k.shape[0]
    hx = (dy.shape[1] - 1) * s + kh
    x = x[:, :hx, :hx]
    out = conv(x.transpose(3, 1, 2, 0), dy.transpose(1, 2, 0, 3), 1, rhs_dil=s)
    return out.transpose(1, 2, 0, 3)
def kgrad_taps(x, k, dy, s):
    kh = k.shape[0]; n, h, w, o = dy.shape
    g = dy.reshape(-1, o)
    rows = []
    for i in range(kh):
        for j in range(kh):
            patch = x[:, i:i + s * (h - 1) + 1:s, j:j + s * (w - 1) + 1:s, :].reshape(-1, x.shape[-1])
            rows.append(patch.T @ g)
    return jnp.stack(rows).reshape(kh, kh, x.shape[-1], o)
def igrad_xla(x, k, dy, s):
    return jax.vjp(lambda x: conv(x, k, s), x)[1](dy)[0]
def igrad_conv(x, k, dy, s):
    kh = k.shape[0]
    kf = jnp.flip(k, (0, 1)).transpose(0, 1, 3, 2)
    hin = x.shape[1]
    # output size with lhs dilation s, padding kh-1 each side: (h-1)*s+1 + 2(kh-1) - kh + 1 = (h-1)*s + kh
    extra = hin - ((dy.shape[1] - 1) * s + kh)
    return conv(dy, kf, 1, lhs_dil=s, pad=[(kh - 1, kh - 1 + extra)] * 2)

def bench(name, f, *args):
    r = f(*args); jax.block_until_ready(r); ts = []
    for _ in range(3):
        t = time.perf_counter(); jax.block_until_ready(f(*args)); ts.append(time.perf_counter() - t)
    print(f"{name}: {min(ts):.3f} s", flush=True); return r
def top(fn, s): return jax.jit(lambda x, k, dy: [fn(x[i], k, dy[i], s) for i in range(2)])
def loop(fn, s): return jax.jit(lambda x, k, dy: jax.lax.scan(lambda c, a: (c, fn(a[0], k, a[1], s)), 0, (x, dy))[1])

for s, cin, hin in [(1, 32, 46), (2, 9, 48)]:
    x = jax.random.normal(key, (2, 128, hin, hin, cin)); k = jax.random.normal(key, (3, 3, cin, 32)) * 0.1
    dy = jax.random.normal(key, (2, 128, (hin - 3) // s + 1, (hin - 3) // s + 1, 32))
    print(f"--- stride {s}, {cin}->32, {hin}²")
    ref = bench("kgrad xla top", top(kgrad_xla, s), x, k, dy)
    for nm, fn in [("kgrad conv", kgrad_conv), ("kgrad taps", kgrad_taps)]:
        r = bench(nm + " top", top(fn, s), x, k, dy); print("   err", float(jnp.max(jnp.abs(r[0] - ref[0]))) / float(jnp.max(jnp.abs(ref[0]))))
        bench(nm + " scan", loop(fn, s), x, k, dy)
    ref = bench("igrad xla top", top(igrad_xla, s), x, k, dy)
    r = bench("igrad conv top", top(igrad_conv, s), x, k, dy); print("   err", float(jnp.max(jnp.abs(r[0] - ref[0]))))
    bench("igrad conv scan", loop(igrad_conv, s), x, k, dy)

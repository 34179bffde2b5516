import time, sys, os
import dva
import jax, jax.numpy as jnp
print(os.environ.get("XLA_FLAGS"))
from dva.networks import conv_valid
key = jax.random.PRNGKey(0)
x = jax.random.normal(key, (2, 128, 46, 46, 32))
k = jax.random.normal(key, (3, 3, 32, 32)) * 0.1
dy = jax.random.normal(key, (2, 128, 44, 44, 32))

def fwd(x, k): return conv_valid(x, k, 1)
def kgrad(x, k, dy): return jax.vjp(lambda k: fwd(x, k), k)[1](dy)[0]
def igrad(x, k, dy): return jax.vjp(lambda x: fwd(x, k), x)[1](dy)[0]

def top(fn):
    return jax.jit(lambda x, k, dy: [fn(x[i], k, dy[i]) for i in range(2)])
def loop(fn):
    return jax.jit(lambda x, k, dy: jax.lax.scan(lambda c, a: (c, fn(a[0], k, a[1])), 0, (x, dy))[1])
def bench(name, f):
    jax.block_until_ready(f(x, k, dy)); ts = []
    for _ in range(3):
        t = time.perf_counter(); jax.block_until_ready(f(x, k, dy)); ts.append(time.perf_counter() - t)
    print(f"{name}: {min(ts):.3f} s", flush=True)
for name, fn in [("fwd", lambda x, k, dy: fwd(x, k)), ("kgrad", kgrad), ("igrad", igrad)]:
    bench(name + " top", top(fn)); bench(name + " scan", loop(fn))

"""Encoder VJP over 256 frames: plain, inside a scan of 1, scan of 2 chunks, vmap of kept vjps."""
import time, sys, os
MODE = os.environ.get("MODE", "vmap")
import dva  # sets XLA flags
import jax, jax.numpy as jnp
from dva.networks import Actor

actor = Actor(3, (64, 64), pixels=True, trunk=50)
key = jax.random.PRNGKey(0)
obs = jax.random.randint(key, (16, 16, 48, 48, 9), 0, 255).astype(jnp.uint8)
g = jax.random.normal(key, (16, 16, 3))
params = actor.init(key, obs[0])

def f(p, o):
    return actor.apply(p, o)[0]

@jax.jit
def plain(p, o, g):
    o = o.reshape((-1,) + o.shape[2:]); g = g.reshape(-1, 3)
    return jax.vjp(lambda p: f(p, o), p)[1](g)[0]

def scanned(chunk):
    @jax.jit
    def run(p, o, g):
        o = o.reshape((-1, chunk * 16) + o.shape[2:]); g = g.reshape(-1, chunk * 16, 3)
        def body(tot, x):
            oo, gg = x
            gr = jax.vjp(lambda p: f(p, oo), p)[1](gg)[0]
            return jax.tree.map(jnp.add, tot, gr), None
        return jax.lax.scan(body, jax.tree.map(jnp.zeros_like, p), (o, g))[0]
    return run

@jax.jit
def kept(p, o, g):
    def step(c, oo):
        out, vjp = jax.vjp(lambda p: f(p, oo), p)
        return c, vjp
    _, vjps = jax.lax.scan(step, 0, o)
    if MODE == "vmap":
        per = jax.vmap(lambda v, gg: v(gg)[0])(vjps, g)
        return jax.tree.map(lambda x: x.sum(0), per)
    def add(tot, vg):
        v, gg = vg
        return jax.tree.map(jnp.add, tot, v(gg)[0]), None
    return jax.lax.scan(add, jax.tree.map(jnp.zeros_like, p), (vjps, g))[0]

def bench(name, fn):
    r = fn(params, obs, g); jax.block_until_ready(r)
    ts = []
    for _ in range(5):
        t = time.perf_counter(); jax.block_until_ready(fn(params, obs, g)); ts.append(time.perf_counter() - t)
    print(f"{name}: best {min(ts):.3f} s median {sorted(ts)[2]:.3f}", flush=True)
    return r

ref = bench("plain batch 256 (fwd+bwd)", plain)
for name in sys.argv[1:]:
    if name == "kept":
        r = bench("kept vjps, vmapped (fwd in scan + bwd)", kept)
    else:
        r = bench(f"scan chunks of {name} steps", scanned(int(name)))
    err = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(r)))
    print("  max abs diff", err)

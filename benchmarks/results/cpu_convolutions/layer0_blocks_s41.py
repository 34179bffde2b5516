import jax, jax.numpy as jnp
import dva  # noqa
from dva.analysis.bench import timed
from dva.networks import conv_valid
best = lambda f, *a: timed(f, *a, repeats=30)[1]
key = jax.random.PRNGKey(0)
x = jax.random.normal(key, (16, 48, 48, 9)); k = 0.1*jax.random.normal(key, (3,3,9,32)); g = jax.random.normal(key, (16,23,23,32))
def blocks(x):  # 2×2 pixel blocks as channels: (N, 24, 24, 36)
    n, h, w, c = x.shape
    return x.reshape(n, h//2, 2, w//2, 2, c).transpose(0, 1, 3, 2, 4, 5).reshape(n, h//2, w//2, 4*c)
def block_kernel(k):  # the 3×3 kernel zero-padded to 4×4, as a 2×2 kernel over blocks
    k4 = jnp.pad(k, ((0, 1), (0, 1), (0, 0), (0, 0)))
    return k4.reshape(2, 2, 2, 2, 9, 32).transpose(0, 2, 1, 3, 4, 5).reshape(2, 2, 36, 32)
direct = lambda x, k: conv_valid(x, k, 2)
blocked = lambda x, k: conv_valid(blocks(x), block_kernel(k), 1)
print("max diff", float(jnp.abs(jax.jit(direct)(x, k) - jax.jit(blocked)(x, k)).max()))
for name, f in (("stride 2", direct), ("2×2 blocks", blocked)):
    fwd = best(jax.jit(f), x, k)
    kg = best(jax.jit(lambda x, k, g: jax.vjp(lambda k: f(x, k), k)[1](g)[0]), x, k, g)
    print(f"{name}: forward {fwd*1e3:.2f} ms, kernel gradient {kg*1e3:.2f} ms, sum {(fwd+kg)*1e3:.2f}")

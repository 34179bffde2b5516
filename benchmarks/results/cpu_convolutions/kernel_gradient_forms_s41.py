import jax, jax.numpy as jnp
import dva  # noqa
from dva.analysis.bench import timed
from dva.networks import conv_valid
best = lambda f, *a: timed(f, *a, repeats=30)[1]
key = jax.random.PRNGKey(0)
for size, cin, stride in ((48, 9, 2), (23, 32, 1), (21, 32, 1), (19, 32, 1)):
    out = (size-3)//stride+1
    x = jax.random.normal(key, (16, size, size, cin)); k = 0.1*jax.random.normal(key, (3,3,cin,32)); g = jax.random.normal(key, (16,out,out,32))
    xla = jax.jit(lambda x,k,g: jax.vjp(lambda k: conv_valid(x,k,stride), k)[1](g)[0])
    def patches_kgrad(x, k, g):
        taps = [x[:, i:i + stride*(out-1)+1:stride, j:j + stride*(out-1)+1:stride] for i in range(3) for j in range(3)]
        p = jnp.concatenate(taps, -1).reshape(-1, 9*cin)
        return (p.T @ g.reshape(-1, 32)).reshape(3, 3, cin, 32)
    def pertap_kgrad(x, k, g):
        gg = g.reshape(-1, 32)
        return jnp.stack([x[:, i:i + stride*(out-1)+1:stride, j:j + stride*(out-1)+1:stride].reshape(-1, cin).T @ gg for i in range(3) for j in range(3)]).reshape(3,3,cin,32)
    ref = xla(x,k,g)
    for name, f in (("xla conv", xla), ("patch matmul", jax.jit(patches_kgrad)), ("per tap", jax.jit(pertap_kgrad))):
        err = float(jnp.abs(f(x,k,g)-ref).max()/jnp.abs(ref).max())
        print(f"{size}²×{cin} s{stride}: {name:13s} {best(f,x,k,g)*1e3:.2f} ms  rel err {err:.1e}")

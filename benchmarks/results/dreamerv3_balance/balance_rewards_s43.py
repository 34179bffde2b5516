"""Cart-pole balance (state, 256 envs, each env's first episode) under uniform random, zero and
constant +1 actions: the return, how often and when the cart leaves the rail (|x| >= 2.5), and the
mean reward by step. Does ending the episode early pay? (The drifted DreamerV3 policy's evaluations
read -2 to -8.)"""
import jax, jax.numpy as jnp, numpy as np
from dva.tasks import make_task

task = make_task("cartpole_balance")
N, T = 256, 240

def run(policy):
    @jax.jit
    def go(key):
        state = task.reset(key, N)
        def one(s, k):
            s = task.step(s, policy(k))
            return s, (s.reward, s.terminated, s.truncated)
        return jax.lax.scan(one, state, jax.random.split(key, T))[1]
    r, term, trunc = map(np.asarray, go(jax.random.PRNGKey(0)))
    return r, term

for name, policy in (("random", lambda k: jax.random.uniform(k, (N, 1), minval=-1, maxval=1)),
                     ("zero", lambda k: jnp.zeros((N, 1))),
                     ("push +1", lambda k: jnp.ones((N, 1)))):
    r, term = run(policy)
    first_end = np.where(term.any(0), term.argmax(0), T)  # step of each env's first termination
    alive = np.arange(T)[:, None] <= first_end[None]
    ret = (r * alive).sum(0)
    per_t = [(t, float(np.mean(r[t][alive[t]])) if alive[t].any() else float('nan')) for t in (0, 30, 60, 90, 120, 180, 239)]
    print(f"{name:8s} first-episode return {ret.mean():7.1f} ± {ret.std():5.1f}; terminated {np.mean(first_end < T):.2f} at step {np.mean(first_end[first_end < T]) if (first_end < T).any() else float('nan'):.0f}")
    print("   mean reward at step", ", ".join(f"{t}: {v:.2f}" for t, v in per_t))
    # what is left after step 60 (the pole down under random actions)
    print("   sum of rewards from step 60 on (alive):", float(((r * alive)[60:]).sum(0).mean()))

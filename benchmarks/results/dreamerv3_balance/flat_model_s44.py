"""From a DreamerV3 checkpoint: what the model imagines for fixed action policies from replayed
posterior starts, and which way the actor's gradient points."""
import sys
import jax, jax.numpy as jnp, numpy as np
from dva.training import load_run
from dva.algorithms.dreamerv3 import features, sample_onehot
from dva.algorithms.dreamer_math import twohot_decode, lambda_returns

spec, agent, state = load_run(sys.argv[1])
cfg = agent.config
model, actor, critic = state.params["model"], state.params["actor"], state.params["critic"]
steps = agent.replay.sample_sequences(state.replay, jax.random.PRNGKey(3))
_, ((deter, stoch), _) = jax.jit(agent.world_model_loss)(model, steps, jax.random.PRNGKey(1))
deter, stoch = deter.reshape(-1, deter.shape[-1]), stoch.reshape((-1,) + stoch.shape[2:])

def rollout(policy, key, horizon=cfg.horizon):
    def step(carry, k):
        d, s = carry
        f = features(d, s)
        a = policy(f)
        d = agent.transition(model, d, s, a)
        s = sample_onehot(agent.prior(model, d), k)
        return (d, s), (f, a)
    (d, s), (feats, acts) = jax.lax.scan(step, (deter, stoch), jax.random.split(key, horizon))
    feats = jnp.concatenate([feats, features(d, s)[None]])
    reward = twohot_decode(agent.reward_head.apply(model["reward"], feats[1:]), agent.bins)
    cont = jax.nn.sigmoid(agent.cont_head.apply(model["cont"], feats[1:])[..., 0])
    value = twohot_decode(agent.critic.apply(critic, feats), agent.bins)
    ret = lambda_returns(reward, value, cont, cfg.gamma, cfg.lam)
    return reward, cont, value, ret, acts

A = agent.task.action_dim
policies = {
    "actor mean": lambda f: agent.action_distribution(actor, f)[0],
    "zero": lambda f: jnp.zeros(f.shape[:-1] + (A,)),
    "+1": lambda f: jnp.ones(f.shape[:-1] + (A,)),
    "-1": lambda f: -jnp.ones(f.shape[:-1] + (A,)),
    "+0.5": lambda f: 0.5 * jnp.ones(f.shape[:-1] + (A,)),
}
key = jax.random.PRNGKey(5)
print(f"{len(deter)} starts; replayed rewards {float(steps.reward.mean()):.2f} ± {float(steps.reward.std()):.2f}")
for name, pol in policies.items():
    r, c, v, R, a = jax.jit(lambda k: rollout(pol, k))(key)
    print(f"{name:10s} reward/step {float(r.mean()):7.2f} (step1 {float(r[0].mean()):6.2f}, step15 {float(r[-1].mean()):6.2f}) "
          f"cont {float(c.mean()):.3f} min {float(c.min()):.3f}  v0 {float(v[0].mean()):8.1f} vH {float(v[-1].mean()):8.1f} R0 {float(R[0].mean()):8.1f} "
          f"mean|a| {float(jnp.abs(a).mean()):.2f} mean a {float(a.mean()):+.2f}")

# the actor's mean action over the starts
mean_a = agent.action_distribution(actor, features(deter, stoch))[0]
print("actor mean action at starts: mean", float(mean_a.mean()), "abs", float(jnp.abs(mean_a).mean()), "frac>0", float((mean_a > 0).mean()))
# gradient of the imagined λ-return R0 w.r.t. a constant action offset added to the actor's mean
def objective(offset, part):
    def pol(f):
        return jnp.clip(agent.action_distribution(actor, f)[0] + offset, -1, 1)
    r, c, v, R, a = rollout(pol, key)
    if part == "R0":
        return R[0].mean()
    if part == "rewards":
        return r.sum(0).mean()
    if part == "vH":
        return v[-1].mean()
    if part == "cont":
        return c.prod(0).mean()
for part in ("R0", "rewards", "vH", "cont"):
    g = jax.jit(jax.grad(lambda o: objective(o, part)))(jnp.zeros(A))
    print(f"d {part:8s}/d offset = {np.asarray(g)}")

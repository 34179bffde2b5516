"""Offline: from a DreamerV3 checkpoint, keep updating on the fixed replay (no new data) and watch
whether the reward head can fit the replayed rewards (loss in nats, correlation of predictions)."""
import sys, time
import jax, numpy as np
from dva.training import load_run
from dva.algorithms.dreamerv3 import features
from dva.algorithms.dreamer_math import twohot_decode

spec, agent, state = load_run(sys.argv[1])
blocks = int(sys.argv[2]) if len(sys.argv) > 2 else 10

@jax.jit
def block(state, key):
    return jax.lax.scan(agent.update, state, jax.random.split(key, 100))

@jax.jit
def reward_fit(state, key):
    steps = agent.replay.sample_sequences(state.replay, key)
    model = state.params["model"]
    # the same alignment as world_model_loss: reward of step t from the state reached at t + 1
    _, ((deter, stoch), _) = agent.world_model_loss(model, steps, key)
    pred = twohot_decode(agent.reward_head.apply(model["reward"], features(deter, stoch)[:, 1:]), agent.bins)
    target = steps.reward[:, :-1]
    keep = ~steps.first[:, 1:]
    return pred, target, keep

key = jax.random.PRNGKey(1)
for i in range(blocks):
    key, k1, k2 = jax.random.split(key, 3)
    pred, target, keep = jax.device_get(reward_fit(state, k2))
    p, t = pred[keep], target[keep]
    print(f"after {i*100:5d} offline updates: pred {p.mean():7.2f} ± {p.std():6.2f}, target {t.mean():7.2f} ± {t.std():6.2f}, "
          f"corr {np.corrcoef(p, t)[0, 1]:.3f}, rmse {np.sqrt(np.mean((p - t) ** 2)):.2f}", flush=True)
    t0 = time.time()
    state, metrics = block(state, k1)
    m = jax.device_get(metrics)
    print(f"   block: reward_loss {m['reward_loss'].mean():.3f} (last 10: {m['reward_loss'][-10:].mean():.3f}), image {m['image_loss'].mean():.1f}, {time.time()-t0:.0f} s", flush=True)

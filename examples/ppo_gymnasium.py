"""PPO on a dva task through Gymnasium's vector API, in CleanRL's one-file style (JAX + Optax).

    python examples/ppo_gymnasium.py --task cartpole_swingup --total-steps 600000

Nothing here is dva-specific but the environment id: ``gymnasium.make_vec("dva/<task>-v0")``
hands out NumPy batches like any Gymnasium vector env, wrapped as CleanRL wraps its continuous
control envs (Gymnasium's own ``RecordEpisodeStatistics``, ``ClipAction``,
``NormalizeObservation``, ``TransformObservation``, ``NormalizeReward``, ``TransformReward``).
The envs auto-reset on the step after an episode ends (``AutoresetMode.NEXT_STEP``, Gymnasium's
default): the ending step returns the observation it reached, so a truncated episode bootstraps
from its value, and the reset step that follows is not a transition and is left out of the loss.
"""

from __future__ import annotations

import dataclasses
import time

import flax.linen as nn
import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import optax
import tyro

import dva


@dataclasses.dataclass
class Args:
    task: str = "cartpole_swingup"
    seed: int = 0
    num_envs: int = 16
    num_steps: int = 128  # per env and rollout
    total_steps: int = 600_000
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    update_epochs: int = 10
    num_minibatches: int = 32
    clip_coef: float = 0.2
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5


class ActorCritic(nn.Module):
    action_dim: int

    @nn.compact
    def __call__(self, obs):
        def mlp(x, out, scale):
            for _ in range(2):
                x = nn.tanh(nn.Dense(64, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
            return nn.Dense(out, kernel_init=nn.initializers.orthogonal(scale))(x)

        mean = mlp(obs, self.action_dim, 0.01)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_dim,))
        return mean, log_std, mlp(obs, 1, 1.0)[..., 0]


def log_prob(mean, log_std, action):
    return jnp.sum(-0.5 * ((action - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi), -1)


def main(args: Args) -> list[tuple[int, float]]:
    """Train; returns (env steps, mean return of the episodes finished in that rollout) per rollout."""
    vector = gymnasium.wrappers.vector
    envs = gymnasium.make_vec(f"dva/{args.task}-v0", num_envs=args.num_envs)
    envs = vector.RecordEpisodeStatistics(envs)  # the unnormalised returns
    envs = vector.ClipAction(envs)
    envs = vector.NormalizeObservation(envs)
    envs = vector.TransformObservation(envs, lambda obs: np.clip(obs, -10, 10))
    envs = vector.NormalizeReward(envs, gamma=args.gamma)
    envs = vector.TransformReward(envs, lambda reward: np.clip(reward, -10, 10))
    model = ActorCritic(envs.single_action_space.shape[0])
    key = jax.random.PRNGKey(args.seed)
    obs, _ = envs.reset(seed=args.seed)
    params = model.init(key, obs)
    num_updates = args.total_steps // (args.num_envs * args.num_steps)
    schedule = optax.linear_schedule(args.learning_rate, 0.0, num_updates * args.update_epochs * args.num_minibatches)
    optimizer = optax.chain(optax.clip_by_global_norm(args.max_grad_norm), optax.adam(schedule, eps=1e-5))
    opt_state = optimizer.init(params)

    @jax.jit
    def act(params, obs, key):
        mean, log_std, value = model.apply(params, obs)
        action = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        return action, log_prob(mean, log_std, action), value

    @jax.jit
    def update(params, opt_state, batch, key):
        def loss_fn(params, mb):
            mean, log_std, value = model.apply(params, mb["obs"])
            ratio = jnp.exp(log_prob(mean, log_std, mb["action"]) - mb["log_prob"])
            valid = mb["valid"]  # 0 on the reset steps: no transition
            count = jnp.maximum(valid.sum(), 1.0)
            adv_mean = jnp.sum(valid * mb["advantage"]) / count
            adv_std = jnp.sqrt(jnp.sum(valid * (mb["advantage"] - adv_mean) ** 2) / count)
            adv = (mb["advantage"] - adv_mean) / (adv_std + 1e-8)
            policy_loss = jnp.maximum(-adv * ratio, -adv * jnp.clip(ratio, 1 - args.clip_coef, 1 + args.clip_coef))
            value_loss = 0.5 * (value - mb["return"]) ** 2
            return jnp.sum(valid * (policy_loss + args.vf_coef * value_loss)) / count

        def epoch(carry, key):
            order = jax.random.permutation(key, len(batch["obs"])).reshape(args.num_minibatches, -1)

            def minibatch(carry, idx):
                params, opt_state = carry
                grads = jax.grad(loss_fn)(params, jax.tree.map(lambda x: x[idx], batch))
                updates, opt_state = optimizer.update(grads, opt_state)
                return (optax.apply_updates(params, updates), opt_state), None

            return jax.lax.scan(minibatch, carry, order)[0], None

        return jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, args.update_epochs))[0]

    @jax.jit
    def advantages(rewards, values, next_value, terminated, dones):
        """GAE, the chain cut where an episode ended; the step after an ending holds the observation
        it reached, so a truncated episode bootstraps from that observation's value."""

        def back(carry, x):
            gae, next_v = carry
            r, v, term, d = x
            delta = r + args.gamma * next_v * (1 - term) - v
            gae = delta + args.gamma * args.gae_lambda * (1 - d) * gae
            return (gae, v), gae

        xs = (rewards, values, terminated, dones)
        _, adv = jax.lax.scan(back, (jnp.zeros_like(next_value), next_value), xs, reverse=True)
        return adv, adv + values

    curve, start = [], time.time()
    autoreset = np.zeros(args.num_envs, bool)  # the envs whose next step is a reset, not a transition
    for update_index in range(num_updates):
        names = ("obs", "action", "log_prob", "value", "reward", "terminated", "done", "valid")
        rollout = {name: [] for name in names}
        returns = []
        for _ in range(args.num_steps):
            key, step_key = jax.random.split(key)
            action, logp, value = act(params, obs, step_key)
            next_obs, reward, terminated, truncated, info = envs.step(np.asarray(action))
            row = (obs, action, logp, value, reward, terminated, terminated | truncated, ~autoreset)
            for name, x in zip(names, row):
                rollout[name].append(np.asarray(x, np.float32))
            if "episode" in info:
                returns += list(info["episode"]["r"][info["_episode"]])
            obs, autoreset = next_obs, terminated | truncated
        data = {name: np.stack(xs) for name, xs in rollout.items()}
        next_value = act(params, obs, key)[2]
        adv, ret = advantages(data["reward"], data["value"], next_value, data["terminated"], data["done"])
        batch = {name: data[name] for name in ("obs", "action", "log_prob", "valid")}
        batch = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), dict(batch, advantage=adv, **{"return": ret}))
        key, update_key = jax.random.split(key)
        params, opt_state = update(params, opt_state, batch, update_key)
        steps = (update_index + 1) * args.num_envs * args.num_steps
        if returns:
            curve.append((steps, float(np.mean(returns))))
            print(f"steps {steps:>8d}  return {curve[-1][1]:8.1f}  {time.time() - start:6.1f} s", flush=True)
    envs.close()
    return curve


if __name__ == "__main__":
    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main(tyro.cli(Args))

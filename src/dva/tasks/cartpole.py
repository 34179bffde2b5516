"""Cart-pole: swing-up (the pole starts hanging down) and balance (it starts upright)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from dva.tasks.base import Task, load_asset_spec
from dva.tasks.physics import PenaltyContact


class CartpoleSwingup(Task):
    """Reward (the paper's appendix E): ``R = 10 − θ² − 0.1 θ̇² − 0.05 x² − 0.1 ẋ²`` with θ measured from upright.

    State observation (5-D, SHAC's): ``[x, ẋ, sin θ, cos θ, θ̇]``. Terminates when ``|x| ≥ 2.5``
    (the cart leaves the fixed camera's view); episodes last 240 steps (4 s).
    """

    name = "cartpole_swingup"
    episode_length = 240
    camera = "view"
    cart_limit = 2.5
    penalty_substeps = 4  # nothing touches the floor and no joint is limited: no stiff forces
    # Our own model: its joints have only their MJCF damping (no dflex-style damping on top).
    penalty_contact = PenaltyContact(ke=2e4, kd=1e3, kf=1e3, mu=0.9, limit_kd=0.0)

    def build_spec(self) -> mujoco.MjSpec:
        return load_asset_spec("cartpole.xml")

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        angle_key, vel_key = jax.random.split(key)
        angle = jnp.pi + jax.random.uniform(angle_key, (), minval=-jnp.pi / 12, maxval=jnp.pi / 12)
        qpos = jnp.stack([jnp.zeros_like(angle), angle])
        qvel = jax.random.uniform(vel_key, (2,), minval=-0.05, maxval=0.05)
        return qpos, qvel

    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        x, angle = data.qpos[0], data.qpos[1]
        x_dot, angle_dot = data.qvel[0], data.qvel[1]
        return jnp.stack([x, x_dot, jnp.sin(angle), jnp.cos(angle), angle_dot])

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        x, angle = data.qpos[0], data.qpos[1]
        x_dot, angle_dot = data.qvel[0], data.qvel[1]
        theta = jnp.arctan2(jnp.sin(angle), jnp.cos(angle))  # wrapped to (-π, π], 0 = upright
        return 10.0 - theta**2 - 0.1 * angle_dot**2 - 0.05 * x**2 - 0.1 * x_dot**2

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return jnp.abs(data.qpos[0]) >= self.cart_limit


class CartpoleBalance(CartpoleSwingup):
    """DMC's balance variant: the pole starts upright (±3°, velocities ±0.05) and must stay up.

    Same model, reward, observation, termination and 240-step episodes as the swing-up, so its
    returns read the same way (at most 2400). A fast sanity task: under random actions the pole
    falls within about a second.
    """

    name = "cartpole_balance"
    initial_angle = jnp.pi / 60

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        angle_key, vel_key = jax.random.split(key)
        angle = jax.random.uniform(angle_key, (), minval=-self.initial_angle, maxval=self.initial_angle)
        qpos = jnp.stack([jnp.zeros_like(angle), angle])
        qvel = jax.random.uniform(vel_key, (2,), minval=-0.05, maxval=0.05)
        return qpos, qvel

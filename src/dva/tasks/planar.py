"""The planar (2-D, side-view) runners: Hopper and Half-Cheetah.

Both models have a root of two slides and a hinge, so ``qpos = [x, z, pitch, joints…]`` with
``z = 0`` at the start pose, and ``qvel = [vx, vz, ω, joint velocities…]``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from dva.tasks.base import Task, load_asset_spec
from dva.tasks.physics import PenaltyContact


class PlanarRunner(Task):
    """Shared state observation and reset noise of the planar robots.

    Observation (SHAC's): ``qpos[1:]`` (height, pitch, joint angles) and ``qvel`` — 11-D for the
    Hopper, 17-D for the Cheetah. Reset (the reference code's): uniform noise ±``reset_noise`` on
    every coordinate but x, ±``reset_velocity`` on every velocity.
    """

    asset: str
    reset_noise = 0.05
    reset_velocity = 0.05

    def build_spec(self) -> mujoco.MjSpec:
        return load_asset_spec(self.asset)

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        pos_key, vel_key = jax.random.split(key)
        nq, nv = self.mj_model.nq, self.mj_model.nv
        noise = jax.random.uniform(pos_key, (nq,), minval=-self.reset_noise, maxval=self.reset_noise)
        qpos = self.qpos0() + noise.at[0].set(0.0)
        qvel = jax.random.uniform(vel_key, (nv,), minval=-self.reset_velocity, maxval=self.reset_velocity)
        return qpos, qvel

    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        return jnp.concatenate([data.qpos[1:], data.qvel])


class Hopper(PlanarRunner):
    """One-legged hopper (3 actuated joints).

    Reward follows the authors' code (SHAC's hopper), which produced the paper's results, rather
    than appendix E's formula: ``R = v_x + R_height + (1 − θ²/(π/6)²) − 0.1‖a‖²`` with
    ``Δh = clip(z + 0.3, −1, 0.3)``, ``R_height = −200 Δh²`` if ``Δh < 0`` else ``Δh``,
    θ the torso pitch and z the height relative to the start. Terminates when ``z < −0.45``.
    """

    name = "hopper"
    asset = "hopper.xml"
    armature = 1.0  # dflex's, root included: a 5× smaller 32-step gradient than the MJCF's 0.5
    termination_height = -0.45
    height_tolerance = 0.15
    max_pitch = jnp.pi / 6

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        height, pitch, vx = data.qpos[1], data.qpos[2], data.qvel[0]
        height_reward = soft_height_reward(height - (self.termination_height + self.height_tolerance), 0.3)
        angle_reward = 1.0 - pitch**2 / self.max_pitch**2
        return vx + height_reward + angle_reward - 0.1 * jnp.sum(action**2)

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return data.qpos[1] < self.termination_height


class Cheetah(PlanarRunner):
    """Half-Cheetah (6 actuated joints): ``R = v_x − 0.1‖a‖²``, as SHAC's cheetah.

    The reference asset's joint ranges are kept as they are: the front foot's is −3.1…−0.3 rad,
    so at q = 0 it starts 0.3 rad past its limit and the limit spring folds it at once. The torso
    starts 0.8 m above the floor. Never terminates; episodes run 1000 steps.
    """

    name = "cheetah"
    asset = "cheetah.xml"
    contact_solref = (0.05, 1.0)
    penalty_contact = PenaltyContact(ke=2e4, kd=1e3, kf=1e3, mu=1.0)
    armature = 0.1  # dflex's, root included
    reset_noise = 0.1
    reset_velocity = 0.25

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        return data.qvel[0] - 0.1 * jnp.sum(action**2)

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return jnp.zeros((), bool)


def soft_height_reward(height_diff: jax.Array, upper: float, scale: float = 1.0) -> jax.Array:
    """SHAC's height term: ``Δh = clip(height_diff, −1, upper)``; ``−200 Δh²`` below 0, else
    ``scale · Δh``."""
    clipped = jnp.clip(height_diff, -1.0, upper)
    return jnp.where(clipped < 0.0, -200.0 * clipped**2, scale * clipped)

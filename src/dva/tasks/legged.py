"""The 3-D legged robots on a free joint: Ant, Humanoid and the quadruped.

``qpos = [xyz, quat (w, x, y, z), joints…]``, ``qvel = [world linear velocity, local angular
velocity, joint velocities…]``. All run along +x.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.typing import ArrayLike
from mujoco import mjx

from dva.tasks.base import Task, load_asset_spec
from dva.tasks.physics import PenaltyContact
from dva.tasks.planar import soft_height_reward


def rotate(quat: jax.Array, vec: ArrayLike) -> jax.Array:
    """Rotate ``vec`` by the unit quaternion ``quat`` (w, x, y, z)."""
    w, u, vec = quat[0], quat[1:], jnp.asarray(vec)
    return vec + 2.0 * jnp.cross(u, jnp.cross(u, vec) + w * vec)


def quat_multiply(a: jax.Array, b: jax.Array) -> jax.Array:
    """The Hamilton product ``a ⊗ b`` of two (w, x, y, z) quaternions."""
    return jnp.concatenate(
        [a[:1] * b[:1] - jnp.dot(a[1:], b[1:]), a[0] * b[1:] + b[0] * a[1:] + jnp.cross(a[1:], b[1:])]
    )


class LeggedRunner(Task):
    """Shared observation, reset and reward terms of the 3-D robots.

    Observation (SHAC's layout): torso height (1), torso quaternion (4), linear velocity (3) and
    angular velocity (3) in the world frame, joint angles, joint velocities ×
    ``joint_velocity_scale``, up projection (1), heading projection (1), previous action — 37-D for
    the Ant, 76-D for the Humanoid. ``R_up`` = z-component of the torso's up axis, ``R_heading`` =
    its forward axis projected on the horizontal direction to the target, a point
    ``target_distance`` metres down +x from the start.

    Reset (the reference code's): the start pose with its root moved by U(±0.1) m, turned by up
    to ``reset_rotation`` about a random axis, joints U(±``reset_noise``) rad and every velocity
    U(±``reset_velocity``).
    """

    termination_height: float
    joint_velocity_scale = 0.1
    reset_noise = 0.2
    reset_position = 0.1
    reset_rotation = jnp.pi / 24
    reset_velocity = 0.25
    target_distance = 1e4
    forward_axis = np.array([1.0, 0.0, 0.0])  # torso axis along +x (NumPy: no JAX work on import)
    up_axis = np.array([0.0, 0.0, 1.0])

    def initial_pose(self) -> jax.Array:
        """Joint angles of the start pose (default: the model's reference pose)."""
        return self.qpos0()[7:]

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        pos_key, angle_key, axis_key, joint_key, vel_key = jax.random.split(key, 5)
        nj = self.mj_model.nq - 7
        position = self.qpos0()[:3] + jax.random.uniform(
            pos_key, (3,), minval=-self.reset_position, maxval=self.reset_position
        )
        half_angle = 0.5 * jax.random.uniform(angle_key, (), minval=-self.reset_rotation, maxval=self.reset_rotation)
        axis = jax.random.uniform(axis_key, (3,), minval=-0.5, maxval=0.5)
        turn = jnp.concatenate([jnp.cos(half_angle)[None], jnp.sin(half_angle) * axis / jnp.linalg.norm(axis)])
        joints = self.initial_pose() + jax.random.uniform(
            joint_key, (nj,), minval=-self.reset_noise, maxval=self.reset_noise
        )
        qpos = jnp.concatenate([position, quat_multiply(self.qpos0()[3:7], turn), joints])
        qvel = jax.random.uniform(vel_key, (self.mj_model.nv,), minval=-self.reset_velocity, maxval=self.reset_velocity)
        return qpos, qvel

    def projections(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """(up projection, heading projection) of the torso, both in [−1, 1]."""
        quat = data.qpos[3:7] / jnp.linalg.norm(data.qpos[3:7])
        up = rotate(quat, self.up_axis)[2]
        to_target = jnp.array([self.target_distance, 0.0]) + self.qpos0()[:2] - data.qpos[:2]
        heading = jnp.dot(rotate(quat, self.forward_axis)[:2], to_target / jnp.linalg.norm(to_target))
        return up, heading

    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        quat = data.qpos[3:7] / jnp.linalg.norm(data.qpos[3:7])
        return jnp.concatenate(
            [
                data.qpos[2:3],
                data.qpos[3:7],
                data.qvel[0:3],
                rotate(quat, data.qvel[3:6]),
                data.qpos[7:],
                self.joint_velocity_scale * data.qvel[6:],
                up[None],
                heading[None],
                action,
            ]
        )

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return data.qpos[2] < self.termination_height


class Ant(LeggedRunner):
    """Four-legged ant (8 actuated joints), as the paper's simulator builds it: density 1000
    (182 kg), 200 N·m motors, joint damping 1 (+ 10), armature 0.05 on every joint, the root's
    included. ``R = v_x + 0.1 R_up + R_heading + (z − 0.27)``.

    Terminates when the torso is below 0.27 m. Start pose: ankles at ±1 rad (legs down).
    """

    name = "ant"
    termination_height = 0.27
    mujoco_substeps = 8
    contact_solref = (0.05, 1.0)
    penalty_contact = PenaltyContact(ke=4e4, kd=1e4, kf=3e3, mu=0.75)
    armature = 0.05

    def build_spec(self) -> mujoco.MjSpec:
        return load_asset_spec("ant.xml")

    def initial_pose(self) -> jax.Array:
        return jnp.array([0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0])

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        return data.qvel[0] + 0.1 * up + heading + (data.qpos[2] - self.termination_height)


class Humanoid(LeggedRunner):
    """Humanoid (21 actuated joints) as the paper's simulator builds it (``assets/humanoid.xml``):
    48 substeps, the joints' own springs, damping and armature, density 1000 (40.8 kg), motors of
    35–210 N·m, contacts ke 2e4, kd 5e3, kf 1e3, mu 0.75 on every geom.

    ``R = v_x + 0.1 R_up + R_heading + R_height − 0.002‖a‖²`` with ``Δh = clip(z − 0.84, −1, 0.1)``
    and ``R_height = −200 Δh²`` if ``Δh < 0`` else ``10 Δh``; the target is 200 m down +x.
    Terminates when the torso is below 0.74 m.
    """

    name = "humanoid"
    termination_height = 0.74
    penalty_substeps = 48
    contact_solref = (0.05, 1.0)
    penalty_contact = PenaltyContact(ke=2e4, kd=5e3, kf=1e3, mu=0.75)
    height_tolerance = 0.1
    target_distance = 200.0

    def build_spec(self) -> mujoco.MjSpec:
        spec = load_asset_spec("humanoid.xml")
        spec.body("torso").add_camera(
            name="track",
            mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
            pos=[0.0, -3.6, 0.3],
            xyaxes=[1, 0, 0, 0, 0.2, 1],
            fovy=50,
        )
        return spec

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        height_diff = data.qpos[2] - (self.termination_height + self.height_tolerance)
        height_reward = soft_height_reward(height_diff, self.height_tolerance, scale=10.0)
        return data.qvel[0] + 0.1 * up + heading + height_reward - 0.002 * jnp.sum(action**2)


class Quadruped(LeggedRunner):
    """Anymal-like quadruped (12 actuated joints), the paper's "more robots" running task.

    ``R = v_x + 0.1 R_up + R_heading + R_height − 0.005‖a‖²`` with ``Δh = clip(z − 0.4, −1, 0.05)``
    and ``R_height = −200 Δh²`` if ``Δh < 0`` else ``10 Δh`` (Humanoid's shape, around its
    standing height of 0.45 m). Terminates when the torso is below 0.25 m (belly on the floor).
    The camera looks from the side at the torso's height, so the far legs hide behind the near
    ones (partially observable, as in the paper).
    """

    name = "quadruped"
    termination_height = 0.25
    # Our own robot, not the paper's: it keeps the reset and observation it learns with.
    joint_velocity_scale = 1.0
    reset_noise = 0.1
    reset_position = 0.0
    reset_rotation = 0.0
    reset_velocity = 0.05
    armature = 0.1  # every joint, the root's too: 2× smaller 32-step gradient growth than the legs' alone
    target_height = 0.4
    height_tolerance = 0.05

    def build_spec(self) -> mujoco.MjSpec:
        return load_asset_spec("quadruped.xml")

    def initial_pose(self) -> jax.Array:
        return jnp.tile(jnp.array([0.0, 0.6, -1.2]), 4)

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        height_reward = soft_height_reward(data.qpos[2] - self.target_height, self.height_tolerance, scale=10.0)
        return data.qvel[0] + 0.1 * up + heading + height_reward - 0.005 * jnp.sum(action**2)

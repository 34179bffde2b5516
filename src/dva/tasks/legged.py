"""The 3-D legged robots on a free joint: Ant and Humanoid.

``qpos = [xyz, quat (w, x, y, z), joints…]``, ``qvel = [world linear velocity, local angular
velocity, joint velocities…]``. Both run along +x.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from dva.tasks.base import Task, load_asset_spec
from dva.tasks.physics import PenaltyContact
from dva.tasks.planar import soft_height_reward


def rotate(quat: jax.Array, vec: jax.Array) -> jax.Array:
    """Rotate ``vec`` by the unit quaternion ``quat`` (w, x, y, z)."""
    w, u = quat[0], quat[1:]
    return vec + 2.0 * jnp.cross(u, jnp.cross(u, vec) + w * vec)


class LeggedRunner(Task):
    """Shared observation, reset and reward terms of the 3-D robots.

    Observation (SHAC's layout): torso height (1), torso quaternion (4), linear velocity (3),
    angular velocity (3), joint angles, joint velocities × ``joint_velocity_scale``, up
    projection (1), heading projection (1), previous action — 37-D for the Ant, 76-D for the
    Humanoid. ``R_up`` = z-component of the torso's up axis, ``R_heading`` = x-component of its
    forward axis (the target direction is +x).
    """

    termination_height: float
    joint_velocity_scale = 1.0
    reset_noise = 0.1
    forward_axis = jnp.array([1.0, 0.0, 0.0])  # torso axis that should point along +x
    up_axis = jnp.array([0.0, 0.0, 1.0])

    def initial_pose(self) -> jax.Array:
        """Joint angles of the start pose (default: the model's reference pose)."""
        return self.qpos0()[7:]

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        pos_key, vel_key = jax.random.split(key)
        nj = self.mj_model.nq - 7
        qpos = self.qpos0().at[7:].set(self.initial_pose())
        qpos = qpos.at[7:].add(jax.random.uniform(pos_key, (nj,), minval=-self.reset_noise, maxval=self.reset_noise))
        qvel = 0.5 * self.reset_noise * jax.random.uniform(vel_key, (self.mj_model.nv,), minval=-1.0, maxval=1.0)
        return qpos, qvel

    def projections(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """(up projection, heading projection) of the torso, both in [−1, 1]."""
        quat = data.qpos[3:7] / jnp.linalg.norm(data.qpos[3:7])
        up = rotate(quat, self.up_axis)[2]
        heading = rotate(quat, self.forward_axis)[0]
        return up, heading

    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        return jnp.concatenate([
            data.qpos[2:3], data.qpos[3:7], data.qvel[0:3], data.qvel[3:6],
            data.qpos[7:], self.joint_velocity_scale * data.qvel[6:],
            up[None], heading[None], action,
        ])

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return data.qpos[2] < self.termination_height


class Ant(LeggedRunner):
    """Four-legged ant (8 actuated joints): ``R = v_x + 0.1 R_up + R_heading + (z − 0.27)``.

    Terminates when the torso is below 0.27 m. Start pose: ankles at ±1 rad (legs down).
    """

    name = "ant"
    termination_height = 0.27
    mujoco_substeps = 8
    contact_solref = (0.05, 1.0)
    # Spec §7's ant weighs ≈ 180 kg (density 1000) with 200 N·m motors; ours is Gym's 0.9 kg with
    # 30 N·m motors, so its stiffnesses are §7's scaled by the mass (÷100) and, for the limits,
    # by the torque: the same settling depth and limit give under full torque (≈ 0.2 rad).
    penalty_contact = PenaltyContact(ke=4e2, kd=1e2, kf=30.0, mu=0.75, limit_ke=150.0, limit_kd=1.5)
    armature = 0.05  # §7's, on every joint (the root's too: 3× smaller 32-step gradient growth)

    def build_spec(self) -> mujoco.MjSpec:
        return load_asset_spec("ant.xml")

    def initial_pose(self) -> jax.Array:
        return jnp.array([0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0])

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        up, heading = self.projections(data)
        return data.qvel[0] + 0.1 * up + heading + (data.qpos[2] - self.termination_height)


class Humanoid(LeggedRunner):
    """Humanoid (21 actuated joints), MuJoCo's humanoid shipped with ``mujoco.mjx``, edited here.

    Reward follows the authors' code (SHAC's humanoid) rather than appendix E:
    ``R = v_x + 0.1 R_up + R_heading + R_height − 0.002‖a‖²`` with ``Δh = clip(z − 0.84, −1, 0.1)``
    and ``R_height = −200 Δh²`` if ``Δh < 0`` else ``10 Δh``. Terminates when the torso is below
    0.74 m. Joint velocities enter the observation × 0.1, as in SHAC.

    Against SHAC's humanoid (spec §7's simulator): our motors are MuJoCo's gears, 0.2 × SHAC's
    motor strengths where SHAC applies 0.35 ×, and the contacts are the default penalty ones
    (kd 1e3, mu 0.9; SHAC's 5e3, 0.75). SHAC's torque makes the 32-step gradient grow less
    (h=32/h=1: 120 vs 182) but learns no faster with the clipped gradient and still explodes with
    the exact one (benchmarks/RESULTS.md, "Humanoid: SHAC's motor strength and contacts").
    """

    name = "humanoid"
    termination_height = 0.74
    contact_solref = (0.05, 1.0)
    height_tolerance = 0.1
    joint_velocity_scale = 0.1

    def build_spec(self) -> mujoco.MjSpec:
        path = Path(mjx.__file__).parent / "test_data" / "humanoid" / "humanoid.xml"
        if not path.exists():
            raise FileNotFoundError(f"the humanoid model ships with mujoco-mjx; not found at {path}")
        spec = mujoco.MjSpec.from_file(str(path))
        # Our scene replaces the model's floor, lights and cameras (pairs find the new floor by name).
        for geom in list(spec.geoms):
            if geom.name == "floor":
                spec.delete(geom)
        for light in list(spec.lights):
            spec.delete(light)
        for camera in list(spec.cameras):
            spec.delete(camera)
        for material in list(spec.materials):
            if material.name == "grid":
                spec.delete(material)
        for texture in list(spec.textures):
            spec.delete(texture)
        for material in spec.materials:
            material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = ""
            material.rgba = [0.9, 0.5, 0.2, 1.0]
        torso = spec.body("torso")
        torso.add_camera(name="track", mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
                         pos=[0.0, -3.6, 0.3], xyaxes=[1, 0, 0, 0, 0.2, 1], fovy=50)
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

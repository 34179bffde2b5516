"""The contact models of ``dva.tasks.physics``: penalty forces against hand-computed values,
no energy injection when the robots fall, and the contact points each robot has."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from dva.tasks import make_task
from dva.tasks.physics import PenaltyContact, contact_state, floor_contact_points, mechanical_energy, penalty_forces

LEGGED = ["hopper", "cheetah", "ant", "humanoid", "quadruped"]


def test_contact_points_are_capsule_end_spheres():
    task = make_task("hopper")
    points = task.contact_points
    # torso, thigh, leg, foot capsules: two end spheres each.
    assert len(points.body) == 8
    foot = mujoco.mj_name2id(task.mj_model, mujoco.mjtObj.mjOBJ_BODY, "foot")
    foot_points = points.local[points.body == foot]
    np.testing.assert_allclose(sorted(foot_points[:, 0]), [-0.13, 0.26], atol=1e-6)
    np.testing.assert_allclose(points.radius[points.body == foot], 0.06)
    # The Humanoid touches the floor with its feet only (its model's explicit pairs).
    humanoid = make_task("humanoid")
    names = {mujoco.mj_id2name(humanoid.mj_model, mujoco.mjtObj.mjOBJ_BODY, b) for b in humanoid.contact_points.body}
    assert names == {"foot_left", "foot_right"}


def test_penalty_force_on_a_sliding_sphere_hand_computed():
    """A free 1-kg sphere 1 cm into the floor, sinking at 0.5 m/s and sliding at 2 m/s along x."""
    spec = mujoco.MjSpec()
    floor = spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1])
    floor.contype, floor.conaffinity = 0, 1
    ball = spec.worldbody.add_body(name="ball", pos=[0, 0, 0.09])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0], mass=1.0)
    model = spec.compile()
    points = floor_contact_points(model)
    params = PenaltyContact(ke=2e4, kd=1e3, kf=1e3, mu=0.9)
    mx = mjx.put_model(model)
    data = mjx.make_data(mx).replace(qvel=jnp.array([2.0, 0.0, -0.5, 0.0, 0.0, 0.0]))

    @jax.jit  # one compile: op by op, MJX's kinematics cost ≈ 500 small ones (half a minute)
    def depth_and_forces(data):
        data = mjx.fwd_velocity(mx, mjx.fwd_position(mx, data))
        no_limits = (np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int))
        return contact_state(mx, data, points)[1], penalty_forces(mx, data, points, params, *no_limits)

    depth, qfrc = depth_and_forces(data)
    assert float(depth[0]) == pytest.approx(0.01, abs=1e-6)
    normal = 2e4 * 0.01 + 1e3 * 0.01 * 0.5  # spring + damping while sinking
    friction = -min(1e3 * 2.0, 0.9 * 2e4 * 0.01)  # Coulomb-capped: 180 N against the sliding
    np.testing.assert_allclose(qfrc[:3], [friction, 0.0, normal], rtol=1e-4)
    # The friction acts at the contact point, 0.1 m below the centre: r × f = (0, 0, −0.1) × (f, 0, n).
    np.testing.assert_allclose(qfrc[3:], [0.0, -0.1 * friction, 0.0], rtol=1e-4, atol=1e-4)


def test_joint_limit_spring_and_damping():
    task = make_task("hopper")
    dofs, ranges, qpos_index = task.limits
    foot = int(np.flatnonzero(np.isclose(ranges[:, 1], np.deg2rad(45)))[0])  # the foot: ±45°
    qpos = np.array(task.mj_model.qpos0)
    qpos[1] = 5.0  # in the air: no contact forces
    qpos[qpos_index[foot]] = ranges[foot, 1] + 0.1  # 0.1 rad past its upper limit …
    qvel = np.zeros(task.mj_model.nv)
    qvel[dofs[foot]] = 2.0  # … still turning outwards
    data = task._data0.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))

    @jax.jit  # one compile, not one per operation
    def forces(data):
        data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
        return penalty_forces(task.model, data, task.contact_points, task.penalty_contact, *task.limits)

    qfrc = np.asarray(forces(data))
    params = task.penalty_contact
    assert qfrc[dofs[foot]] == pytest.approx(-params.limit_ke * 0.1 - params.limit_kd * 2.0, rel=1e-4)
    np.testing.assert_allclose(np.delete(qfrc, dofs[foot]), 0.0, atol=1e-6)  # nothing else pushes


@pytest.mark.parametrize("name", LEGGED)
def test_falling_robot_never_gains_energy(name):
    """Zero action, 2.5 s from the start pose: the robot lands, topples, settles. Its mechanical
    energy may only fall, up to the integrator's O(dt) wobble (0.5 % of the energy it starts with)."""
    task = make_task(name)
    state = task.reset(jax.random.PRNGKey(1), 2)

    # One compiled function, the start's energy included: evaluated op by op outside jit,
    # mechanical_energy alone took 40 s on the Humanoid (every primitive compiled on its own).
    @jax.jit
    def energies(data):
        energy = jax.vmap(lambda x: mechanical_energy(task, x))

        def step(d, _):
            d = jax.vmap(task.physics_step)(d, jnp.zeros((2, task.action_dim)))
            return d, energy(d)
        return jnp.concatenate([energy(data)[None], jax.lax.scan(step, data, None, length=150)[1]])

    energy = np.asarray(energies(state.data))
    initial = energy[0]
    assert np.all(np.isfinite(energy))
    rise = energy[1:] - np.minimum.accumulate(energy, axis=0)[:-1]
    assert np.all(rise <= 0.005 * initial), f"{name}: energy rose by {rise.max():.3g} J (start {initial})"
    assert np.all(energy[-1] < initial - 1.0)  # it did land and lose energy (contacts dissipate)

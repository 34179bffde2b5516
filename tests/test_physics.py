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
from dva.tasks.physics import (
    PenaltyContact,
    bodies_of,
    contact_state,
    floor_contact_points,
    joint_forces,
    mechanical_energy,
    penalty_forces,
    penalty_step,
    point_forces_to_joints,
    point_velocities,
)

LEGGED = ["hopper", "cheetah", "ant", "humanoid", "quadruped"]


def mjx_penalty_forces(task, data: mjx.Data) -> jax.Array:
    """The task's penalty forces (nv,) with MJX computing the kinematics and velocities they read."""
    data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
    bodies = bodies_of(task.model, data)
    return penalty_forces(data.qpos, data.qvel, bodies, task.contact_points, task.penalty_contact, task.joints)


def test_contact_points_are_capsule_end_spheres():
    task = make_task("hopper")
    points = task.contact_points
    # torso, thigh, leg, foot capsules: two end spheres each.
    assert len(points.body) == 8
    foot = mujoco.mj_name2id(task.mj_model, mujoco.mjtObj.mjOBJ_BODY, "foot")
    foot_points = points.local[points.body == foot]
    np.testing.assert_allclose(sorted(foot_points[:, 0]), [-0.13, 0.26], atol=1e-6)
    np.testing.assert_allclose(points.radius[points.body == foot], 0.06)
    # Every geom of the Humanoid touches the floor, as in the paper's simulator: 16 capsules' end
    # spheres and 3 spheres (head, hands), on all 13 bodies.
    humanoid = make_task("humanoid")
    assert len(humanoid.contact_points.body) == 2 * 16 + 3
    assert len(set(humanoid.contact_points.body)) == humanoid.mj_model.nbody - 1


def test_point_velocities_and_forces_match_mujocos_jacobians():
    """The contact points' velocities and their forces' generalised forces, computed from the
    bodies' spatial velocities and the dofs' motion axes, equal J·q̇ and Σ Jᵀf with MJX's own
    Jacobian of every point (Humanoid, a random pose and velocity, random forces)."""
    task = make_task("humanoid")
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    qpos, qvel = task.initial_state(keys[0])
    data = task._data0.replace(qpos=qpos, qvel=qvel + jax.random.normal(keys[1], qvel.shape))
    points = task.contact_points
    force = jax.random.normal(keys[2], (len(points.body), 3))

    @jax.jit
    def both(data):
        data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
        bodies = bodies_of(task.model, data)
        position, _ = contact_state(bodies, points)
        jacobian = jax.vmap(lambda p, b: mjx.jac(task.model, data, p, b)[0])(position, jnp.asarray(points.body))
        ours = (
            point_velocities(bodies, points, position),
            point_forces_to_joints(bodies, points, position, force),
        )
        return ours, (jnp.einsum("pvi,v->pi", jacobian, data.qvel), jnp.einsum("pvi,pi->v", jacobian, force))

    (velocity, qfrc), (velocity_ref, qfrc_ref) = both(data)
    np.testing.assert_allclose(velocity, velocity_ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(qfrc, qfrc_ref, rtol=1e-4, atol=1e-4)
    assert float(jnp.abs(qfrc_ref).max()) > 1.0


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
        no_joints = joint_forces(model, params.limit_kd)  # a free joint only: no joint forces
        bodies = bodies_of(mx, data)
        return contact_state(bodies, points)[1], penalty_forces(data.qpos, data.qvel, bodies, points, params, no_joints)

    depth, qfrc = depth_and_forces(data)
    assert float(depth[0]) == pytest.approx(0.01, abs=1e-6)
    normal = 2e4 * 0.01 + 1e3 * 0.01 * 0.5  # spring + damping while sinking
    friction = -min(1e3 * 2.0, 0.9 * 2e4 * 0.01)  # Coulomb-capped: 180 N against the sliding
    np.testing.assert_allclose(qfrc[:3], [friction, 0.0, normal], rtol=1e-4)
    # The friction acts at the contact point, 0.1 m below the centre: r × f = (0, 0, −0.1) × (f, 0, n).
    np.testing.assert_allclose(qfrc[3:], [0.0, -0.1 * friction, 0.0], rtol=1e-4, atol=1e-4)


def test_joint_limit_spring_and_damping():
    task = make_task("hopper")
    joints = task.joints
    foot = int(np.flatnonzero(np.isclose(joints.limit_range[:, 1], np.deg2rad(45)))[0])  # the foot: ±45°
    foot_dof = joints.limit_dof[foot]
    qpos = np.array(task.mj_model.qpos0)
    qpos[1] = 5.0  # in the air: no contact forces
    qpos[joints.limit_qpos[foot]] = joints.limit_range[foot, 1] + 0.1  # 0.1 rad past its upper limit …
    qvel = np.zeros(task.mj_model.nv)
    qvel[foot_dof] = 2.0  # … still turning outwards
    data = task._data0.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))

    @jax.jit  # one compile, not one per operation
    def forces(data):
        data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
        bodies = bodies_of(task.model, data)
        return penalty_forces(data.qpos, data.qvel, bodies, task.contact_points, task.penalty_contact, joints)

    qfrc = np.asarray(forces(data))
    # The hopper's joints: damping 2 of their own + 10 (dflex's limit_kd, on at all times).
    assert qfrc[foot_dof] == pytest.approx(-1e3 * 0.1 - (2.0 + 10.0) * 2.0, rel=1e-4)
    np.testing.assert_allclose(np.delete(qfrc, foot_dof), 0.0, atol=1e-6)  # nothing else pushes


def test_joint_springs_and_always_on_damping_hand_computed():
    """Humanoid in the air, inside every joint range: each joint feels its own spring towards 0
    and its own damping plus 10 N·m·s/rad (dflex's rule), hand-computed from the MJCF's numbers."""
    task = make_task("humanoid")
    names = ["abdomen_z", "right_knee", "left_elbow"]
    # (stiffness, damping) from assets/humanoid.xml: the abdomen's class, the default, the small joints'.
    expected = {"abdomen_z": (20.0, 5.0 + 10.0), "right_knee": (5.0, 0.1 + 10.0), "left_elbow": (2.0, 1.0 + 10.0)}
    qpos = np.array(task.mj_model.qpos0)
    qpos[2] = 5.0
    qvel = np.zeros(task.mj_model.nv)
    for name, (angle, speed) in zip(names, [(0.3, 1.5), (-0.5, -2.0), (0.2, 0.7)]):
        joint = task.mj_model.joint(name)
        qpos[joint.qposadr[0]], qvel[joint.dofadr[0]] = angle, speed
    data = task._data0.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
    qfrc = np.asarray(jax.jit(lambda d: mjx_penalty_forces(task, d))(data))
    for name, (angle, speed) in zip(names, [(0.3, 1.5), (-0.5, -2.0), (0.2, 0.7)]):
        stiffness, damping = expected[name]
        assert qfrc[task.mj_model.joint(name).dofadr[0]] == pytest.approx(
            -stiffness * angle - damping * speed, rel=1e-5
        )
    others = np.setdiff1d(np.arange(task.mj_model.nv), [task.mj_model.joint(n).dofadr[0] for n in names])
    np.testing.assert_allclose(qfrc[others], 0.0, atol=1e-5)


def test_one_substep_equals_mujocos_own_step():
    """With one substep the mass matrix factored once per control step is the current one, so the
    penalty step must equal MJX's full pipeline (position, velocity, actuation, acceleration,
    Euler) under the same explicit forces — in contact, float64."""
    task_class = type(make_task("hopper"))  # outside float64: make_task keeps the task it builds
    with jax.enable_x64(True):
        task = task_class()
        state = task.reset(jax.random.PRNGKey(2), 1)
        data = jax.tree.map(lambda x: x[0], state.data)
        data = data.replace(qpos=data.qpos.at[1].set(-0.1), ctrl=jnp.linspace(-1.0, 1.0, task.action_dim))
        forces = lambda d: mjx_penalty_forces(task, d)

        def reference(data):
            data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
            data = mjx.fwd_acceleration(
                task.model, mjx.fwd_actuation(task.model, data.replace(qfrc_applied=forces(data)))
            )
            return mjx.euler(task.model, data.replace(qacc=data.qacc_smooth))

        tree_forces = lambda qpos, qvel, bodies: penalty_forces(
            qpos, qvel, bodies, task.contact_points, task.penalty_contact, task.joints
        )
        ours = jax.jit(lambda d: penalty_step(task.model, task.tree, d, 1, tree_forces))(data)
        theirs = jax.jit(reference)(data)
        assert float(jnp.abs(forces(mjx.fwd_position(task.model, data))).max()) > 100.0  # feet in the floor
        np.testing.assert_allclose(ours.qvel, theirs.qvel, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(ours.qpos, theirs.qpos, rtol=1e-12, atol=1e-12)


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

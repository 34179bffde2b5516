"""The level-batched rigid-body pass of ``dva.tasks.tree`` against MJX, its reference: every output
in float64 on every robot (the mass matrix against MuJoCo's own), and the reverse pass of whole
penalty steps (in contact, joint limits and springs on) against ``jax.vjp`` of the same steps
built from MJX's own functions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import smooth as mjx_smooth

from dva.errors import DvaUsageError
from dva.tasks import BUILTIN_TASKS, make_task
from dva.tasks.physics import bodies_of, penalty_forces
from dva.tasks.tree import KinematicTree, forward, integrate, mass_matrix

ROBOTS = [name for name in BUILTIN_TASKS if name != "cartpole_balance"]  # balance shares swing-up's model


def random_state(task, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A pose 0.3 rad (or m) from the reference in every coordinate, a random velocity."""
    rng = np.random.default_rng(seed)
    qpos = np.array(task.mj_model.qpos0, float) + 0.3 * rng.normal(size=task.mj_model.nq)
    return qpos, rng.normal(size=task.mj_model.nv)


def mjx_forward(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    return mjx.rne(model, mjx.com_vel(model, mjx.com_pos(model, mjx.kinematics(model, data))))


@pytest.mark.parametrize("name", ROBOTS)
def test_forward_equals_mjx_in_float64(name):
    task_class = type(make_task(name))  # outside float64: make_task keeps the task it builds
    with jax.enable_x64(True):
        task = task_class()
        qpos, qvel = random_state(task, 0)
        data = mjx_forward(task.model, task._data0.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel)))
        normalised, bodies, bias = jax.jit(lambda q, v: forward(task.tree, q, v))(qpos, qvel)
        reference = bodies_of(task.model, data)
        np.testing.assert_allclose(normalised, data.qpos, atol=1e-12)
        for field in ("xpos", "xmat", "cvel", "cdof"):
            np.testing.assert_allclose(getattr(bodies, field), getattr(reference, field), atol=1e-12, err_msg=field)
        np.testing.assert_allclose(bodies.root_com[1:], reference.root_com[1:], atol=1e-12)
        np.testing.assert_allclose(bias, data.qfrc_bias, rtol=1e-12, atol=1e-12 * np.abs(data.qfrc_bias).max())
        assert np.abs(data.qfrc_bias).max() > 1e-2  # gravity and Coriolis forces are there to compare
        # The mass matrix, armature included, against MuJoCo's own (mj_fullM) at the same pose.
        mj_data = mujoco.MjData(task.mj_model)
        mj_data.qpos[:] = np.asarray(data.qpos)
        mujoco.mj_forward(task.mj_model, mj_data)
        full = np.zeros((task.mj_model.nv, task.mj_model.nv))
        mujoco.mj_fullM(task.mj_model, mj_data, full)
        ours = jax.jit(lambda q: mass_matrix(task.tree, q))(qpos)
        np.testing.assert_allclose(ours, full, atol=1e-12 * np.abs(full).max())
        # MJX's Euler position update, free joints' quaternions included.
        dt = 0.01
        advanced = mjx.euler(
            task.model.replace(opt=task.model.opt.replace(timestep=dt)), data.replace(qacc=0 * data.qvel)
        )
        np.testing.assert_allclose(integrate(task.tree, data.qpos, data.qvel, dt), advanced.qpos, atol=1e-12)


@pytest.mark.parametrize("name", ["hopper", "humanoid"])  # slides and limits; a free joint and springs
def test_reverse_pass_equals_the_mjx_reference(name):
    """Three substeps in contact with joint limits and springs active: the step and its VJP (state
    and action, a random cotangent) equal the same step built from MJX's kinematics, velocities,
    bias forces, back-substitution and Euler step, to 1e-9 in float64."""
    task_class = type(make_task(name))  # outside float64: make_task keeps the task it builds
    with jax.enable_x64(True):
        task = task_class()
        qpos, qvel = random_state(task, 1)
        qpos[1 if name == "hopper" else 2] -= {"hopper": 0.3, "humanoid": 1.0}[name]  # into the floor
        data = task._data0.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
        action = jnp.linspace(-1.0, 1.0, task.action_dim)
        model, points, params, joints = task.model, task.contact_points, task.penalty_contact, task.joints

        def reference_step(data):
            mass = mjx.factor_m(model, mjx.crb(model, mjx.com_pos(model, mjx.kinematics(model, data))))
            actuator = mjx.fwd_actuation(model, mjx.transmission(model, mass)).qfrc_actuator

            def substep(_, state):  # a loop, not unrolled: MJX's reverse pass compiles once
                d = mjx_forward(model, data.replace(qpos=state[0], qvel=state[1]))
                qfrc = actuator + penalty_forces(d.qpos, d.qvel, bodies_of(model, d), points, params, joints)
                d = mjx.euler(model, d.replace(qacc=mjx_smooth.solve_m(model, mass, qfrc - d.qfrc_bias)))
                return d.qpos, d.qvel

            return jax.lax.fori_loop(0, 3, substep, (data.qpos, data.qvel))

        keys = jax.random.split(jax.random.PRNGKey(3), 2)
        cotangent = (jax.random.normal(keys[0], data.qpos.shape), jax.random.normal(keys[1], data.qvel.shape))

        def with_vjp(step):  # one compiled program per side: the step and its pullback of the cotangent
            def both(q, v, a):
                out, pullback = jax.vjp(step, q, v, a)
                return out, pullback(cotangent)

            return jax.jit(both)

        substeps, task.substeps = task.substeps, 3
        try:
            ours = lambda q, v, a: (lambda d: (d.qpos, d.qvel))(task.physics_step(data.replace(qpos=q, qvel=v), a))
            theirs = lambda q, v, a: reference_step(data.replace(qpos=q, qvel=v, ctrl=a))
            args = (data.qpos, data.qvel, action)
            out, ours_pulled = with_vjp(ours)(*args)
            reference_out, theirs_pulled = with_vjp(theirs)(*args)
        finally:
            task.substeps = substeps
        for a, b in zip(out, reference_out):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)
        normalised, bodies, _ = forward(task.tree, data.qpos, data.qvel)
        assert float(jnp.abs(penalty_forces(normalised, data.qvel, bodies, points, params, joints)).max()) > 100.0
        for a, b in zip(ours_pulled, theirs_pulled):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * float(jnp.abs(b).max()))


def test_a_ball_joint_is_refused_by_name():
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body(name="arm")
    body.add_joint(name="shoulder", type=mujoco.mjtJoint.mjJNT_BALL)
    body.add_geom(size=[0.1, 0, 0])
    with pytest.raises(DvaUsageError, match="joint 'shoulder' is a mjJNT_BALL; use hinge, slide or free joints"):
        KinematicTree.from_model(spec.compile())

"""How a task advances its physics: the two differentiable contact models a task can choose.

``"penalty"`` — the paper's simulator (dflex): MuJoCo's rigid-body dynamics (:mod:`dva.tasks.tree`
computes the mass matrix and every substep's kinematics and bias forces) with MuJoCo's
contact and joint-limit constraints switched off, and this module adds the ground contacts, joint
limits, joint springs and joint damping as explicit forces, integrated by semi-implicit Euler
with 16–48 substeps per 60 Hz control step and the mass matrix inverted once per control step.
Every force is an explicit, smooth-almost-everywhere function of ``(qpos, qvel)``, so reverse
mode differentiates exactly the physics that runs forward: no solver, no warm start carried from
step to step.

``"mujoco"`` — MuJoCo's soft constraints with an accurate forward and an implicit gradient: the
constraint solve runs to convergence under ``stop_gradient`` and one full Newton step from its
solution carries the gradient (for a fixed active set its derivative is the
implicit-function-theorem gradient), with ``qacc_warmstart`` cut from the graph.

Both are pure functions of one environment's ``mjx.Data``; :class:`~dva.tasks.base.Task` vmaps them.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import solver as mjx_solver

from dva.errors import DvaUsageError
from dva.tasks.tree import Bodies, KinematicTree, integrate, is_ancestor, mass_matrix
from dva.tasks.tree import forward as tree_forward

PHYSICS: tuple[str, ...] = ("penalty", "mujoco")
SAFE_EPS = 1e-6  # keeps |v_t| and its gradient finite at zero sliding speed


def check_physics(physics: str) -> None:
    """Raise a one-line ``ValueError`` naming ``physics`` and the models there are."""
    if physics not in PHYSICS:
        raise DvaUsageError(f"unknown physics {physics!r}; choose one of: {', '.join(PHYSICS)}")


@dataclasses.dataclass(frozen=True)
class PenaltyContact:
    """Penalty-contact and joint parameters (dflex's names: ke, kd, kf, mu).

    Per contact point at penetration depth ``d ≥ 0`` with point velocity ``v`` (normal ``v_n``,
    tangential ``v_t``): normal force ``ke·d − kd·d·min(v_n, 0)`` and friction
    ``−v_t/|v_t| · min(kf·|v_t|, mu·ke·d)``. A joint past its range by ``e`` gets ``limit_ke·e``
    back towards the range. ``limit_kd`` damps every hinge and slide joint *all the time*, on top
    of its own damping, as dflex does (its damping term sits outside the limit test).
    """

    ke: float
    kd: float
    kf: float
    mu: float
    limit_ke: float = 1e3
    limit_kd: float = 10.0


@dataclasses.dataclass(frozen=True)
class ContactPoints:
    """Sphere centres that touch the floor: capsule end-spheres, sphere centres, box corners."""

    body: np.ndarray  # (P,) int, the body each point is fixed to
    local: np.ndarray  # (P, 3) position in that body's frame
    radius: np.ndarray  # (P,) sphere radius (0 for box corners)
    moved_by: np.ndarray  # (nv, P) 1.0 where dof i moves point p (its body is p's body or an ancestor)


@dataclasses.dataclass(frozen=True)
class JointForces:
    """The explicit forces on the hinge and slide joints of one robot, read from its compiled model.

    Limits are springs (``limit_ke``) past each limited joint's range; every hinge and slide
    joint has a spring ``−stiffness·(q − q_ref)`` (the MJCF's stiffness, towards its ``springref``)
    and a viscous damping ``−damping·q̇`` (the MJCF's damping plus ``limit_kd``).
    """

    limit_dof: np.ndarray  # (L,) dof index of each limited joint
    limit_qpos: np.ndarray  # (L,) its qpos index
    limit_range: np.ndarray  # (L, 2) its range
    dof: np.ndarray  # (J,) dof index of every hinge and slide joint
    qpos: np.ndarray  # (J,) its qpos index
    stiffness: np.ndarray  # (J,)
    reference: np.ndarray  # (J,) spring rest positions
    damping: np.ndarray  # (J,)


def joint_forces(model: mujoco.MjModel, limit_kd: float) -> JointForces:
    """The :class:`JointForces` of ``model``'s hinge and slide joints with ``limit_kd`` added to
    their own damping."""
    hinge_or_slide = [
        j
        for j in range(model.njnt)
        if int(model.jnt_type[j]) in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
    ]
    limited = [j for j in hinge_or_slide if model.jnt_limited[j]]
    dof, qpos = model.jnt_dofadr[hinge_or_slide], model.jnt_qposadr[hinge_or_slide]
    return JointForces(
        limit_dof=np.array(model.jnt_dofadr[limited], int),
        limit_qpos=np.array(model.jnt_qposadr[limited], int),
        limit_range=np.array(model.jnt_range[limited]).reshape(-1, 2),
        dof=np.array(dof, int),
        qpos=np.array(qpos, int),
        stiffness=np.array(model.jnt_stiffness[hinge_or_slide]),
        reference=np.array(model.qpos_spring[qpos]),
        damping=np.array(model.dof_damping[dof]) + limit_kd,
    )


def check_joint_transmissions(model: mujoco.MjModel) -> None:
    """The penalty step drives actuators through joints only (their moment is the gear, whatever
    the pose); an error names an actuator with another transmission."""
    for a in range(model.nu):
        kind = mujoco.mjtTrn(int(model.actuator_trntype[a]))
        if kind != mujoco.mjtTrn.mjTRN_JOINT:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
            raise DvaUsageError(
                f"actuator {name!r} has a {kind.name} transmission; penalty physics allows mjTRN_JOINT only"
                " (or use --physics mujoco)"
            )


def floor_contact_points(model: mujoco.MjModel, floor: str = "floor") -> ContactPoints:
    """The contact spheres of every geom that can touch the floor (by contype/conaffinity or an
    explicit ``<pair>`` with it), in its body's frame."""
    floor_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, floor)
    if floor_id < 0:
        raise DvaUsageError(f"the model has no geom named {floor!r} to make contacts with")
    paired = {
        int(g)
        for g1, g2 in zip(model.pair_geom1, model.pair_geom2)
        for g in (g1, g2)
        if floor_id in (g1, g2) and g != floor_id
    }
    bodies, points, radii = [], [], []
    for g in range(model.ngeom):
        if g == floor_id or model.geom_bodyid[g] == 0:
            continue
        collides = (model.geom_contype[g] & model.geom_conaffinity[floor_id]) or (
            model.geom_conaffinity[g] & model.geom_contype[floor_id]
        )
        if not collides and g not in paired:
            continue
        size, kind = model.geom_size[g], model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            local, radius = np.zeros((1, 3)), size[0]
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            local, radius = np.array([[0, 0, size[1]], [0, 0, -size[1]]]), size[0]
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
            local, radius = signs * size, 0.0
        else:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g)
            raise DvaUsageError(
                f"geom {name!r} of type {mujoco.mjtGeom(kind).name} cannot make penalty contacts; "
                "use spheres, capsules or boxes"
            )
        rotation = np.zeros(9)
        mujoco.mju_quat2Mat(rotation, model.geom_quat[g])
        points.append(model.geom_pos[g] + local @ rotation.reshape(3, 3).T)
        bodies += [model.geom_bodyid[g]] * len(local)
        radii += [radius] * len(local)
    if not points:  # e.g. the cart-pole: nothing reaches the floor
        return ContactPoints(np.zeros(0, int), np.zeros((0, 3)), np.zeros(0), np.zeros((model.nv, 0)))
    moved_by = np.array([[is_ancestor(model, model.dof_bodyid[i], b) for b in bodies] for i in range(model.nv)], float)
    return ContactPoints(np.array(bodies), np.concatenate(points), np.array(radii), moved_by)


def _rows(index: np.ndarray, size: int, dtype) -> jax.Array:
    """The one-hot (len(index), size) matrix that picks ``x[index]`` as ``rows @ x``: its reverse
    pass is a matrix product, where a gather's is a scatter."""
    return jnp.asarray(np.eye(size)[np.asarray(index, int)], dtype)


def bodies_of(model: mjx.Model, data: mjx.Data) -> Bodies:
    """The :class:`~dva.tasks.tree.Bodies` of MJX data whose kinematics and ``com_pos`` (and for
    ``cvel``, ``com_vel``) have run."""
    return Bodies(
        xpos=data.xpos, xmat=data.xmat, root_com=data.subtree_com[model.body_rootid], cvel=data.cvel, cdof=data.cdof
    )


def contact_state(bodies: Bodies, points: ContactPoints) -> tuple[jax.Array, jax.Array]:
    """Contact positions (P, 3) and penetration depths (P,) of the points.

    A sphere's contact position is its lowest point (centre − radius·ẑ), as in dflex: forces act
    there, so friction also turns the body.
    """
    pick = _rows(points.body, bodies.xpos.shape[0], bodies.xpos.dtype)
    centre = pick @ bodies.xpos + jnp.einsum(
        "pij,pj->pi", jnp.tensordot(pick, bodies.xmat, axes=1), jnp.asarray(points.local)
    )
    radius = jnp.asarray(points.radius)
    depth = jnp.maximum(radius - centre[:, 2], 0.0)
    return centre - radius[:, None] * jnp.array([0.0, 0.0, 1.0]), depth


def penalty_forces(
    qpos: jax.Array, qvel: jax.Array, bodies: Bodies, points: ContactPoints, params: PenaltyContact, joints: JointForces
) -> jax.Array:
    """Generalised forces (nv,) of the ground contacts and the joints' limits, springs and
    damping of one environment."""
    qfrc = joint_torques(qpos, qvel, params, joints)
    if len(points.body):
        qfrc = qfrc + contact_forces(bodies, points, params)
    return qfrc


def joint_torques(qpos: jax.Array, qvel: jax.Array, params: PenaltyContact, joints: JointForces) -> jax.Array:
    """Generalised forces (nv,) of the joint limits, springs and damping (see :class:`JointForces`)."""
    nq, nv, dtype = qpos.shape[0], qvel.shape[0], qvel.dtype
    q = _rows(joints.limit_qpos, nq, dtype) @ qpos
    lower, upper = joints.limit_range[:, 0], joints.limit_range[:, 1]
    limit = params.limit_ke * (jnp.maximum(lower - q, 0.0) - jnp.maximum(q - upper, 0.0))
    spring = -joints.stiffness * (_rows(joints.qpos, nq, dtype) @ qpos - joints.reference)
    damping = -joints.damping * (_rows(joints.dof, nv, dtype) @ qvel)
    return (spring + damping) @ _rows(joints.dof, nv, dtype) + limit @ _rows(joints.limit_dof, nv, dtype)


def contact_forces(bodies: Bodies, points: ContactPoints, params: PenaltyContact) -> jax.Array:
    """Generalised forces (nv,) of the penalty ground contacts (see :class:`PenaltyContact`)."""
    lowest, depth = contact_state(bodies, points)
    velocity = point_velocities(bodies, points, lowest)
    normal_speed = velocity[:, 2]
    normal = params.ke * depth - params.kd * depth * jnp.minimum(normal_speed, 0.0)
    tangential = velocity * jnp.array([1.0, 1.0, 0.0])
    speed = jnp.sqrt(jnp.sum(tangential**2, axis=-1) + SAFE_EPS**2)
    # −v_t/|v_t| · min(kf |v_t|, μ ke d): viscous when slow, Coulomb-capped when sliding.
    friction = -tangential * (jnp.minimum(params.kf * speed, params.mu * params.ke * depth) / speed)[:, None]
    return point_forces_to_joints(bodies, points, lowest, friction + normal[:, None] * jnp.array([0.0, 0.0, 1.0]))


# Both below use the bodies' spatial velocities and the dofs' motion axes instead of a Jacobian per
# point (J·q̇ and Jᵀf without forming J): the Humanoid's substep, 35 points, runs 5× faster.
def _c_frame_offsets(bodies: Bodies, points: ContactPoints, position: jax.Array) -> jax.Array:
    """``position`` (P, 3) relative to the origin of the c-frame of each point's body (its tree's
    centre of mass), where ``cvel`` and ``cdof`` are expressed."""
    return position - _rows(points.body, bodies.xpos.shape[0], position.dtype) @ bodies.root_com


def point_velocities(bodies: Bodies, points: ContactPoints, position: jax.Array) -> jax.Array:
    """World velocities (P, 3) of the points at ``position`` (P, 3), each fixed to its body."""
    # (P, 6): angular velocity, linear velocity at the c-frame origin
    spatial = _rows(points.body, bodies.xpos.shape[0], position.dtype) @ bodies.cvel
    return spatial[:, 3:] + jnp.cross(spatial[:, :3], _c_frame_offsets(bodies, points, position))


def point_forces_to_joints(bodies: Bodies, points: ContactPoints, position: jax.Array, force: jax.Array) -> jax.Array:
    """Generalised forces (nv,) of world forces (P, 3) applied at ``position`` (P, 3): ``Σ_p J_pᵀ f_p``."""
    offset = _c_frame_offsets(bodies, points, position)
    wrench = jnp.concatenate([jnp.cross(offset, force), force], axis=-1)  # (P, 6): torque, force
    return jnp.sum(bodies.cdof * (jnp.asarray(points.moved_by, force.dtype) @ wrench), axis=-1)


def penalty_step(model: mjx.Model, tree: KinematicTree, data: mjx.Data, substeps: int, forces) -> mjx.Data:
    """``substeps`` semi-implicit Euler steps of the penalty model under one ``ctrl``.

    As dflex, the mass matrix is built and inverted once per call (a control step) and reused by
    every substep: a substep runs the kinematics and bias forces (gravity, Coriolis) of
    :func:`dva.tasks.tree.forward`, ``forces(qpos, qvel, bodies) -> (nv,)`` (contacts and joint
    forces), then one matrix-vector product. Motor forces depend on ``ctrl`` alone and are computed
    once too. No constraint exists, so nothing is solved; damping is explicit (in ``forces``).
    """
    # The mass matrix from the same level-batched pass: MJX's kinematics and crb took ~5000 of the
    # Hopper step's operations to compile (1.5× the compile time, 1.3× the memory). Inverted once,
    # each substep's solve is one matrix-vector product (a batched triangular solve per substep,
    # and its transpose, cost 5× as much on the CPU).
    inverse_mass = jnp.linalg.inv(mass_matrix(tree, data.qpos))
    # Joint transmissions (every task's) read only qpos and the gears: no kinematics needed.
    qfrc_actuator = mjx.fwd_actuation(model, mjx.transmission(model, data)).qfrc_actuator
    dt = float(model.opt.timestep)

    def substep(state: tuple[jax.Array, jax.Array], _) -> tuple[tuple[jax.Array, jax.Array], None]:
        # Only (qpos, qvel) is carried: the reverse pass moves two vectors from substep to substep.
        qpos, bodies, qfrc_bias = tree_forward(tree, *state)
        qvel = state[1] + dt * inverse_mass @ (qfrc_actuator + forces(qpos, state[1], bodies) - qfrc_bias)
        return (integrate(tree, qpos, qvel, dt), qvel), None

    # Rematerialised: the reverse pass recomputes each substep's forward instead of storing its
    # intermediates (48 substeps × 32 steps of kinematics per env); 1.3× faster on the CPU.
    qpos, qvel = jax.lax.scan(jax.checkpoint(substep), (data.qpos, data.qvel), None, length=substeps)[0]
    return data.replace(qpos=qpos, qvel=qvel, time=data.time + substeps * model.opt.timestep)


def implicit_gradient_substep(model: mjx.Model, converged_model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """One step of MuJoCo's soft-constraint model: a converged solve forward, its implicit gradient.

    ``converged_model`` solves the constraints to convergence on a copy of the state cut from the
    graph, giving ``qacc*``. One full Newton step from it, ``qacc* − H⁻¹ ∇c(qacc*)`` (no line
    search: at the solution its step length is 0/0), has the value ``qacc*`` and, for the active
    set found, the derivative ``−H⁻¹ ∂∇c/∂θ`` of the implicit function theorem.
    """
    data = data.replace(qacc_warmstart=jax.lax.stop_gradient(data.qacc_warmstart))
    data = mjx.fwd_velocity(model, mjx.fwd_position(model, data))
    data = mjx.fwd_acceleration(model, mjx.fwd_actuation(model, data))
    converged = jax.lax.stop_gradient(mjx.solve(converged_model, jax.lax.stop_gradient(data)).qacc)
    # MJX's solver context (private API) evaluates the cost's gradient and H⁻¹·gradient (Newton).
    newton = mjx_solver.Context.create(model, data.replace(qacc=converged))
    qacc = converged - newton.Mgrad
    data = data.replace(qacc=qacc, qfrc_constraint=mjx.mul_m(model, data, qacc) - data.qfrc_smooth)
    return mjx.euler(model, data)


def mechanical_energy(task, data: mjx.Data) -> jax.Array:
    """Kinetic + gravitational (floor at z = 0) + the potential energy of the penalty contact and
    limit springs and of the joints' own springs, of one environment of a penalty-physics task."""
    data = mjx.fwd_velocity(task.model, mjx.fwd_position(task.model, data))
    kinetic = 0.5 * data.qvel @ mjx.full_m(task.model, data) @ data.qvel
    gravity = -jnp.sum(task.model.body_mass * (data.xipos @ task.model.opt.gravity))
    contact = 0.0
    if len(task.contact_points.body):
        _, depth = contact_state(bodies_of(task.model, data), task.contact_points)
        contact = 0.5 * task.penalty_contact.ke * jnp.sum(depth**2)
    joints = task.joints
    q = data.qpos[joints.limit_qpos]
    violation = jnp.maximum(joints.limit_range[:, 0] - q, 0.0) + jnp.maximum(q - joints.limit_range[:, 1], 0.0)
    limits = 0.5 * task.penalty_contact.limit_ke * jnp.sum(violation**2)
    springs = 0.5 * jnp.sum(joints.stiffness * (data.qpos[joints.qpos] - joints.reference) ** 2)
    return kinetic + gravity + contact + limits + springs

"""How a task advances its physics: the two differentiable contact models a task can choose.

``"penalty"`` — the paper's simulator (dflex, spec §7): MJX computes the smooth rigid-body
dynamics with MuJoCo's contact and joint-limit constraints switched off, and this module adds the
ground contacts and joint limits as explicit penalty forces (``qfrc_applied``), integrated by
MuJoCo's semi-implicit Euler with 16 substeps per 60 Hz control step. Every force is an explicit,
smooth-almost-everywhere function of ``(qpos, qvel)``, so reverse mode differentiates exactly
the physics that runs forward: no solver, no warm start carried from step to step.

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

PHYSICS: tuple[str, ...] = ("penalty", "mujoco")
SAFE_EPS = 1e-6  # keeps |v_t| and its gradient finite at zero sliding speed


def check_physics(physics: str) -> None:
    """Raise a one-line ``ValueError`` naming ``physics`` and the models there are."""
    if physics not in PHYSICS:
        raise ValueError(f"unknown physics {physics!r}; choose one of: {', '.join(PHYSICS)}")


@dataclasses.dataclass(frozen=True)
class PenaltyContact:
    """Penalty-contact and joint-limit parameters (dflex's names: ke, kd, kf, mu; spec §7).

    Per contact point at penetration depth ``d ≥ 0`` with point velocity ``v`` (normal ``v_n``,
    tangential ``v_t``): normal force ``ke·d − kd·d·min(v_n, 0)`` and friction
    ``−v_t/|v_t| · min(kf·|v_t|, mu·ke·d)``. A joint past its range by ``e`` gets
    ``limit_ke·e`` back towards the range and ``−limit_kd·q̇`` damping.
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


def floor_contact_points(model: mujoco.MjModel, floor: str = "floor") -> ContactPoints:
    """The contact spheres of every geom that can touch the floor (by contype/conaffinity or an
    explicit ``<pair>`` with it), in its body's frame."""
    floor_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, floor)
    if floor_id < 0:
        raise ValueError(f"the model has no geom named {floor!r} to make contacts with")
    paired = {int(g) for g1, g2 in zip(model.pair_geom1, model.pair_geom2) for g in (g1, g2)
              if floor_id in (g1, g2) and g != floor_id}
    bodies, points, radii = [], [], []
    for g in range(model.ngeom):
        if g == floor_id or model.geom_bodyid[g] == 0:
            continue
        collides = (model.geom_contype[g] & model.geom_conaffinity[floor_id]) or \
                   (model.geom_conaffinity[g] & model.geom_contype[floor_id])
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
            raise ValueError(f"geom {name!r} of type {mujoco.mjtGeom(kind).name} cannot make penalty contacts; "
                             "use spheres, capsules or boxes")
        rotation = np.zeros(9)
        mujoco.mju_quat2Mat(rotation, model.geom_quat[g])
        points.append(model.geom_pos[g] + local @ rotation.reshape(3, 3).T)
        bodies += [model.geom_bodyid[g]] * len(local)
        radii += [radius] * len(local)
    if not points:  # e.g. the cart-pole: nothing reaches the floor
        return ContactPoints(np.zeros(0, int), np.zeros((0, 3)), np.zeros(0))
    return ContactPoints(np.array(bodies), np.concatenate(points), np.array(radii))


def contact_state(model: mjx.Model, data: mjx.Data, points: ContactPoints):
    """Contact positions (P, 3), penetration depths (P,) and Jacobians (P, nv, 3) of the points.

    A sphere's contact position is its lowest point (centre − radius·ẑ): forces act there, so
    friction also turns the body, and a rolling sphere does not slip (dflex applies them at the
    centre). Needs the kinematics of ``data`` (``xpos``, ``xmat``, ``subtree_com``, ``cdof``).
    """
    body, radius = jnp.asarray(points.body), jnp.asarray(points.radius)
    centre = data.xpos[body] + jnp.einsum("pij,pj->pi", data.xmat[body], jnp.asarray(points.local))
    depth = jnp.maximum(radius - centre[:, 2], 0.0)
    lowest = centre.at[:, 2].add(-radius)
    jacobian = jax.vmap(lambda p, b: mjx.jac(model, data, p, b)[0])(lowest, body)
    return lowest, depth, jacobian


def penalty_forces(model: mjx.Model, data: mjx.Data, points: ContactPoints, params: PenaltyContact,
                   limited_dofs: np.ndarray, limit_ranges: np.ndarray, limit_qpos: np.ndarray) -> jax.Array:
    """Generalised forces (nv,) of the ground contacts and joint limits of one environment."""
    qfrc = jnp.zeros(model.nv, data.qvel.dtype)
    if len(points.body):
        qfrc = qfrc + contact_forces(model, data, points, params)
    if len(limited_dofs):
        q = data.qpos[jnp.asarray(limit_qpos)]
        qdot = data.qvel[jnp.asarray(limited_dofs)]
        lower, upper = jnp.asarray(limit_ranges[:, 0]), jnp.asarray(limit_ranges[:, 1])
        spring = params.limit_ke * (jnp.maximum(lower - q, 0.0) - jnp.maximum(q - upper, 0.0))
        damping = -params.limit_kd * jnp.where((q < lower) | (q > upper), qdot, 0.0)
        qfrc = qfrc.at[jnp.asarray(limited_dofs)].add(spring + damping)
    return qfrc


def contact_forces(model: mjx.Model, data: mjx.Data, points: ContactPoints, params: PenaltyContact) -> jax.Array:
    """Generalised forces (nv,) of the penalty ground contacts (see :class:`PenaltyContact`)."""
    _, depth, jacobian = contact_state(model, data, points)
    velocity = jnp.einsum("pvi,v->pi", jacobian, data.qvel)
    normal_speed = velocity[:, 2]
    normal = params.ke * depth - params.kd * depth * jnp.minimum(normal_speed, 0.0)
    tangential = velocity.at[:, 2].set(0.0)
    speed = jnp.sqrt(jnp.sum(tangential**2, axis=-1) + SAFE_EPS**2)
    # −v_t/|v_t| · min(kf |v_t|, μ ke d): viscous when slow, Coulomb-capped when sliding.
    friction = -tangential * (jnp.minimum(params.kf * speed, params.mu * params.ke * depth) / speed)[:, None]
    force = friction.at[:, 2].add(normal)
    return jnp.einsum("pvi,pi->v", jacobian, force)


def limited_joints(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dof index, range (lo, hi), qpos index) of every limited hinge or slide joint."""
    rows = [(model.jnt_dofadr[j], model.jnt_range[j], model.jnt_qposadr[j]) for j in range(model.njnt)
            if model.jnt_limited[j] and int(model.jnt_type[j]) in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)]
    if not rows:
        return np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int)
    dofs, ranges, qpos = zip(*rows)
    return np.array(dofs), np.array(ranges), np.array(qpos)


def penalty_substep(model: mjx.Model, data: mjx.Data, forces) -> mjx.Data:
    """One semi-implicit Euler step of the penalty model; ``forces(data) -> (nv,)`` runs once the
    kinematics and velocities of ``data`` are current. No constraint exists, so nothing is solved."""
    data = mjx.fwd_velocity(model, mjx.fwd_position(model, data))
    data = data.replace(qfrc_applied=forces(data))
    data = mjx.fwd_acceleration(model, mjx.fwd_actuation(model, data))
    return mjx.euler(model, data.replace(qacc=data.qacc_smooth))


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
        _, depth, _ = contact_state(task.model, data, task.contact_points)
        contact = 0.5 * task.penalty_contact.ke * jnp.sum(depth**2)
    _, ranges, qpos_index = task.limits
    q = data.qpos[qpos_index]
    violation = jnp.maximum(ranges[:, 0] - q, 0.0) + jnp.maximum(q - ranges[:, 1], 0.0)
    limits = 0.5 * task.penalty_contact.limit_ke * jnp.sum(violation**2)
    mj = task.mj_model
    hinge = np.isin(mj.jnt_type, [int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)])
    adr = mj.jnt_qposadr[hinge]
    springs = 0.5 * jnp.sum(mj.jnt_stiffness[hinge] * (data.qpos[adr] - mj.qpos_spring[adr]) ** 2)
    return kinetic + gravity + contact + limits + springs

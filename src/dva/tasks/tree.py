"""The rigid-body quantities a penalty step needs (kinematics, the mass matrix, bias forces),
computed one tree level at a time.

MJX's ``kinematics``, ``com_pos``, ``crb``, ``com_vel`` and ``rne`` walk the kinematic tree through
``scan.body_tree``, which takes each group of bodies' rows out of full-size arrays and writes them
back. Reverse mode turns every such take into a zero-padded full-size cotangent, and every write
into a scatter; summed over all groups and fields, that padding is where the reverse pass's time
went (``benchmarks/physics_profile.py``: on the Humanoid it cost 7× the forward).

Here bodies are grouped by depth. A level's bodies are computed together as (n, …) arrays, a
parent's value reaches its children through a constant one-hot matrix (the transpose, in reverse
mode, is a matrix product again), and coordinates reach joints the same way: a forward and a
reverse pass of only matrix products, elementwise arithmetic and a few concatenations.

The formulas are MJX's (the same quaternion conventions, the same c-frame at each tree's centre
of mass, the free joint's quaternion normalised as MJX's kinematics does); ``tests/test_tree.py``
checks every output against MJX in float64. Hinge, slide and free joints are supported: every
task here uses only those.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from dva.errors import DvaUsageError

FREE, SLIDE, HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)


@dataclasses.dataclass(frozen=True)
class JointSlot:
    """The ``k``-th hinge or slide joint of each body of a level (a body with fewer has none there)."""

    hinge: np.ndarray  # (n,) 1.0 where the slot is a hinge
    slide: np.ndarray  # (n,) 1.0 where the slot is a slide
    pos: np.ndarray  # (n, 3) anchor in the body frame
    axis: np.ndarray  # (n, 3) axis in the body frame
    qpos: np.ndarray  # (n, nq) one-hot row of the joint's coordinate (zeros for no joint)
    qpos0: np.ndarray  # (n,) its reference position


@dataclasses.dataclass(frozen=True)
class Level:
    """The bodies at one depth below the world, with what their poses need."""

    parent: np.ndarray  # (n, n_parent_level) one-hot: row i picks body i's parent
    pos: np.ndarray  # (n, 3) body frame in the parent's
    quat: np.ndarray  # (n, 4)
    free: np.ndarray  # (n,) 1.0 where the body hangs from a free joint (its only joint)
    free_qpos: np.ndarray  # (n, 7, nq) one-hot rows of a free joint's position and quaternion
    slots: tuple[JointSlot, ...]


@dataclasses.dataclass(frozen=True)
class KinematicTree:
    """A model's kinematic tree, read once from the compiled model: levels for the poses, and
    constant matrices over all bodies and dofs for everything that is linear along the tree.

    Velocities, accelerations and forces need no walk down or up the tree: a body's spatial
    velocity is the sum of the motions of the dofs above it (``ancestors``), the velocity a dof
    moves against is the sum of the motions before it in its chain (``before``), and the force
    a dof carries is the sum of its subtree's forces (``subtree``).
    """

    levels: tuple[Level, ...]
    order: np.ndarray  # (nbody, nbody) one-hot: row b picks body b from [world, level 1, level 2, …]
    # Per dof: its motion axis from a joint slot's world axis, a free body's frame column or a
    # constant (free translation), and the point it turns about (slot anchor or body origin).
    dof_slot: np.ndarray  # (nv, slots) one-hot: the slot row of a hinge or slide dof
    dof_column: np.ndarray  # (nv, 3·nbody) one-hot: the body-frame column of a free rotation dof
    dof_origin: np.ndarray  # (nv, nbody) one-hot: the body origin a free rotation dof turns about
    dof_axis: np.ndarray  # (nv, 3) constant axes (free translation dofs)
    dof_rotates: np.ndarray  # (nv,) 1.0 for hinge and free-rotation dofs
    dof_com: np.ndarray  # (nv, nbody) mass fractions of the tree of each dof's body
    ancestors: np.ndarray  # (nbody, nv) 1.0 where the dof's body is the body or above it
    before: np.ndarray  # (nv, nv) 1.0 where dof c moves before dof d (MJX's order within a body)
    subtree: np.ndarray  # (nv, nbody) 1.0 where the body is the dof's body or below it
    com_weights: np.ndarray  # (nbody, nbody) mass fractions of each body's tree (world: of all)
    ipos: np.ndarray  # (nbody, 3) centre of mass in the body frame
    iquat: np.ndarray  # (nbody, 4) principal axes of inertia in the body frame
    mass: np.ndarray  # (nbody,)
    inertia: np.ndarray  # (nbody, 3) principal moments
    gravity: np.ndarray  # (3,)
    armature: np.ndarray  # (nv,) added to the mass matrix's diagonal, as MuJoCo's
    velocity_map: np.ndarray  # (nq, nv) one-hot: the dof whose velocity moves each coordinate (none for quaternions)
    free_quat: np.ndarray  # (nfree, 4, nq) one-hot rows of each free joint's quaternion
    free_spin: np.ndarray  # (nfree, 3, nv) one-hot rows of its angular velocity
    nv: int

    @classmethod
    def from_model(cls, model: mujoco.MjModel) -> KinematicTree:
        """Read the tree of a compiled model; an error names a joint type that is not supported."""
        nb, nq, nv = int(model.nbody), int(model.nq), int(model.nv)
        parent = [int(p) for p in model.body_parentid]
        depth = [0] * nb
        for b in range(1, nb):
            depth[b] = depth[parent[b]] + 1
        by_level = [[b for b in range(1, nb) if depth[b] == k] for k in range(1, max(depth, default=0) + 1)]
        joints: list[list[int]] = [[] for _ in range(nb)]
        for j in range(model.njnt):
            kind = int(model.jnt_type[j])
            if kind not in (FREE, SLIDE, HINGE):
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise DvaUsageError(
                    f"joint {name!r} is a {mujoco.mjtJoint(kind).name}; use hinge, slide or free joints"
                )
            joints[int(model.jnt_bodyid[j])].append(j)
        is_free = [any(model.jnt_type[j] == FREE for j in joints[b]) for b in range(nb)]
        eye_q, eye_v = np.eye(nq), np.eye(nv)

        levels, previous, slot_of_joint, slot_rows = [], [0], {}, 0
        for bodies in by_level:
            n = len(bodies)
            free_qpos = np.zeros((n, 7, nq))
            for i, b in enumerate(bodies):
                if is_free[b]:
                    (j,) = joints[b]  # MuJoCo allows a free joint only alone, on a body below the world
                    free_qpos[i] = eye_q[model.jnt_qposadr[j] : model.jnt_qposadr[j] + 7]
            slots = []
            for k in range(max((len(joints[b]) for b in bodies if not is_free[b]), default=0)):
                present = [joints[b][k] if len(joints[b]) > k and not is_free[b] else -1 for b in bodies]
                for i, j in enumerate(present):
                    if j >= 0:
                        slot_of_joint[j] = slot_rows + i
                slot_rows += n
                slots.append(
                    JointSlot(
                        hinge=np.array([float(j >= 0 and model.jnt_type[j] == HINGE) for j in present]),
                        slide=np.array([float(j >= 0 and model.jnt_type[j] == SLIDE) for j in present]),
                        pos=np.array([model.jnt_pos[j] if j >= 0 else np.zeros(3) for j in present]),
                        axis=np.array([model.jnt_axis[j] if j >= 0 else np.zeros(3) for j in present]),
                        qpos=np.array([eye_q[model.jnt_qposadr[j]] if j >= 0 else np.zeros(nq) for j in present]),
                        qpos0=np.array([model.qpos0[model.jnt_qposadr[j]] if j >= 0 else 0.0 for j in present]),
                    )
                )
            levels.append(
                Level(
                    parent=np.array([[float(parent[b] == p) for p in previous] for b in bodies]),
                    pos=model.body_pos[bodies].copy(),
                    quat=model.body_quat[bodies].copy(),
                    free=np.array([float(is_free[b]) for b in bodies]),
                    free_qpos=free_qpos,
                    slots=tuple(slots),
                )
            )
            previous = bodies
        level_order = [b for bodies in by_level for b in bodies]
        order = np.eye(nb)[[0] + level_order].T  # column c of [world, level order] is body order_c

        dof_body = [int(b) for b in model.dof_bodyid]
        dof_joint = [int(j) for j in model.dof_jntid]
        dof_slot, dof_column, dof_origin = np.zeros((nv, slot_rows)), np.zeros((nv, 3 * nb)), np.zeros((nv, nb))
        dof_axis, dof_rotates = np.zeros((nv, 3)), np.zeros(nv)
        before = np.zeros((nv, nv))
        for d in range(nv):
            j, b = dof_joint[d], dof_body[d]
            if model.jnt_type[j] == FREE:
                i = d - model.jnt_dofadr[j]
                if i < 3:
                    dof_axis[d, i] = 1.0
                else:
                    dof_column[d, 3 * b + i - 3], dof_origin[d, b], dof_rotates[d] = 1.0, 1.0, 1.0
                    before[d, model.jnt_dofadr[j] : model.jnt_dofadr[j] + 3] = 1.0  # MJX: after the translation
            else:
                dof_slot[d, slot_of_joint[j]] = 1.0
                dof_rotates[d] = float(model.jnt_type[j] == HINGE)
                before[d, :d] = [
                    float(dof_body[c] == b or is_ancestor(model, dof_body[c], parent[b])) for c in range(d)
                ]
            # Dofs of the bodies above (all of them, free ones included) move before this one.
            before[d, :] = np.maximum(
                before[d, :], [float(dof_body[c] != b and is_ancestor(model, dof_body[c], b)) for c in range(nv)]
            )
        roots = np.asarray(model.body_rootid)
        same_tree = (roots[:, None] == roots[None, :]).astype(float)  # (body, body)
        com_weights = same_tree * model.body_mass / np.maximum(same_tree @ model.body_mass, mujoco.mjMINVAL)[:, None]
        com_weights[0] = model.body_mass / max(float(model.body_mass.sum()), mujoco.mjMINVAL)

        velocity_map = np.zeros((nq, nv))
        free = [j for j in range(model.njnt) if model.jnt_type[j] == FREE]
        for j in range(model.njnt):
            q, v = model.jnt_qposadr[j], model.jnt_dofadr[j]
            width = 3 if j in free else 1  # a free joint's translation; its quaternion below
            velocity_map[q : q + width, v : v + width] = np.eye(width)
        return cls(
            levels=tuple(levels),
            order=order,
            dof_slot=dof_slot,
            dof_column=dof_column,
            dof_origin=dof_origin,
            dof_axis=dof_axis,
            dof_rotates=dof_rotates,
            dof_com=com_weights[dof_body],
            ancestors=np.array([[float(is_ancestor(model, dof_body[d], b)) for d in range(nv)] for b in range(nb)]),
            before=before,
            subtree=np.array([[float(is_ancestor(model, dof_body[d], b)) for b in range(nb)] for d in range(nv)]),
            com_weights=com_weights,
            ipos=model.body_ipos.copy(),
            iquat=model.body_iquat.copy(),
            mass=model.body_mass.copy(),
            inertia=model.body_inertia.copy(),
            gravity=model.opt.gravity.copy(),
            armature=model.dof_armature.copy(),
            velocity_map=velocity_map,
            free_quat=np.array([eye_q[model.jnt_qposadr[j] + 3 : model.jnt_qposadr[j] + 7] for j in free]).reshape(
                -1, 4, nq
            ),
            free_spin=np.array([eye_v[model.jnt_dofadr[j] + 3 : model.jnt_dofadr[j] + 6] for j in free]).reshape(
                -1, 3, nv
            ),
            nv=nv,
        )


def is_ancestor(model: mujoco.MjModel, ancestor: int, body: int) -> bool:
    """Whether ``ancestor`` is ``body`` or one of its parents."""
    while body > 0 and body != ancestor:
        body = model.body_parentid[body]
    return body == ancestor


class Bodies(struct.PyTreeNode):
    """The world-frame state of one environment's bodies (body order, world first) and dofs."""

    xpos: jax.Array  # (nbody, 3) body frame origins
    xmat: jax.Array  # (nbody, 3, 3) body frame orientations
    root_com: jax.Array  # (nbody, 3) the centre of mass of each body's tree: the origin of its c-frame
    cvel: jax.Array  # (nbody, 6) spatial velocity (angular; linear at the c-frame origin)
    cdof: jax.Array  # (nv, 6) motion axis of each dof in its body's c-frame


# ---- small vector algebra on (n, …) arrays --------------------------------------------------
def quat_mul(u: jax.Array, v: jax.Array) -> jax.Array:
    """The quaternion products ``u v`` (w, x, y, z) of (…, 4) arrays, as MJX's."""
    w0, x0, y0, z0 = jnp.moveaxis(u, -1, 0)
    w1, x1, y1, z1 = jnp.moveaxis(v, -1, 0)
    return jnp.stack(
        [
            w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1,
            w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
            w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1,
            w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1,
        ],
        axis=-1,
    )


def rotate(vec: jax.Array, quat: jax.Array) -> jax.Array:
    """``vec`` (…, 3) rotated by the unit quaternions ``quat`` (…, 4), MJX's formula."""
    s, u = quat[..., :1], quat[..., 1:]
    dot = jnp.sum(u * vec, axis=-1, keepdims=True)
    return 2 * dot * u + (s * s - jnp.sum(u * u, axis=-1, keepdims=True)) * vec + 2 * s * jnp.cross(u, vec)


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrices (…, 3, 3) of unit quaternions (…, 4), as MJX's."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    rows = [
        [ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


_CROSS = np.stack([np.stack([np.cross(a, b) for b in np.eye(3)], -1) for a in np.eye(3)], 1)  # Levi-Civita


def _normalize_with_norm(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    # MJX's: a norm whose gradient is finite at 0 (a body at rest turns by a zero step), no 0/0.
    is_zero = jnp.all(jnp.isclose(x, 0.0), axis=-1, keepdims=True)
    norm = jnp.where(is_zero, 0.0, jnp.linalg.norm(jnp.where(is_zero, 1.0, x), axis=-1, keepdims=True))
    return x / (norm + 1e-6 * (norm == 0.0)), norm


def _normalize(x: jax.Array) -> jax.Array:
    return _normalize_with_norm(x)[0]


def motion_cross(v: jax.Array, u: jax.Array) -> jax.Array:
    """Spatial motion cross products ``v × u`` of (…, 6) arrays (angular first)."""
    return jnp.concatenate(
        [jnp.cross(v[..., :3], u[..., :3]), jnp.cross(v[..., 3:], u[..., :3]) + jnp.cross(v[..., :3], u[..., 3:])],
        axis=-1,
    )


def motion_cross_force(v: jax.Array, f: jax.Array) -> jax.Array:
    """Spatial force cross products ``v ×* f`` of (…, 6) arrays (torque first)."""
    return jnp.concatenate(
        [jnp.cross(v[..., :3], f[..., :3]) + jnp.cross(v[..., 3:], f[..., 3:]), jnp.cross(v[..., :3], f[..., 3:])],
        axis=-1,
    )


def _pick(rows: np.ndarray, x: jax.Array) -> jax.Array:
    """``rows @ x`` over the leading axis of ``x``, for a constant one-hot ``rows``."""
    return jnp.tensordot(jnp.asarray(rows, x.dtype), x, axes=1)


# ---- the pass ---------------------------------------------------------------------------------
class _Frames(struct.PyTreeNode):
    """What the poses give: the normalised ``qpos``, the :class:`Bodies`' frames and motion axes,
    and each body's spatial inertia (6, 6) about its tree's c-frame origin."""

    qpos: jax.Array
    xpos: jax.Array
    xmat: jax.Array
    root_com: jax.Array
    cdof: jax.Array
    inertia: jax.Array


def _frames(tree: KinematicTree, qpos: jax.Array) -> _Frames:
    """Kinematics and the c-frame quantities of one environment: MJX's ``kinematics`` and
    ``com_pos``."""
    dtype = qpos.dtype
    const = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    # Down the tree, a level at a time: body poses, and each joint's world anchor and axis.
    positions, quaternions, anchors, axes = [jnp.zeros((1, 3), dtype)], [const([[1.0, 0.0, 0.0, 0.0]])], [], []
    normalised = qpos
    for level in tree.levels:
        parent_quat = _pick(level.parent, quaternions[-1])
        pos = _pick(level.parent, positions[-1]) + rotate(const(level.pos), parent_quat)
        quat = quat_mul(parent_quat, const(level.quat))
        for slot in level.slots:
            anchor = rotate(const(slot.pos), quat) + pos
            axis = rotate(const(slot.axis), quat)
            coordinate = _pick(slot.qpos, qpos) - const(slot.qpos0)
            half = 0.5 * const(slot.hinge) * coordinate
            quat = quat_mul(
                quat, jnp.concatenate([jnp.cos(half)[:, None], const(slot.axis) * jnp.sin(half)[:, None]], -1)
            )
            hinged = anchor - rotate(const(slot.pos), quat)
            pos = jnp.where(slot.hinge[:, None] > 0, hinged, pos + axis * (const(slot.slide) * coordinate)[:, None])
            anchors.append(anchor)
            axes.append(axis)
        if level.free.any():
            coordinates = jnp.einsum("nkq,q->nk", const(level.free_qpos), qpos)
            free_quat = _normalize(coordinates[:, 3:])
            pos = jnp.where(level.free[:, None] > 0, coordinates[:, :3], pos)
            quat = jnp.where(level.free[:, None] > 0, free_quat, quat)
            # The normalised quaternion replaces the coordinates it came from.
            selection = const(level.free_qpos[:, 3:])
            normalised = normalised * (1.0 - jnp.einsum("nkq->q", selection)) + jnp.einsum(
                "nkq,nk->q", selection, free_quat
            )
        positions.append(pos)
        quaternions.append(quat)
    xpos, xquat = _pick(tree.order, jnp.concatenate(positions)), _pick(tree.order, jnp.concatenate(quaternions))
    xmat = quat_to_mat(xquat)

    # Each tree's centre of mass: the origin of the c-frame its bodies' spatial vectors are in.
    xipos = xpos + rotate(const(tree.ipos), xquat)
    root_com = _pick(tree.com_weights, xipos)

    # Every dof's motion axis (cdof).
    joint_anchor = jnp.concatenate(anchors) if anchors else jnp.zeros((0, 3), dtype)
    joint_axis = jnp.concatenate(axes) if axes else jnp.zeros((0, 3), dtype)
    columns = jnp.swapaxes(xmat, -1, -2).reshape(-1, 3)
    axis = _pick(tree.dof_slot, joint_axis) + _pick(tree.dof_column, columns) + const(tree.dof_axis)
    point = _pick(tree.dof_slot, joint_anchor) + _pick(tree.dof_origin, xpos)
    rotates = const(tree.dof_rotates)[:, None]
    cdof = jnp.concatenate(
        [rotates * axis, rotates * jnp.cross(axis, _pick(tree.dof_com, xipos) - point) + (1.0 - rotates) * axis], -1
    )

    # Each body's spatial inertia about the c-frame origin, for motion vectors (ω, v):
    # [[I, [m]×], [[m]×ᵀ, M·1]] with I the rotational inertia there and m the mass moment.
    principal = quat_to_mat(quat_mul(xquat, const(tree.iquat)))
    offset = xipos - root_com
    mass = const(tree.mass)[:, None, None]
    rotational = jnp.einsum("nik,nk,njk->nij", principal, const(tree.inertia), principal)
    squared = jnp.sum(offset * offset, axis=-1)[:, None, None]
    rotational = rotational + mass * (squared * jnp.eye(3, dtype=dtype) - offset[:, :, None] * offset[:, None, :])
    skew = jnp.einsum("ijk,nj->nik", const(_CROSS), offset * mass[:, 0])  # [m]× v = m × v
    inertia = jnp.concatenate(
        [
            jnp.concatenate([rotational, skew], axis=-1),
            jnp.concatenate([jnp.swapaxes(skew, -1, -2), mass * jnp.eye(3, dtype=dtype)], axis=-1),
        ],
        axis=-2,
    )
    return _Frames(qpos=normalised, xpos=xpos, xmat=xmat, root_com=root_com, cdof=cdof, inertia=inertia)


def forward(tree: KinematicTree, qpos: jax.Array, qvel: jax.Array) -> tuple[jax.Array, Bodies, jax.Array]:
    """Kinematics, velocities and bias forces (gravity, Coriolis, centrifugal) of one environment.

    Returns ``qpos`` with its free joints' quaternions normalised (as MJX's kinematics writes it
    back), the :class:`Bodies`, and ``qfrc_bias`` (nv,): MJX's ``kinematics``, ``com_pos``,
    ``com_vel`` and ``rne`` (without joint accelerations) in one pass.
    """
    frames = _frames(tree, qpos)
    cdof = frames.cdof
    # Velocities and accelerations as sums along the tree.
    motion = cdof * qvel[:, None]
    cvel = _pick(tree.ancestors, motion)
    # cdof_dot·q̇: each dof's motion crossed with the velocity of what carries it.
    velocity_product = motion_cross(_pick(tree.before, motion), motion)
    gravity = jnp.concatenate([jnp.zeros(3, qvel.dtype), -jnp.asarray(tree.gravity, qvel.dtype)])
    cacc = gravity + _pick(tree.ancestors, velocity_product)
    # Each body's force; a dof carries its subtree's.
    inert_mul = lambda v: jnp.einsum("nij,nj->ni", frames.inertia, v)  # noqa: E731
    force = inert_mul(cacc) + motion_cross_force(cvel, inert_mul(cvel))
    qfrc_bias = jnp.sum(cdof * _pick(tree.subtree, force), axis=-1)
    bodies = Bodies(xpos=frames.xpos, xmat=frames.xmat, root_com=frames.root_com, cvel=cvel, cdof=cdof)
    return frames.qpos, bodies, qfrc_bias


def mass_matrix(tree: KinematicTree, qpos: jax.Array) -> jax.Array:
    """The joint-space mass matrix (nv, nv) of one environment, armature included: MJX's ``crb``
    as ``Σ_b J_bᵀ I_b J_b`` over the bodies, ``J_b`` the motion axes of the dofs that move body b."""
    frames = _frames(tree, qpos)
    ancestors = jnp.asarray(tree.ancestors, qpos.dtype)
    mass = jnp.einsum("bd,be,dk,bkl,el->de", ancestors, ancestors, frames.cdof, frames.inertia, frames.cdof)
    return mass + jnp.diag(jnp.asarray(tree.armature, qpos.dtype))


def integrate(tree: KinematicTree, qpos: jax.Array, qvel: jax.Array, dt: float) -> jax.Array:
    """``qpos`` advanced by ``qvel`` over ``dt``, free joints' quaternions turned on the sphere:
    MJX's Euler position update."""
    dtype = qvel.dtype
    moved = qpos + dt * _pick(tree.velocity_map, qvel)
    if not len(tree.free_quat):
        return moved
    quat = jnp.einsum("fkq,q->fk", jnp.asarray(tree.free_quat, dtype), qpos)
    axis, speed = _normalize_with_norm(jnp.einsum("fkv,v->fk", jnp.asarray(tree.free_spin, dtype), qvel))
    half = 0.5 * dt * speed
    turned = _normalize(quat_mul(quat, jnp.concatenate([jnp.cos(half), axis * jnp.sin(half)], axis=-1)))
    written = jnp.einsum("fkq->q", jnp.asarray(tree.free_quat, dtype))
    return moved * (1.0 - written) + jnp.einsum("fkq,fk->q", jnp.asarray(tree.free_quat, dtype), turned)

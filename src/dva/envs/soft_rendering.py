"""A differentiable renderer: the scenes of :class:`~dva.envs.rendering.PixelRenderer` as a pure JAX
function of ``qpos``, so that gradients flow from pixels to joint positions (visual SHAC).

Each pixel's camera ray is tested against every geom at once, as dense array algebra over
(pixel, geom): capsules and spheres by the ray's closest approach to their axis segment, boxes by
a slab test, the floor plane exactly. Hard hits would give no gradient at silhouettes, so a geom
covers a pixel with the smooth weight ``sigmoid((radius − distance) / (softness · pixel
footprint))`` (boxes: the length of the ray inside the box in place of ``radius − distance``).
Geoms are shaded like MuJoCo's renderer without specular light or shadows (headlight ambient +
directional lights' and headlight's diffuse terms) and composited front to back by hit depth;
the floor (checker) is opaque, the sky behind everything.

Limits: no gradient where the depth order of two geoms flips (sorting is piecewise constant);
the floor's checker has no gradient (nothing on it moves); the image is smooth in ``qpos``
except at such order changes and at the box's edges between faces (normal switches).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dva.envs.rendering import MAX_DEPTH, SKY_COLOR, check_image_size, scene_poses
from dva.errors import DvaUsageError
from dva.tasks.base import Task

CAPSULE, SPHERE, BOX, PLANE = (
    int(mujoco.mjtGeom.mjGEOM_CAPSULE),
    int(mujoco.mjtGeom.mjGEOM_SPHERE),
    int(mujoco.mjtGeom.mjGEOM_BOX),
    int(mujoco.mjtGeom.mjGEOM_PLANE),
)
SUPPORTED = {CAPSULE: "capsule", SPHERE: "sphere", BOX: "box", PLANE: "plane"}


class SoftRenderer:
    """Renders ``num_envs`` copies of a task from its pixel camera, differentiably.

    Returns float RGB in [0, 255] (float64 under ``jax.enable_x64``) (``(num_envs, height, width, 3)``): the
    pixel encoder takes it
    like the uint8 frames of :class:`~dva.envs.rendering.PixelRenderer`, with gradients attached.
    ``softness`` is the silhouette width in pixels. The render is rematerialised in the backward
    pass (``jax.checkpoint``): a rollout keeps only poses per step, not per-pixel intermediates.
    """

    differentiable = True

    def __init__(
        self, task: Task, num_envs: int, width: int = 84, height: int | None = None, softness: float = 0.5
    ) -> None:
        height = width if height is None else height
        check_image_size(width, height)
        mjm = task.mj_model
        unsupported = sorted(
            {SUPPORTED.get(int(t), mujoco.mjtGeom(int(t)).name) for t in mjm.geom_type} - set(SUPPORTED.values())
        )
        if unsupported:
            raise DvaUsageError(
                f"SoftRenderer draws capsules, spheres, boxes and planes; {task.name} has {unsupported}"
            )
        self.task, self.num_envs, self.width, self.height, self.softness = task, num_envs, width, height, softness
        self._camera = mjm.camera(task.camera).id
        self._tan_half_fovy = float(np.tan(np.deg2rad(mjm.cam_fovy[self._camera]) / 2))
        visible = mjm.geom_rgba[:, 3] > 0
        self._planes = np.flatnonzero(visible & (mjm.geom_type == PLANE))
        self._bodies = np.flatnonzero(visible & (mjm.geom_type != PLANE))
        self._types = jnp.asarray(mjm.geom_type[self._bodies])
        self._sizes = jnp.asarray(mjm.geom_size[self._bodies])
        # A geom with a material takes the material's colour (as in MuJoCo).
        colors = np.where(mjm.geom_matid[:, None] >= 0, mjm.mat_rgba[np.maximum(mjm.geom_matid, 0)], mjm.geom_rgba)
        self._colors = jnp.asarray(colors[self._bodies, :3])
        self._floor_colors = jnp.asarray(_checker_colors(mjm))
        self._light_dirs = jnp.asarray(mjm.light_dir)  # (L, 3), directional, world-fixed
        self._light_diffuse = jnp.asarray(mjm.light_diffuse)
        self._ambient = jnp.asarray(mjm.vis.headlight.ambient)
        self._head_diffuse = jnp.asarray(mjm.vis.headlight.diffuse)
        # Unit ray directions in the camera frame (x right, y up, looking down −z), row-major pixels.
        ys = (1.0 - 2.0 * (np.arange(height) + 0.5) / height) * self._tan_half_fovy
        xs = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * self._tan_half_fovy * width / height
        rays = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], -np.ones((1, 1))), -1).reshape(-1, 3)
        self._camera_rays = jnp.asarray(rays / np.linalg.norm(rays, axis=-1, keepdims=True))
        self._pixel_angle = 2.0 * self._tan_half_fovy / height  # ray spread per pixel, per metre of depth

    def __call__(self, qpos: jax.Array) -> jax.Array:
        """Render ``qpos`` of shape ``(num_envs, nq)``: float RGB in [0, 255], differentiable."""
        if qpos.shape != (self.num_envs, self.task.mj_model.nq):
            raise DvaUsageError(
                f"qpos has shape {tuple(qpos.shape)}; this renderer needs ({self.num_envs}, {self.task.mj_model.nq})"
            )
        poses = scene_poses(self.task, qpos)
        render = jax.checkpoint(jax.vmap(self._render_one))
        images = render(
            poses.cam_xpos[:, self._camera], poses.cam_xmat[:, self._camera], poses.geom_xpos, poses.geom_xmat
        )
        return images.reshape(self.num_envs, self.height, self.width, 3) * 255.0

    def _render_one(self, cam_pos, cam_mat, geom_pos, geom_mat) -> jax.Array:
        rays = self._camera_rays @ cam_mat.T  # (P, 3) world directions
        centres, frames = geom_pos[self._bodies], geom_mat[self._bodies]
        depth, coverage, normal = _hit_geoms(
            cam_pos, rays, centres, frames, self._types, self._sizes, self.softness * self._pixel_angle
        )
        shade = self._shade(normal, -cam_mat[:, 2])  # (P, K, 3) light per geom
        colors = self._colors[None] * shade
        floor_depth, floor_color = self._floor(cam_pos, rays, geom_pos, cam_mat)
        # Front-to-back compositing over the geoms sorted by depth, then the (opaque) floor or sky.
        order = jnp.argsort(depth, axis=-1)
        depth, coverage = jnp.take_along_axis(depth, order, -1), jnp.take_along_axis(coverage, order, -1)
        colors = jnp.take_along_axis(colors, order[..., None], 1)
        coverage = jnp.where(depth < floor_depth[:, None], coverage, 0.0)  # behind the floor: hidden
        transmitted = jnp.cumprod(1.0 - coverage, axis=-1)
        before = jnp.concatenate([jnp.ones_like(transmitted[:, :1]), transmitted[:, :-1]], axis=-1)
        image = jnp.sum((before * coverage)[..., None] * colors, axis=1)
        return jnp.clip(image + transmitted[:, -1:] * floor_color, 0.0, 1.0)

    def _shade(self, normal: jax.Array, view: jax.Array) -> jax.Array:
        """Headlight ambient + diffuse of each directional light and the headlight (``view``)."""
        lambert = jnp.maximum(0.0, -jnp.einsum("pkc,lc->pkl", normal, self._light_dirs))
        light = self._ambient + jnp.einsum("pkl,lc->pkc", lambert, self._light_diffuse)
        return light + jnp.maximum(0.0, -(normal @ view))[..., None] * self._head_diffuse

    def _floor(self, cam_pos, rays, geom_pos, cam_mat) -> tuple[jax.Array, jax.Array]:
        """Depth along each ray to the floor (``inf``: sky) and the lit checker or sky colour."""
        height = geom_pos[self._planes[0], 2] if len(self._planes) else jnp.asarray(-jnp.inf)
        down = rays[:, 2] < -1e-6
        t = jnp.where(down, (height - cam_pos[2]) / jnp.where(down, rays[:, 2], -1.0), jnp.inf)
        t = jnp.where(t < MAX_DEPTH * 10, t, jnp.inf)
        point = cam_pos + jnp.where(jnp.isfinite(t), t, 0.0)[:, None] * rays
        square = (jnp.floor(2.0 * point[:, 0]) + jnp.floor(2.0 * point[:, 1])) % 2
        albedo = jnp.where(square[:, None] == 0, self._floor_colors[0], self._floor_colors[1])
        up = jnp.array([0.0, 0.0, 1.0])
        shade = self._shade(up[None, None], -cam_mat[:, 2])[:, 0]
        color = jnp.where(jnp.isfinite(t)[:, None], albedo * shade, jnp.asarray(SKY_COLOR))
        return jax.lax.stop_gradient(t), jax.lax.stop_gradient(color)


def _hit_geoms(origin, rays, centres, frames, types, sizes, spread):
    """Per (pixel, geom): front-surface depth along the ray, soft coverage and surface normal."""
    # Capsules and spheres: closest approach of the ray to the axis segment p0 + s·e, s ∈ [0, 1].
    half = jnp.where(types == CAPSULE, sizes[:, 1], 0.0)
    axis = frames[:, :, 2]  # local z in world coordinates (xmat columns)
    p0, e = centres - half[:, None] * axis, 2.0 * half[:, None] * axis  # (K, 3)
    w0 = origin - p0  # (K, 3)
    b = rays @ e.T  # (P, K)
    c = jnp.sum(e * e, -1)  # (K,)
    d = rays @ w0.T  # (P, K)
    f = jnp.sum(e * w0, -1)  # (K,); the minimum of |w0 + t·ray − s·e|² has s = (f − b d) / (c − b²)
    denom = c - b**2
    safe = denom > 1e-9 * jnp.maximum(c, 1e-9)
    s = jnp.clip(jnp.where(safe, (f - b * d) / jnp.where(safe, denom, 1.0), 0.0), 0.0, 1.0)
    s = jnp.where(c > 0, s, 0.0)
    axis_point = p0 + s[..., None] * e  # (P, K, 3)
    t = jnp.maximum(jnp.einsum("pkc,pc->pk", axis_point - origin, rays), 1e-3)
    offset = origin + t[..., None] * rays[:, None, :] - axis_point
    distance = jnp.sqrt(jnp.sum(offset**2, -1) + 1e-12)
    radius = sizes[:, 0]
    chord = jnp.sqrt(jnp.maximum(radius**2 - distance**2, 0.0) + 1e-6 * radius**2)
    round_depth = t - chord
    round_normal = offset - chord[..., None] * rays[:, None, :]  # from the axis to the hit point
    round_normal = round_normal / jnp.linalg.norm(round_normal, axis=-1, keepdims=True)
    round_margin = radius - distance
    # Boxes: slab test in the box frame; the margin is the ray's length inside the box.
    local_origin = jnp.einsum("kji,kj->ki", frames, origin - centres)  # Rᵀ (o − c)
    local_rays = jnp.einsum("kji,pj->pki", frames, rays)
    local_rays = jnp.where(jnp.abs(local_rays) < 1e-9, 1e-9, local_rays)
    t1 = (-sizes - local_origin) / local_rays
    t2 = (sizes - local_origin) / local_rays
    near, far = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
    entry, exit_ = jnp.max(near, -1), jnp.min(far, -1)
    face = jax.nn.one_hot(jnp.argmax(near, -1), 3) * -jnp.sign(local_rays)
    box_normal = jnp.einsum("kij,pkj->pki", frames, face)
    box_depth = jnp.maximum(entry, 1e-3)
    box_margin = jnp.minimum(exit_ - entry, exit_)  # no hit behind the camera
    is_box = (types == BOX)[None, :]
    depth = jnp.where(is_box, box_depth, round_depth)
    margin = jnp.where(is_box, box_margin, round_margin)
    normal = jnp.where(is_box[..., None], box_normal, round_normal)
    coverage = jax.nn.sigmoid(margin / (spread * depth))
    return depth, coverage, normal


def _checker_colors(mjm: mujoco.MjModel) -> np.ndarray:
    """The two colours of the floor's checker texture (or its material colour twice)."""
    planes = np.flatnonzero(mjm.geom_type == PLANE)
    if len(planes) == 0 or mjm.geom_matid[planes[0]] < 0 or mjm.ntex == 0:
        return np.tile(mjm.geom_rgba[planes[0], :3] if len(planes) else np.zeros(3), (2, 1))
    texture = mjm.mat_texid[mjm.geom_matid[planes[0]]].max()
    start = mjm.tex_adr[texture]
    size = mjm.tex_height[texture] * mjm.tex_width[texture] * mjm.tex_nchannel[texture]
    data = mjm.tex_data[start : start + size].reshape(mjm.tex_height[texture], mjm.tex_width[texture], -1)
    return np.stack([data[0, 0, :3], data[0, -1, :3]]).astype(np.float32) / 255.0

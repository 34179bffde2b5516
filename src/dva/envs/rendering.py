"""Pixel observations: MuJoCo's batched Warp ray-tracer inside ``jax.jit``, and frame stacking.

Physics runs on MJX's JAX implementation (differentiable); the Warp renderer needs a Warp-backed
``mjx.Data``. :class:`PixelRenderer` bridges the two: it runs forward kinematics for the camera and
geom poses in JAX, writes them into a Warp ``Data`` template, refits the ray-tracer's BVH and
renders. Rendering is not differentiable, so its input passes through ``jax.lax.stop_gradient``
— exactly D.Va's decoupling of the observation from the physics graph.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sys
import tempfile
import types

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from dva.errors import DvaUsageError
from dva.tasks.base import Task

DEFAULT_IMAGE_SIZE = 84
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 16, 1024
MAX_DEPTH = 30.0  # metres; farther surfaces read as this
SKY_COLOR = (0.6, 0.64, 0.7)  # background RGB in [0, 1]


def check_image_size(width: int, height: int) -> None:
    """A clear error unless both sides are ints in [MIN_IMAGE_SIZE, MAX_IMAGE_SIZE]."""
    for label, value in (("width", width), ("height", height)):
        if not isinstance(value, int) or not MIN_IMAGE_SIZE <= value <= MAX_IMAGE_SIZE:
            raise DvaUsageError(
                f"image {label} {value!r} is not allowed; use an int in [{MIN_IMAGE_SIZE}, {MAX_IMAGE_SIZE}]"
            )


LOG = logging.getLogger("dva")
# What Warp's native start-up prints on a machine without a GPU: nothing wrong, so only at DEBUG.
CUDA_ABSENT = "Could not find or load the NVIDIA CUDA driver"


@functools.cache
def load_warp() -> types.ModuleType:
    """Warp (the ``pixels`` extra, a one-line error naming it when missing), initialised once and
    quietly: its start-up banner, its per-kernel "Module … load" lines and the notice a machine
    without a GPU prints go to the ``dva`` logger at DEBUG
    (``logging.getLogger("dva").setLevel(logging.DEBUG)`` shows them); anything else it prints
    while starting, and its warnings after, still reach stderr."""
    try:  # the 'pixels' extra, imported only when a Warp renderer is made
        import mujoco_warp  # noqa: F401
        import warp
    except ImportError as error:
        raise ImportError(
            f"the Warp pixel renderer needs the 'pixels' extra: pip install 'dva[pixels]' ({error})"
        ) from None
    if not LOG.isEnabledFor(logging.DEBUG):
        warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
    with captured_stderr() as printed:
        warp.init()
    for line in printed():
        if CUDA_ABSENT in line:
            LOG.debug("Warp: %s", line.strip())
        else:
            sys.stderr.write(line)
    return warp


@contextlib.contextmanager
def captured_stderr():
    """Everything written to file descriptor 2 inside the block (native code's ``fprintf`` too),
    held back; yields a function that returns its lines once the block has ended."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as held:
        os.dup2(held.fileno(), 2)
        lines: list[str] = []
        try:
            yield lambda: lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            lines.extend(held.read().decode(errors="replace").splitlines(keepends=True))


def scene_poses(task: Task, qpos: jax.Array) -> mjx.Data:
    """Forward kinematics (JAX, differentiable) of a batch of ``qpos``: geom and camera poses."""
    model = task.model
    data0 = mjx.make_data(model)

    def one(q: jax.Array) -> mjx.Data:
        d = mjx.kinematics(model, data0.replace(qpos=q))
        d = mjx.com_pos(model, d)  # subtree centres of mass, for the tracking cameras
        return mjx.camlight(model, d)

    return jax.vmap(one)(qpos)


class PixelRenderer:
    """Renders ``num_envs`` copies of a task from its pixel camera as uint8 RGB (and depth).

    The Warp render context has a fixed batch size, so one renderer serves one ``num_envs``, on
    one ``device`` (JAX's default unless given; a run split over devices has one per device).
    Keep the renderer object alive while jitted functions that call it are in use; renders
    already queued when it is dropped still finish (see ``__del__``).
    """

    differentiable = False  # pixels carry no gradient to qpos (D.Va needs none)

    def __init__(
        self,
        task: Task,
        num_envs: int,
        width: int = DEFAULT_IMAGE_SIZE,
        height: int | None = None,
        depth: bool = False,
        samples_per_pixel: int = 1,
        device: jax.Device | None = None,
    ) -> None:
        height = width if height is None else height
        check_image_size(width, height)
        if not isinstance(num_envs, int) or num_envs < 1:
            raise DvaUsageError(f"num_envs must be a positive int, got {num_envs!r}")
        self.task, self.num_envs, self.width, self.height, self.depth = task, num_envs, width, height, depth
        warp = load_warp()
        if device is not None:  # build the model, template and render context on that device
            warp_device = f"cuda:{device.local_hardware_id}" if device.platform == "gpu" else "cpu"
            with jax.default_device(device), warp.ScopedDevice(warp_device):
                self._build(task, num_envs, width, height, depth, samples_per_pixel)
        else:
            self._build(task, num_envs, width, height, depth, samples_per_pixel)

    def _build(self, task: Task, num_envs: int, width: int, height: int, depth: bool, samples_per_pixel: int) -> None:
        mjm = task.mj_model
        self._camera = mjm.camera(task.camera).id
        self._warp_model = mjx.put_model(mjm, impl="warp")
        # Beyond the geom and camera poses each call sets, the renderer reads only the lights' poses.
        # The lights are directional and attached to the world, so MuJoCo's C forward pass gives
        # them once: no compiled Warp forward pass (≈ 20 s of kernels on a CPU) just for those.
        lit = mujoco.MjData(mjm)
        mujoco.mj_forward(mjm, lit)
        template = jax.vmap(lambda _: mjx.make_data(mjm, impl="warp"))(jnp.arange(num_envs))
        tiled = lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.float32), (num_envs, *x.shape))
        self._template = template.replace(
            _impl=template._impl.replace(light_xpos=tiled(lit.light_xpos), light_xdir=tiled(lit.light_xdir))
        )
        self._context = mjx.create_render_context(
            mjm=mjm,
            nworld=num_envs,
            cam_res=(width, height),
            render_rgb=True,
            render_depth=depth,
            cam_active=[task.camera],
            use_textures=True,
            use_shadows=False,
            samples_per_pixel=samples_per_pixel,
            background_color=(*SKY_COLOR, 1.0),
        )
        self._camera_slot = 0  # only the pixel camera is active in the context

    def __del__(self) -> None:
        # MJX looks the render context up by id when a queued render runs, and the context's
        # buffers go with this object. Renders are side-effecting calls, which JAX tracks: wait
        # for those still in flight, e.g. after ``jax.jit(PixelRenderer(...).__call__)(qpos)``.
        if getattr(self, "_context", None) is not None:
            try:
                jax.effects_barrier()
            except Exception:  # noqa: BLE001 - a failed computation reports itself where its result is read
                pass

    def __call__(self, qpos: jax.Array) -> jax.Array:
        """Render ``qpos`` of shape ``(num_envs, nq)``: uint8 RGB ``(num_envs, height, width, 3)``."""
        return self.render_with_depth(qpos)[0]

    def render_with_depth(self, qpos: jax.Array) -> tuple[jax.Array, jax.Array | None]:
        """RGB as :meth:`__call__` and, from a renderer made with ``depth=True``, float32 depth in
        metres ``(num_envs, height, width)``, clipped at ``MAX_DEPTH`` (else None)."""
        if qpos.shape != (self.num_envs, self.task.mj_model.nq):
            raise DvaUsageError(
                f"qpos has shape {tuple(qpos.shape)}; this renderer needs ({self.num_envs}, {self.task.mj_model.nq})"
            )
        poses = scene_poses(self.task, jax.lax.stop_gradient(qpos))
        warp_data = self._template.replace(
            qpos=poses.qpos,
            geom_xpos=poses.geom_xpos,
            geom_xmat=poses.geom_xmat,
            cam_xpos=poses.cam_xpos,
            cam_xmat=poses.cam_xmat,
        )
        context = self._context.pytree()
        warp_data = mjx.refit_bvh(self._warp_model, warp_data, context)
        rgb_packed, depth_packed, _ = mjx.render(self._warp_model, warp_data, context)
        rgb = mjx.get_rgb(context, self._camera_slot, rgb_packed)
        rgb = jnp.round(rgb * 255.0).astype(jnp.uint8)
        if not self.depth:
            return rgb, None
        # get_depth divides by a scale and clips to [0, 1]: scale by the far limit, then back.
        depth = MAX_DEPTH * mjx.get_depth(context, self._camera_slot, depth_packed, MAX_DEPTH)[..., 0]
        return rgb, depth


def reset_frame_stack(frame: jax.Array, num_frames: int) -> jax.Array:
    """A stack of ``num_frames`` copies of ``frame`` (N, H, W, C) → (N, H, W, C·num_frames)."""
    return jnp.concatenate([frame] * num_frames, axis=-1)


def push_frame(stack: jax.Array, frame: jax.Array, reset: jax.Array) -> jax.Array:
    """Drop the oldest frame of ``stack`` and append ``frame``; where ``reset`` (N,) is true the
    stack restarts as ``frame`` tiled (the first frame of a new episode)."""
    channels = frame.shape[-1]
    num_frames = stack.shape[-1] // channels
    shifted = jnp.concatenate([stack[..., channels:], frame], axis=-1)
    tiled = reset_frame_stack(frame, num_frames)
    return jnp.where(reset[:, None, None, None], tiled, shifted)

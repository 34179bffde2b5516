"""Image grids and videos of rollouts (PNG via imageio, mp4 via imageio-ffmpeg)."""

from __future__ import annotations

import warnings
from pathlib import Path

import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import numpy as np

from dva.envs.rendering import PixelRenderer
from dva.errors import DvaUsageError
from dva.tasks.base import CONTROL_DT, EnvState, Task


def image_grid(images: np.ndarray, columns: int | None = None, pad: int = 2) -> np.ndarray:
    """Tile ``images`` (N, H, W, 3) into one image, ``columns`` per row (default: square-ish)."""
    n, h, w, c = images.shape
    columns = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / columns))
    grid = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, c), 255, np.uint8)
    for i, image in enumerate(images):
        r, col = divmod(i, columns)
        grid[pad + r * (h + pad) : pad + r * (h + pad) + h, pad + col * (w + pad) : pad + col * (w + pad) + w] = image
    return grid


def random_rollout(task: Task, key: jax.Array, num_envs: int, steps: int) -> tuple[EnvState, jax.Array]:
    """Roll out uniform random actions; returns the final state and ``qpos`` per step (T, N, nq)."""
    reset_key, action_key = jax.random.split(key)

    @jax.jit
    def run(reset_key: jax.Array, action_key: jax.Array) -> tuple[EnvState, jax.Array]:
        state = task.reset(reset_key, num_envs)
        actions = jax.random.uniform(action_key, (steps, num_envs, task.action_dim), minval=-1.0, maxval=1.0)

        def one(state: EnvState, action: jax.Array) -> tuple[EnvState, jax.Array]:
            state = task.step(state, action)
            return state, state.data.qpos

        return jax.lax.scan(one, state, actions)

    return run(reset_key, action_key)


def write_video(path: Path, frames: list[np.ndarray] | np.ndarray, fps: int = 30) -> None:
    """Write RGB ``frames`` (T, H, W, 3) uint8 as an H.264 mp4."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        # imageio starts ffmpeg as a subprocess; it does not touch JAX, so the fork is safe.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        imageio.mimwrite(path, list(frames), fps=fps, macro_block_size=1)


def render_trajectory(
    renderer: PixelRenderer, qpos_trajectory: np.ndarray | jax.Array, columns: int | None = None, tile: bool = True
) -> np.ndarray:
    """Render each step of ``qpos_trajectory`` (T, num_envs, nq): tiled into one image per step
    (T, H', W', 3), or with ``tile=False`` per env (T, num_envs, H, W, 3)."""
    render = jax.jit(renderer.__call__)
    frames = [np.asarray(render(jnp.asarray(qpos))) for qpos in qpos_trajectory]
    return np.stack([image_grid(f, columns) for f in frames] if tile else frames)


def save_png(path: Path, image: np.ndarray) -> None:
    """Write one RGB image."""
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, image)


def upscale(images: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resize of (..., H, W, C) images to (..., size, size, C)."""
    rows = np.arange(size) * images.shape[-3] // size
    cols = np.arange(size) * images.shape[-2] // size
    return images[..., rows[:, None], cols[None, :], :]


def side_by_side_video(camera: np.ndarray | None, views: np.ndarray) -> np.ndarray:
    """Frames (T, H', W', 3) with, per env, the actor's camera view (upscaled to the view size,
    when given: (T, N, h, w, 3)) left of a larger view (T, N, S, S, 3); envs stacked vertically."""
    if camera is not None:
        views = np.concatenate([upscale(camera, views.shape[-2]), views], axis=-2)
    return np.stack([image_grid(step, columns=1) for step in views])


def policy_video(
    path: Path,
    task: Task,
    qpos: np.ndarray,
    camera: np.ndarray,
    num_envs: int = 4,
    size: int = 256,
    action_repeat: int = 1,
) -> None:
    """An mp4 of a recorded rollout (``qpos`` (T, N, nq), one entry per ``action_repeat`` control
    steps) of the first ``num_envs`` envs: the actor's camera frames (T, N, h, w, 3; may be
    empty) next to a ``size``² view, in real time."""
    num_envs = min(num_envs, qpos.shape[1])
    renderer = PixelRenderer(task, num_envs, size, samples_per_pixel=2)
    views = render_trajectory(renderer, qpos[:, :num_envs], tile=False)
    shown = np.clip(camera[:, :num_envs], 0, 255).astype(np.uint8) if camera.size else None  # float if soft-rendered
    write_video(path, side_by_side_video(shown, views), fps=round(1.0 / (CONTROL_DT * action_repeat)))


def policy_strip(path: Path, task: Task, qpos: np.ndarray, env: int = 0, frames: int = 8, size: int = 256) -> None:
    """A PNG of env ``env``'s ``size``² view at ``frames`` steps evenly spaced over the recorded
    rollout ``qpos`` (T, N, nq), first to last, left to right (an episode that ends early goes on
    from a reset, as in the video)."""
    if not 1 <= frames <= len(qpos):
        raise DvaUsageError(f"frames = {frames} is not allowed; use 1 to {len(qpos)} (the steps recorded)")
    steps = np.linspace(0, len(qpos) - 1, frames).round().astype(int)
    renderer = PixelRenderer(task, 1, size, samples_per_pixel=2)
    views = render_trajectory(renderer, np.asarray(qpos)[steps, env : env + 1], tile=False)[:, 0]
    save_png(path, image_grid(views, columns=frames))

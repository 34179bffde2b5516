"""Image grids and videos of rollouts (PNG via imageio, mp4 via imageio-ffmpeg)."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import numpy as np

from dva.rendering import PixelRenderer
from dva.tasks import EnvState, Task


def image_grid(images: np.ndarray, columns: int | None = None, pad: int = 2) -> np.ndarray:
    """Tile ``images`` (N, H, W, 3) into one image, ``columns`` per row (default: square-ish)."""
    n, h, w, c = images.shape
    columns = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / columns))
    grid = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, c), 255, np.uint8)
    for i, image in enumerate(images):
        r, col = divmod(i, columns)
        grid[pad + r * (h + pad): pad + r * (h + pad) + h, pad + col * (w + pad): pad + col * (w + pad) + w] = image
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
    imageio.mimwrite(path, list(frames), fps=fps, macro_block_size=1)


def render_trajectory(renderer: PixelRenderer, qpos_trajectory: jax.Array, columns: int | None = None) -> np.ndarray:
    """Render each step of ``qpos_trajectory`` (T, num_envs, nq) and tile the envs: (T, H', W', 3)."""
    render = jax.jit(renderer.__call__)
    frames = [image_grid(np.asarray(render(jnp.asarray(qpos))), columns) for qpos in qpos_trajectory]
    return np.stack(frames)


def save_png(path: Path, image: np.ndarray) -> None:
    """Write one RGB image."""
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, image)

"""Pixels: frame stacking, and Warp renders that actually show the robot."""

from __future__ import annotations

import gc

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.envs.rendering import PixelRenderer, push_frame, reset_frame_stack
from dva.tasks import make_task


def robot_mask(image: np.ndarray) -> np.ndarray:
    """Saturated pixels: the robots are orange/blue/green, floor and sky are near-grey."""
    image = image.astype(np.int32)
    return (image.max(-1) - image.min(-1)) > 60


def test_frame_stack_tiles_on_reset_and_shifts_otherwise():
    first = jnp.arange(2 * 2 * 2 * 3, dtype=jnp.uint8).reshape(2, 2, 2, 3)
    stack = reset_frame_stack(first, 3)
    assert stack.shape == (2, 2, 2, 9)
    np.testing.assert_array_equal(stack[..., 3:6], first)
    second = first + 100
    stack = push_frame(stack, second, jnp.array([False, True]))
    np.testing.assert_array_equal(stack[0, ..., 0:3], first[0])  # oldest dropped, order kept
    np.testing.assert_array_equal(stack[0, ..., 3:6], first[0])
    np.testing.assert_array_equal(stack[0, ..., 6:9], second[0])
    np.testing.assert_array_equal(stack[1], np.concatenate([second[1]] * 3, -1))  # new episode


@pytest.fixture(scope="module")
def cartpole_renderer():
    return PixelRenderer(make_task("cartpole_swingup"), num_envs=2, depth=True)


def test_cartpole_render_shows_the_cart_where_it_is(cartpole_renderer):
    qpos = jnp.array([[-1.0, 0.0], [1.0, 0.0]])  # cart left / right, pole upright
    rgb, depth = jax.jit(cartpole_renderer.render_with_depth)(qpos)
    rgb = np.asarray(rgb)
    assert rgb.shape == (2, 84, 84, 3) and rgb.dtype == np.uint8
    masks = [robot_mask(image) for image in rgb]
    assert all(mask.sum() > 40 for mask in masks), [int(mask.sum()) for mask in masks]
    # 2 m of cart travel is ~29 px at this camera (84 px span ≈ 5.7 m).
    centre = [np.nonzero(mask)[1].mean() for mask in masks]
    assert 20 < centre[1] - centre[0] < 40, centre
    # The pole is above the cart: upright pole pixels are higher (smaller row) than the cart's.
    rows = np.nonzero(masks[0])[0]
    assert rows.min() < 42 - 10
    depth = np.asarray(depth)
    assert depth.shape == (2, 84, 84)
    assert 5.0 < depth[0][masks[0]].mean() < 7.0  # the cart is ~6.2 m from the camera


@pytest.mark.parametrize("name", ["hopper", "cheetah", "ant", "humanoid", "quadruped"])
def test_tracking_camera_sees_robot_and_pose_changes_image(name):
    task = make_task(name)
    renderer = PixelRenderer(task, num_envs=2, width=64)
    qpos = jnp.stack([task.qpos0(), task.qpos0()])
    moved = qpos.at[1, -task.action_dim :].add(0.6)  # bend every actuated joint
    moved = moved.at[1, 0].add(5.0)  # and move 5 m forward: the camera follows
    images = np.asarray(jax.jit(renderer.__call__)(moved))
    masks = [robot_mask(image) for image in images]
    assert all(mask.sum() > 30 for mask in masks), [int(mask.sum()) for mask in masks]
    # The tracking camera keeps the robot near the middle of the view.
    for mask in masks:
        assert 16 < np.nonzero(mask)[1].mean() < 48
    assert (masks[0] != masks[1]).sum() > 10  # bent joints change the silhouette


def test_a_dropped_renderer_lets_its_queued_render_finish():
    """MJX looks the render context up when the render runs: a renderer dropped while its render
    is still queued (as in ``jax.jit(PixelRenderer(...).__call__)(qpos)``) must not take it along."""
    task = make_task("cartpole_swingup")

    def render_after_a_delay(qpos):
        renderer = PixelRenderer(task, num_envs=2, width=16)

        def delayed(qpos, matrix):
            busy = jax.lax.fori_loop(0, 20, lambda _, m: jnp.tanh(m @ m), matrix)  # runs before the render
            return renderer(qpos + 0.0 * busy[0, 0])

        return jax.jit(delayed)(qpos, 0.5 * jnp.eye(1000))

    pixels = render_after_a_delay(jnp.zeros((2, task.mj_model.nq)))  # returns before the render has run
    gc.collect()  # the renderer and its jitted function are gone now
    assert np.asarray(pixels).shape == (2, 16, 16, 3)


def test_bad_image_size_and_batch_are_rejected():
    task = make_task("cartpole_swingup")
    with pytest.raises(ValueError, match="image width 8 is not allowed"):
        PixelRenderer(task, num_envs=1, width=8)
    with pytest.raises(ValueError, match="image height 84.5"):
        PixelRenderer(task, num_envs=1, width=84, height=84.5)


def test_wrong_batch_is_rejected(cartpole_renderer):
    with pytest.raises(ValueError, match=r"qpos has shape \(3, 2\)"):
        cartpole_renderer(jnp.zeros((3, 2)))


QUIET_PROBE = """
import logging, sys
if sys.argv[1] == "debug":
    logging.basicConfig()
    logging.getLogger("dva").setLevel(logging.DEBUG)
import gymnasium, dva
gymnasium.make_vec("dva/cartpole_swingup-v0", num_envs=2, obs_type="pixels", image_size=16)
print("made")
"""


def test_warp_starts_quietly_unless_dvas_logger_asks_for_its_messages():
    """Making a pixel env prints nothing of Warp's start-up (its banner, per-kernel load lines, the
    notice a machine without a GPU gets) unless the ``dva`` logger is at DEBUG."""
    import subprocess
    import sys

    quiet, verbose = (
        subprocess.run([sys.executable, "-c", QUIET_PROBE, level], capture_output=True, text=True, timeout=600)
        for level in ("default", "debug")
    )
    assert quiet.returncode == 0 and verbose.returncode == 0, quiet.stderr + verbose.stderr
    assert quiet.stdout.strip() == "made" and "Warp" not in quiet.stderr, quiet.stderr
    assert "Warp" in verbose.stdout + verbose.stderr

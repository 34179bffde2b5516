"""The ``dva`` command line end to end."""

from __future__ import annotations

import imageio.v3 as iio
import pytest

from dva.cli import main


def test_tasks_lists_every_task_with_sizes(capsys):
    main(["tasks"])
    out = capsys.readouterr().out
    assert "ant" in out and "37" in out and "humanoid" in out and "76" in out
    assert "cartpole_swingup" in out and "240" in out


def test_render_writes_grid_and_video(tmp_path):
    main(["render", "--task", "cartpole_swingup", "--num-envs", "4", "--out", str(tmp_path),
          "--steps", "20", "--video-size", "96"])
    grid = iio.imread(tmp_path / "cartpole_swingup_observations.png")
    assert grid.shape == (2 * 86 + 2, 2 * 86 + 2, 3)
    frames = iio.imread(tmp_path / "cartpole_swingup_random.mp4")
    assert frames.shape[0] == 20 and frames.shape[-1] == 3
    assert frames.std(axis=0).max() > 10  # the video shows motion


def test_unknown_task_is_one_line_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--task", "walker"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == "dva: error: unknown task 'walker'; choose one of: cartpole_swingup, hopper, cheetah, ant, humanoid"


def test_bad_image_size_is_one_line_error(capsys):
    with pytest.raises(SystemExit):
        main(["render", "--task", "cartpole_swingup", "--image-size", "5"])
    assert "image width 5 is not allowed" in capsys.readouterr().err

"""One run over several devices: on two CPU devices (XLA's forced host device count, in a
subprocess: JAX reads the flag at start-up) the environments split, the gradient of an iteration
is the one-device gradient, and a short run follows the one-device run's curve."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from dva.algorithms import make_config
from dva.runner.checkpoint import RunSpec
from dva.runner.sharding import device_mesh
from dva.runner.training import run_mesh

TWO_DEVICES = textwrap.dedent(
    """
    import json, sys
    import dva, jax, numpy as np
    from dva.algorithms import build_agent, make_config
    from dva.runner.sharding import device_mesh, place
    from dva.runner.training import train

    SMALL = dict(num_envs=4, horizon=4, critic_minibatches=2, actor_hidden=(16,), critic_hidden=(16,))
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])
    part, out = sys.argv[1], {"devices": len(jax.devices())}
    mesh = device_mesh(2, 4)
    if part == "state":  # and Warp's renderer split over the devices
        from dva.envs.rendering import PixelRenderer
        from dva.envs.factory import SplitRenderer
        from dva.tasks import make_task

        task = make_task("cartpole_swingup")
        whole = PixelRenderer(task, 4, 16)
        split = SplitRenderer(lambda n, device: PixelRenderer(task, n, 16, device=device), 4, mesh)
        qpos = task.reset(jax.random.PRNGKey(0), 4).data.qpos + jax.numpy.arange(4.0)[:, None] * 0.3
        expected, got = np.asarray(jax.jit(whole.__call__)(qpos)), jax.jit(split.__call__)(qpos)
        out["render_error"] = int(np.abs(expected.astype(int) - np.asarray(got).astype(int)).max())
        out["render_spread"] = float(expected.std())
        out["render_split"] = str(got.sharding.spec)
    if part in ("state", "pixels"):
        algo, extra = {"state": ("shac", {}), "pixels": ("dva", {"image_size": 16})}[part]
        config = make_config("cartpole_swingup", algo, "cpu", **SMALL, **extra)
        one = build_agent("cartpole_swingup", algo, config)
        two = build_agent("cartpole_swingup", algo, config, mesh=mesh)
        state = jax.jit(one.init)(jax.random.PRNGKey(0))
        noise = jax.random.normal(jax.random.PRNGKey(1), (4, 4, 1))
        split = place(state, mesh, two.batch_fields)
        expected = flat(jax.jit(one.actor_gradient)(state.actor_params, state, noise)[2])
        got = flat(jax.jit(two.actor_gradient)(split.actor_params, split, noise)[2])
        after, _ = jax.jit(two.iteration)(split)
        out["gradient_error"] = float(np.abs(got - expected).max() / np.abs(expected).max())
        out["stays_split"] = str(after.env.data.qpos.sharding.spec)
    if part == "state":
        try:
            device_mesh(2, 3)
        except ValueError as error:
            out["odd_batch"] = str(error)
    if part == "curve":
        curves = []
        for devices in (1, 2):
            run = train("cartpole_swingup", "shac", iterations=40, eval_every=20, run_dir=sys.argv[2] + f"/d{devices}",
                        devices=devices, **SMALL)
            rows = [line.split(",") for line in open(run / "progress.csv").read().splitlines()]
            curves.append([float(row[4]) for row in rows[1:] if row[4]])
        out["curves"] = curves
    print("RESULT " + json.dumps(out))
    """
)


def on_two_devices(part: str, tmp_path) -> dict:
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    done = subprocess.run(
        [sys.executable, "-c", TWO_DEVICES, part, str(tmp_path)],
        env=dict(os.environ, XLA_FLAGS=flags),
        capture_output=True,
        text=True,
        timeout=1200,
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    assert lines, done.stderr[-3000:]
    out = json.loads(lines[0][len("RESULT ") :])
    assert out["devices"] == 2
    return out


def test_shac_on_two_devices_has_the_one_device_gradient_and_warp_renders_each_share(tmp_path):
    out = on_two_devices("state", tmp_path)
    assert out["gradient_error"] < 1e-4, out
    assert out["stays_split"] == "P('data',)", out
    assert out["odd_batch"] == "num_envs = 3 does not split over 2 devices; use a multiple of 2"
    # One renderer per device, each drawing its two envs, draws what one renderer of four draws.
    assert out["render_error"] == 0 and out["render_spread"] > 10, out
    assert out["render_split"] == "P('data',)", out


@pytest.mark.slow
def test_a_short_shac_run_on_two_devices_follows_the_one_device_curve(tmp_path):
    one, two = on_two_devices("curve", tmp_path)["curves"]
    assert len(one) == len(two) == 3
    assert one[0] == pytest.approx(two[0], rel=1e-5)  # the same untrained policy
    assert two == pytest.approx(one, rel=0.05), (one, two)


@pytest.mark.slow
def test_dva_on_two_devices_has_the_one_device_gradient(tmp_path):
    out = on_two_devices("pixels", tmp_path)
    assert out["gradient_error"] < 1e-4, out
    assert out["stays_split"] == "P('data',)", out


def test_device_counts_that_cannot_work_are_refused():
    with pytest.raises(ValueError, match=r"devices = 2 is not allowed; JAX sees 1 cpu device\(s\): use 1 to 1"):
        device_mesh(2, 16)
    spec = RunSpec("cartpole_swingup", "drqv2", "cpu", 0, make_config("cartpole_swingup", "drqv2", "cpu"), "penalty")
    with pytest.raises(ValueError, match="devices = 2 is not allowed for drqv2: it runs on one device; use 1"):
        run_mesh(spec, 2)
    assert run_mesh(spec, None) is None
    shac = make_config("cartpole_swingup", "shac", "cpu")
    assert run_mesh(RunSpec("cartpole_swingup", "shac", "cpu", 0, shac, "penalty"), None) is None

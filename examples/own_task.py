"""Your own task from your own MJCF, trained with D.Va: a pendulum swing-up defined in this file.

    python examples/own_task.py [--iterations 300]

A task is a :class:`dva.tasks.base.Task` subclass: its model (``build_spec``, here from the MJCF
string below; the floor and lights are added for you), a random initial state, the state
observation, the reward and the failure condition, each for one environment in JAX (the class
batches and differentiates them). ``dva.register_task`` then makes its name work everywhere a task
name does: ``train(...)`` here, ``dva train --task`` from a script that registers it, ``dva
compare``, ``gymnasium.make_vec("dva/pendulum_swingup-v0")``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

import dva
from dva.runner.logs import read_progress
from dva.runner.training import train
from dva.tasks.base import Task
from dva.tasks.physics import PenaltyContact

# A pole on a hinge 1.2 m above the floor, a motor at the hinge, and the camera the pixel
# observations come from (a task's camera is named "track" unless it sets ``camera``).
PENDULUM_MJCF = """
<mujoco model="pendulum">
  <worldbody>
    <camera name="track" pos="0 -2 1.2" xyaxes="1 0 0 0 0 1"/>
    <body name="pole" pos="0 0 1.2">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.6" size="0.08" mass="1" rgba="0.8 0.4 0.2 1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hinge" gear="4" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


class PendulumSwingup(Task):
    """Swing the pole up from hanging down: reward ``cos θ − 0.1 θ̇²`` per step (θ = 0 upright),
    240-step episodes (4 s), never terminated early. State observation ``[sin θ, cos θ, θ̇]``."""

    name = "pendulum_swingup"
    episode_length = 240
    penalty_substeps = 4  # nothing touches the floor: no stiff contact forces to resolve
    penalty_contact = PenaltyContact(ke=2e4, kd=1e3, kf=1e3, mu=0.9, limit_kd=0.0)

    def build_spec(self) -> mujoco.MjSpec:
        return mujoco.MjSpec.from_string(PENDULUM_MJCF)

    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        angle_key, velocity_key = jax.random.split(key)
        hanging = jnp.pi + jax.random.uniform(angle_key, (1,), minval=-0.1, maxval=0.1)
        return hanging, jax.random.uniform(velocity_key, (1,), minval=-0.05, maxval=0.05)

    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        angle, velocity = data.qpos[0], data.qvel[0]
        return jnp.stack([jnp.sin(angle), jnp.cos(angle), velocity])

    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        return jnp.cos(data.qpos[0]) - 0.1 * data.qvel[0] ** 2

    def is_terminated(self, data: mjx.Data) -> jax.Array:
        return jnp.zeros((), bool)


def main(iterations: int = 300, run_dir: Path = Path("runs/pendulum_swingup_dva"), **config) -> list[dict]:
    """Register the task and train D.Va on it from pixels (CPU preset; ``config`` overrides its
    fields, e.g. ``num_envs=4``) for ``iterations``; returns the run's logged rows."""
    dva.register_task("pendulum_swingup", PendulumSwingup)
    train("pendulum_swingup", "dva", iterations=iterations, run_dir=run_dir, eval_every=iterations, **config)
    return read_progress(run_dir)


if __name__ == "__main__":
    dva.configure()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--run-dir", type=Path, default=Path("runs/pendulum_swingup_dva"))
    args = parser.parse_args()
    rows = main(args.iterations, args.run_dir)
    print(
        f"evaluation return: {float(rows[0]['eval_return']):.1f} untrained, {float(rows[-1]['eval_return']):.1f} after"
    )

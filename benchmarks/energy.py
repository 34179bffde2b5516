"""Energy audit of trained policies: does the physics hand out energy the motors did not put in?

    python benchmarks/energy.py runs/hopper_shac_s0 [runs/… …] [--num-envs 8] [--steps 1000]

Replays each run's deterministic policy (state-observation runs) at the physics' own substep
resolution and books, per env, the work the motors do (``Σ dt · τ_actuator · q̇``: semi-implicit
Euler moves each coordinate by ``dt · q̇`` of the new velocity) against the change of mechanical
energy (kinetic, gravity, contact/limit/joint springs, ``dva.tasks.physics.mechanical_energy``).
Contacts, friction and damping only take energy out, so ``E(t) − E(0) − W(t)`` must stay ≤ 0 up to
the integrator's wobble; the table prints its largest value (the energy "from nowhere") next to
the motors' total work, and the highest torso height reached next to the start height.
Episodes are not reset inside the replay, so a fall is followed to the floor.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dva.analysis.bench import machine_description, markdown_table
from dva.runner.compiled import load_run
from dva.tasks.physics import mechanical_energy


def audit(run_dir: Path, num_envs: int, steps: int) -> list:
    spec, agent, state = load_run(run_dir)
    task = agent.task
    if agent.config.observation != "state" or task.physics != "penalty":
        raise ValueError(f"{run_dir}: the audit replays state-observation runs on penalty physics")
    dt = task.model.opt.timestep
    height_index = 1 if task.name in ("hopper", "cheetah") else 2

    def control_step(carry, _):
        data, work = carry
        obs = jax.vmap(task.observation)(data, data.ctrl)
        action = jnp.tanh(agent.pre_tanh_action(state.actor_params, state.obs_stats.normalize(obs), None))
        data = data.replace(ctrl=jnp.clip(action, -1.0, 1.0))

        def substep(carry, _):
            data, work = carry
            stepped = jax.vmap(task.substep)(data)
            # qfrc_actuator was evaluated at the start of the substep, q moved by dt · new q̇.
            work = work + dt * jnp.sum(stepped.qfrc_actuator * stepped.qvel, axis=-1)
            return (stepped, work), None

        (data, work), _ = jax.lax.scan(substep, (data, work), None, length=task.substeps)
        energy = jax.vmap(lambda d: mechanical_energy(task, d))(data)
        return (data, work), (energy, work, data.qpos[:, height_index])

    @jax.jit
    def replay(key):
        env = task.reset(key, num_envs)
        start = jax.vmap(lambda d: mechanical_energy(task, d))(env.data)
        _, (energy, work, height) = jax.lax.scan(control_step, (env.data, jnp.zeros(num_envs)), None, length=steps)
        return start, energy, work, height, env.data.qpos[:, height_index]

    start, energy, work, height, start_height = jax.device_get(replay(jax.random.PRNGKey(0)))
    from_nowhere = np.max(energy - start[None] - work, axis=0)  # per env
    return [
        spec.task,
        run_dir.name,
        f"{np.max(from_nowhere):.3g}",
        f"{np.mean(work[-1]):.4g}",
        f"{np.max(from_nowhere) / np.mean(np.abs(work[-1])):.2%}",
        f"{np.mean(start_height):.3f}",
        f"{np.max(height):.3f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    rows = [audit(run, args.num_envs, args.steps) for run in args.runs]
    print(f"\nEnergy audit over {args.steps} control steps × {args.num_envs} envs; {machine_description()}\n")
    print(
        markdown_table(
            [
                "task",
                "run",
                "max E(t) − E(0) − W(t) [J]",
                "motor work W [J]",
                "of |W|",
                "start height [m]",
                "highest torso [m]",
            ],
            rows,
        )
    )


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()

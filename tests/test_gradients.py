"""Differentiable physics you can trust: gradients of rollouts against central finite
differences of the same forward physics in float64, contact-free and in contact, and finite
gradients through 32 steps.

Compiling a reverse pass through MJX takes minutes on 2 cores, so each task compiles exactly one
function: ``value_and_grad`` of a 32-step rollout whose steps past the horizon ``H`` are
skipped. The same executable gives the gradient for H = 1, 3 and 32 and, evaluated at perturbed
inputs, the finite differences.
"""

from __future__ import annotations

import copy
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from dva.tasks import BUILTIN_TASKS, task_class
from dva.tasks.cartpole import CartpoleSwingup

MAX_STEPS = 32
EPS = 1e-6
NUM_DIRECTIONS = 6


def rollout_objective(task, state0, horizon, actions, dqvel, projection):
    """Σ rewards of the first ``horizon`` steps + a random projection of the state they reach."""
    data = state0.data.replace(qvel=state0.data.qvel + dqvel)

    def one(carry, inputs):
        t, action = inputs

        def advance(carry):
            state, total = carry
            stepped = task.step(state, action)
            return stepped, total + stepped.reward.sum()

        # A cond, not a select: steps past the horizon cost nothing, so the finite differences at
        # H = 1 and 3 run 1 and 3 physics steps of the 32-step executable, not 32.
        return jax.lax.cond(t < horizon, advance, lambda carry: carry, carry), None

    total0 = jnp.zeros((), actions.dtype)
    (state, total), _ = jax.lax.scan(one, (state0.replace(data=data), total0), (jnp.arange(MAX_STEPS), actions))
    return total + jnp.dot(projection, jnp.concatenate([state.data.qpos[0], state.data.qvel[0]]))


def with_coordinates(state, qpos, qvel):
    return state.replace(data=state.data.replace(qpos=jnp.asarray(qpos)[None], qvel=jnp.asarray(qvel)[None]))


def in_contact_coordinates(task):
    """(qpos, qvel) of a robot pressing into the floor, found with MuJoCo's C simulator (its
    contacts switched on even where the task's physics makes them penalty forces: capsule-plane
    penetration is the same geometry either way)."""
    model = copy.copy(task.mj_model)
    model.opt.disableflags = 0
    data = mujoco.MjData(model)
    for _ in range(120 * task.substeps):
        mujoco.mj_step(model, data)
        if data.ncon and min(data.contact.dist[: data.ncon]) < -1e-3:
            return data.qpos.copy(), data.qvel.copy()
    pytest.fail(f"{task.name}: no contact within 2 s")


def lifted_coordinates(task):
    """The reference pose 1 m above its start: nothing touches the floor for the next steps."""
    qpos = task.mj_model.qpos0.copy()
    if not isinstance(task, CartpoleSwingup):  # the cart-poles (swing-up, balance) never touch the floor
        qpos[1 if task.name in ("hopper", "cheetah") else 2] += 1.0
    return qpos, np.full(task.mj_model.nv, 0.1)


# Every model with its default physics (penalty contacts), and MuJoCo's soft constraints once: its
# forward is the converged solve, so these finite differences are those of the converged physics.
# Cart-pole balance is left out: it is the swing-up's model and physics from another start, and
# this test sets its own start (each case costs minutes of tracing and compiling).
CASES = [(name, task_class(name).physics) for name in BUILTIN_TASKS if name != "cartpole_balance"] + [
    ("hopper", "mujoco")
]


@pytest.mark.parametrize("name,physics", CASES)
def test_rollout_gradients_match_finite_differences(name, physics):
    with jax.enable_x64(True):
        task = task_class(name)(physics)  # a float64 model
        nv, nu = task.mj_model.nv, task.action_dim
        keys = jax.random.split(jax.random.PRNGKey(0), 4)
        state0 = jax.jit(task.reset, static_argnums=1)(keys[0], 1)
        actions = 0.5 * jax.random.uniform(keys[1], (MAX_STEPS, 1, nu), jnp.float64, -1, 1)
        projection = jax.random.normal(keys[2], (task.mj_model.nq + nv,), jnp.float64)
        value_and_grad = jax.jit(jax.value_and_grad(functools.partial(rollout_objective, task), argnums=(2, 3)))
        value = lambda *args: float(value_and_grad(*args)[0])

        cases = {"contact-free": lifted_coordinates(task)}
        if not isinstance(task, CartpoleSwingup):  # the cart-poles have no contacts
            cases["in contact"] = in_contact_coordinates(task)
        for label, (qpos, qvel) in cases.items():
            state = with_coordinates(state0, qpos, qvel)
            for horizon in (1, 3):
                _, (grad_actions, grad_qvel) = value_and_grad(state, horizon, actions, jnp.zeros(nv), projection)
                assert np.all(np.isfinite(grad_actions)) and np.all(np.isfinite(grad_qvel))
                assert np.all(np.asarray(grad_actions[horizon:]) == 0.0)  # steps past the horizon
                # Directional derivatives along random directions of (first H actions, initial qvel).
                direction_keys = jax.random.split(keys[3], NUM_DIRECTIONS)
                for key in direction_keys:
                    ka, kv = jax.random.split(key)
                    da = jax.random.normal(ka, (MAX_STEPS, 1, nu)).at[horizon:].set(0.0)
                    dv = jax.random.normal(kv, (nv,))
                    analytic = float(jnp.sum(grad_actions * da) + jnp.dot(grad_qvel, dv))
                    numeric = (
                        value(state, horizon, actions + EPS * da, EPS * dv, projection)
                        - value(state, horizon, actions - EPS * da, -EPS * dv, projection)
                    ) / (2 * EPS)
                    assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-6), (
                        f"{name} {physics} {label} H={horizon}"
                    )

        # 32 steps of random actions (wider ones) from a fresh state: everything stays finite.
        total, (grad_actions, grad_qvel) = value_and_grad(state0, MAX_STEPS, 2.0 * actions, jnp.zeros(nv), projection)
        assert np.isfinite(float(total))
        assert np.all(np.isfinite(grad_actions)) and np.all(np.isfinite(grad_qvel))
        assert float(jnp.abs(grad_actions[0]).max()) > 0.0

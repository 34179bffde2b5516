"""State-to-visual DAgger: every stored observation is labelled with the teacher's action, the
mixture follows the teacher exactly when told to, the student fits the labels, the stop rule."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fakes import StripeRenderer

from dva.algorithms import make_config
from dva.algorithms.dagger import DAgger
from dva.envs.observations import PixelObservations
from dva.tasks import make_task

NUM_ENVS, HORIZON = 4, 6


class LinearTeacher:
    """A stand-in teacher on the state: ``clip(gain · x + bias)`` of the cart position x."""

    def __init__(self, task) -> None:
        self.task = task

    def act(self, policy, observation):
        gain, bias = policy
        return jnp.clip(gain * observation["state"][:, :1] + bias, -1.0, 1.0)


def dagger(**overrides) -> DAgger:
    task = make_task("cartpole_balance")
    config = make_config(
        "cartpole_balance",
        "dagger",
        "cpu",
        teacher="unused",
        num_envs=NUM_ENVS,
        horizon=HORIZON,
        image_size=16,
        batch_size=8,
        replay_size=200,
        updates_per_iteration=4,
        actor_hidden=(16,),
        trunk=16,
        **overrides,
    )
    env = PixelObservations(task, NUM_ENVS, StripeRenderer(NUM_ENVS), config.frame_stack)
    return DAgger(env, config, LinearTeacher(task), (jnp.asarray(-3.0), jnp.asarray(-0.5)))


def test_dagger_labels_with_the_teacher_and_follows_it_when_told():
    agent = dagger(teacher_fraction=1.0, teacher_decay=1.0)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    after, metrics = jax.jit(agent.iteration)(state)
    # With the teacher always acting, the envs are where the teacher's own rollout takes them.
    env, expected = state.env, []
    teacher_action = jax.jit(lambda env: agent.teacher.act(agent.teacher_policy, agent.env.observe(env)))
    step = jax.jit(agent.env.step)  # compiled: op by op the physics step costs ≈ 100 small compiles
    for _ in range(HORIZON):
        expected.append(teacher_action(env))
        env = step(env, expected[-1])
    np.testing.assert_allclose(after.env.data.qpos, env.data.qpos, rtol=1e-5, atol=1e-6)
    stored = np.asarray(after.replay.experience["action"][0, : NUM_ENVS * HORIZON])
    np.testing.assert_allclose(stored, np.concatenate(expected), rtol=1e-6)  # every label is the teacher's
    assert float(metrics.logged["teacher_fraction"]) == 1.0 and np.isfinite(metrics.logged["bc_loss"])


def test_dagger_student_rollouts_are_still_labelled_and_the_student_learns_the_labels():
    agent = dagger(teacher_fraction=0.0)
    initial = jax.jit(agent.init)(jax.random.PRNGKey(1))
    state, iteration = initial, jax.jit(agent.iteration)
    for _ in range(8):
        state, metrics = iteration(state)
    observations = agent.env.observe(state.env)
    # The student acted (fraction 0), yet the labels are the teacher's actions on what it saw.
    pixels = state.replay.experience["pixels"][0, : 8 * NUM_ENVS * HORIZON]
    labels = state.replay.experience["action"][0, : 8 * NUM_ENVS * HORIZON]
    assert float(pixels.std()) > 0 and float(labels.std()) > 0
    # It fits the labels: the cloning loss over everything stored falls well below the untrained one.
    assert float(agent.bc_loss(state.student, pixels, labels)) < 0.2 * float(
        agent.bc_loss(initial.student, pixels, labels)
    )
    assert agent.act(agent.policy(state), observations).shape == (NUM_ENVS, 1)
    student_driven = dagger(teacher_fraction=0.0, stop_bc_loss=1e9)
    _, metrics = jax.jit(student_driven.iteration)(jax.jit(student_driven.init)(jax.random.PRNGKey(0)))
    assert bool(metrics.stop)  # the student drives and its loss is below the threshold: the run ends
    # The stop rule waits until the student drives: with the teacher acting, even a loss below
    # the threshold does not end the run (its samples are the teacher's states, not the student's).
    teacher_driven = dagger(stop_bc_loss=1e9)
    _, metrics = jax.jit(teacher_driven.iteration)(jax.jit(teacher_driven.init)(jax.random.PRNGKey(0)))
    assert float(metrics.logged["fresh_bc_loss"]) < 1e9 and not bool(metrics.stop)


def test_dagger_stops_on_the_averaged_fresh_loss_not_on_one_dip():
    agent = dagger(teacher_fraction=0.0, stop_bc_loss=1e9, stop_loss_decay=0.9)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    # Past iteration 0 the rule reads the EMA: an average still far above the threshold keeps the
    # run going although this iteration's fresh loss is below it.
    state = state.replace(iteration=jnp.asarray(5, jnp.int32), fresh_loss_average=jnp.asarray(1e11))
    after, metrics = jax.jit(agent.iteration)(state)
    fresh = float(metrics.logged["fresh_bc_loss"])
    assert fresh < 1e9 and not bool(metrics.stop)
    np.testing.assert_allclose(float(metrics.logged["fresh_bc_loss_average"]), 0.9 * 1e11 + 0.1 * fresh, rtol=1e-6)
    np.testing.assert_allclose(float(after.fresh_loss_average), float(metrics.logged["fresh_bc_loss_average"]))
    # Once the average has come down, the same rule ends the run.
    _, metrics = jax.jit(agent.iteration)(state.replace(fresh_loss_average=jnp.asarray(1e8)))
    assert bool(metrics.stop)
    with pytest.raises(ValueError, match="stop_loss_decay = 1.0"):
        dagger(stop_loss_decay=1.0)

"""Task API: rewards against hand-computed values, termination, auto-reset, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dva.tasks import make_task
from dva.tasks.physics import joint_torques


def data_with(task, qpos, qvel):
    """An unbatched physics state of ``task`` with the given coordinates."""
    return task._data0.replace(qpos=jnp.asarray(qpos, jnp.float32), qvel=jnp.asarray(qvel, jnp.float32))


def test_cartpole_reward_and_termination():
    task = make_task("cartpole_swingup")
    data = data_with(task, [0.5, np.pi - 0.2], [0.4, 1.5])
    expected = 10 - (np.pi - 0.2) ** 2 - 0.1 * 1.5**2 - 0.05 * 0.5**2 - 0.1 * 0.4**2
    assert float(task.reward(data, jnp.zeros(1))) == pytest.approx(expected, rel=1e-5)
    # Angles past π wrap: 2π − 0.3 is 0.3 from upright.
    wrapped = data_with(task, [0.0, 2 * np.pi - 0.3], [0.0, 0.0])
    assert float(task.reward(wrapped, jnp.zeros(1))) == pytest.approx(10 - 0.3**2, rel=1e-5)
    assert not bool(task.is_terminated(data))
    assert bool(task.is_terminated(data_with(task, [-2.5, 0.0], [0.0, 0.0])))
    obs = task.observation(data, jnp.zeros(1))
    np.testing.assert_allclose(obs, [0.5, 0.4, np.sin(np.pi - 0.2), np.cos(np.pi - 0.2), 1.5], rtol=1e-5, atol=1e-6)


def test_cartpole_balance_starts_upright_and_shares_the_swing_up_reward():
    balance, swingup = make_task("cartpole_balance"), make_task("cartpole_swingup")
    state = jax.jit(balance.reset, static_argnums=1)(jax.random.PRNGKey(0), 256)
    angle = np.asarray(state.data.qpos[:, 1])
    assert np.abs(angle).max() <= np.pi / 60 + 1e-6 and angle.std() > 0.01  # upright ± 3°, random
    assert np.abs(np.asarray(state.data.qpos[:, 0])).max() == 0.0
    data = data_with(balance, [0.3, 0.1], [0.2, -0.4])
    expected = 10 - 0.1**2 - 0.1 * 0.4**2 - 0.05 * 0.3**2 - 0.1 * 0.2**2
    assert float(balance.reward(data, jnp.zeros(1))) == pytest.approx(expected, rel=1e-5)
    assert float(swingup.reward(data_with(swingup, [0.3, 0.1], [0.2, -0.4]), jnp.zeros(1))) == pytest.approx(
        expected, rel=1e-5
    )


def test_hopper_reward_above_and_below_target_height():
    task = make_task("hopper")
    action = jnp.array([0.5, -0.5, 1.0])
    up = data_with(task, [0.0, -0.1, 0.2, 0.0, 0.0, 0.0], [1.5, 0, 0, 0, 0, 0])
    # Δh = −0.1 + 0.3 = 0.2 ≥ 0 → +0.2; angle 1 − 0.2²/(π/6)²; action 0.1·(0.25 + 0.25 + 1).
    expected = 1.5 + 0.2 + (1 - 0.2**2 / (np.pi / 6) ** 2) - 0.15
    assert float(task.reward(up, action)) == pytest.approx(expected, rel=1e-5)
    low = data_with(task, [0.0, -0.4, 0.0, 0.0, 0.0, 0.0], [0.0] * 6)
    # Δh = −0.1 → −200·0.01 = −2; upright → angle term 1.
    assert float(task.reward(low, jnp.zeros(3))) == pytest.approx(-2.0 + 1.0, rel=1e-5)
    assert not bool(task.is_terminated(low))
    assert bool(task.is_terminated(data_with(task, [0.0, -0.46, 0, 0, 0, 0], [0.0] * 6)))


def test_cheetah_reward_penalises_actions_as_the_reference():
    task = make_task("cheetah")
    data = data_with(task, task.mj_model.qpos0, [2.5] + [0.3] * 8)
    action = jnp.array([1.0, -0.5, 0.0, 0.5, 0.0, 0.0])
    # v_x − 0.1·(1 + 0.25 + 0.25)
    assert float(task.reward(data, action)) == pytest.approx(2.5 - 0.15, rel=1e-6)
    assert not bool(task.is_terminated(data_with(task, np.full(9, -5.0), np.zeros(9))))


def test_cheetah_has_the_reference_assets_joint_ranges_and_start_height():
    task = make_task("cheetah")
    model = task.mj_model
    ranges = {
        name: model.jnt_range[model.joint(name).id].tolist()
        for name in ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
    }
    assert ranges == {
        "bthigh": [-0.52, 1.05],
        "bshin": [-0.785, 0.785],
        "bfoot": [-0.4, 0.785],
        "fthigh": [-1.5, 0.8],
        "fshin": [-1.2, 1.1],
        "ffoot": [-3.1, -0.3],
    }
    assert model.body("torso").pos[2] == pytest.approx(0.8)
    # At q = 0 the front foot is 0.3 rad past its upper limit: the limit spring (1e3 N·m/rad)
    # pushes it back with 300 N·m, as the reference's robot does.
    qpos, qvel = jnp.asarray(model.qpos0), jnp.zeros(model.nv)
    torques = joint_torques(qpos, qvel, task.penalty_contact, task.joints)
    ffoot = model.jnt_dofadr[model.joint("ffoot").id]
    assert float(torques[ffoot]) == pytest.approx(-300.0, rel=1e-5)
    others = np.delete(np.asarray(torques), ffoot)
    np.testing.assert_allclose(others, 0.0, atol=1e-6)  # every other joint rests in its range


def test_ant_reward_with_torso_turned_left():
    task = make_task("ant")
    qpos = np.array(task.mj_model.qpos0)
    qpos[2] = 0.6
    qpos[3:7] = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]  # 90° yaw: upright, facing +y
    qvel = np.zeros(task.mj_model.nv)
    qvel[0] = 0.7
    data = data_with(task, qpos, qvel)
    # v_x + 0.1·up(1) + heading(0) + (0.6 − 0.27)
    assert float(task.reward(data, jnp.zeros(8))) == pytest.approx(0.7 + 0.1 + 0.0 + 0.33, abs=1e-5)
    obs = task.observation(data, jnp.full(8, 0.25))
    assert obs.shape == (37,)
    np.testing.assert_allclose(obs[-10:-8], [1.0, 0.0], atol=1e-6)  # up, heading projections
    assert bool(task.is_terminated(data_with(task, np.r_[0, 0, 0.26, qpos[3:]], qvel)))


def test_humanoid_reward_code_version():
    task = make_task("humanoid")
    qpos = np.array(task.mj_model.qpos0)
    qpos[2] = 1.0  # Δh = clip(1.0 − 0.84, −1, 0.1) = 0.1 → 10·0.1
    qvel = np.zeros(task.mj_model.nv)
    qvel[0] = 1.2
    action = jnp.full(21, 0.5)
    expected = 1.2 + 0.1 * 1.0 + 1.0 + 1.0 - 0.002 * 21 * 0.25
    assert float(task.reward(data_with(task, qpos, qvel), action)) == pytest.approx(expected, rel=1e-5)
    qpos[2] = 0.8  # Δh = −0.04 → −200·0.0016
    expected_low = 1.2 + 0.1 + 1.0 - 200 * 0.04**2 - 0.002 * 21 * 0.25
    assert float(task.reward(data_with(task, qpos, qvel), action)) == pytest.approx(expected_low, rel=1e-4)
    assert task.observation(data_with(task, qpos, qvel), action).shape == (76,)


def test_quadruped_reward_and_start_pose():
    task = make_task("quadruped")
    qpos, qvel = task.initial_state(jax.random.PRNGKey(0))
    # Hips at 0.6 rad, knees at −1.2 (± the reset noise): the feet stand under the hips.
    np.testing.assert_allclose(qpos[7:].reshape(4, 3), np.tile([0.0, 0.6, -1.2], (4, 1)), atol=task.reset_noise)
    pitched = np.array(task.mj_model.qpos0)
    pitched[2] = 0.42  # Δh = clip(0.42 − 0.4, −1, 0.05) = 0.02 → 10·0.02
    pitched[3:7] = [np.cos(0.3 / 2), 0, np.sin(0.3 / 2), 0]  # pitched 0.3 rad about y
    qvel = np.zeros(task.mj_model.nv)
    qvel[0] = 1.5
    action = jnp.full(12, 0.5)
    up = heading = np.cos(0.3)
    expected = 1.5 + 0.1 * up + heading + 10 * 0.02 - 0.005 * 12 * 0.25
    assert float(task.reward(data_with(task, pitched, qvel), action)) == pytest.approx(expected, rel=1e-5)
    pitched[2] = 0.3  # Δh = −0.1 → −200·0.01
    expected_low = 1.5 + 0.1 * up + heading - 2.0 - 0.005 * 12 * 0.25
    assert float(task.reward(data_with(task, pitched, qvel), action)) == pytest.approx(expected_low, rel=1e-5)
    assert not bool(task.is_terminated(data_with(task, pitched, qvel)))
    pitched[2] = 0.24
    assert bool(task.is_terminated(data_with(task, pitched, qvel)))


def test_observation_sizes_match_shac(task):
    expected = {
        "cartpole_swingup": (5, 1),
        "cartpole_balance": (5, 1),
        "hopper": (11, 3),
        "cheetah": (17, 6),
        "ant": (37, 8),
        "humanoid": (76, 21),
        "quadruped": (49, 12),
    }
    assert (task.obs_dim, task.action_dim) == expected[task.name]


def test_reset_noise_and_shapes():
    task = make_task("cartpole_swingup")
    state = jax.jit(task.reset, static_argnums=1)(jax.random.PRNGKey(3), 256)
    angle, velocity = np.asarray(state.data.qpos[:, 1]), np.asarray(state.data.qvel)
    assert np.all(np.abs(angle - np.pi) <= np.pi / 12 + 1e-6) and np.std(angle) > 0.05
    assert np.all(np.abs(velocity) <= 0.05 + 1e-6) and np.std(velocity) > 0.01
    assert state.obs.shape == (256, 5) and state.prev_action.shape == (256, 1)
    assert not bool(state.done.any())


@pytest.fixture(scope="module")
def cartpole_step():
    """Cart-pole's jitted step on 3 envs and a fresh state: one compile shared by the step tests
    (same shapes and strongly typed inputs in each, so none of them compiles it again)."""
    task = make_task("cartpole_swingup")
    return task, jax.jit(task.step), task.reset(jax.random.PRNGKey(0), 3)


def test_termination_auto_resets_and_keeps_final_observation(cartpole_step):
    task, step, state = cartpole_step
    data = state.data.replace(qpos=state.data.qpos.at[0, 0].set(2.49), qvel=state.data.qvel.at[0, 0].set(3.0))
    after = step(state.replace(data=data), jnp.ones((3, 1)))
    assert after.terminated.tolist() == [True, False, False] and not after.truncated.any()
    assert float(after.final_obs[0, 0]) >= 2.5  # the state the step reached
    assert abs(float(after.obs[0, 0])) < 1e-6  # a fresh episode: cart at the centre
    assert float(after.data.qpos[0, 1]) == pytest.approx(np.pi, abs=np.pi / 12 + 1e-6)
    assert after.step_count.tolist() == [0, 1, 1]
    np.testing.assert_array_equal(after.prev_action[0], [0.0])
    np.testing.assert_allclose(after.final_obs[1], after.obs[1])


def test_time_limit_truncates_not_terminates(cartpole_step):
    task, step, state = cartpole_step
    state = state.replace(step_count=jnp.array([task.episode_length - 1, 5, task.episode_length - 1], jnp.int32))
    after = step(state, jnp.zeros((3, 1)))
    assert after.truncated.tolist() == [True, False, True]
    assert not after.terminated.any()
    assert after.step_count.tolist() == [0, 6, 0]
    np.testing.assert_allclose(after.final_obs[1], after.obs[1])
    assert not np.allclose(after.final_obs[0], after.obs[0])


def test_actions_are_clipped_to_unit_range(cartpole_step):
    _, step, state = cartpole_step
    same_start = jax.tree.map(lambda x: jnp.broadcast_to(x[:1], x.shape), state.data)  # env 0's state in all 3
    qpos = step(state.replace(data=same_start), jnp.array([[5.0], [1.0], [0.2]], jnp.float32)).data.qpos
    np.testing.assert_allclose(qpos[0], qpos[1])  # 5 acts as 1
    assert not np.allclose(qpos[0], qpos[2])  # and the action does move the cart


def test_bad_input_errors_name_the_value():
    with pytest.raises(ValueError, match="unknown task 'walker'.*cartpole_swingup"):
        make_task("walker")
    task = make_task("cartpole_swingup")
    state = task.reset(jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match=r"shape \(2, 3\).*needs \(2, 1\)"):
        task.step(state, jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        task.step(state, jnp.array([[0.0], [jnp.nan]]))
    with pytest.raises(ValueError, match="num_envs"):
        task.reset(jax.random.PRNGKey(0), 0)

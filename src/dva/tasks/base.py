"""The batched, differentiable task API shared by every algorithm.

A :class:`Task` owns one MuJoCo model (MJX, JAX implementation, so that ``jax.grad`` flows through
the physics) and exposes two pure functions over a batch of environments::

    state = task.reset(key, num_envs)
    state = task.step(state, action)      # action in [-1, 1], shape (num_envs, action_dim)

Both are jittable and differentiable with respect to the action and the physics state. ``step``
auto-resets finished environments; the observation *before* the reset is kept in
``state.final_obs`` and ``terminated`` (a failure: no bootstrap) is kept apart from ``truncated``
(time-out: the critic bootstraps from ``final_obs``).
"""

from __future__ import annotations

import abc
from importlib import resources
from typing import ClassVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from dva.errors import DvaUsageError
from dva.tasks.physics import (
    PenaltyContact,
    check_joint_transmissions,
    check_physics,
    floor_contact_points,
    implicit_gradient_substep,
    joint_forces,
    penalty_forces,
    penalty_step,
)
from dva.tasks.tree import KinematicTree

CONTROL_DT = 1.0 / 60.0  # the paper's control rate (60 Hz)


class EnvState(struct.PyTreeNode):
    """State of a batch of environments; every leaf has a leading ``num_envs`` axis."""

    data: mjx.Data  # physics state
    obs: jax.Array  # (N, obs_dim) state observation after any auto-reset
    final_obs: jax.Array  # (N, obs_dim) observation reached by the last step, before auto-reset
    final_qpos: jax.Array  # (N, nq) joint positions reached by the last step, before auto-reset (to render)
    reward: jax.Array  # (N,) reward of the last step
    terminated: jax.Array  # (N,) bool, the last step ended the episode by failure
    truncated: jax.Array  # (N,) bool, the last step hit the episode length
    step_count: jax.Array  # (N,) int32, steps taken in the current episode
    prev_action: jax.Array  # (N, action_dim) last action applied (part of some observations)
    key: jax.Array  # (N, 2) per-env random keys for resets
    # (N, H, W, 3·k) stacked camera frames, kept up to date by dva.envs.observations.PixelObservations (which
    # sets it to an empty (N, 0) array when it renders nothing); None on a bare task's state.
    pixels: jax.Array | None = None

    @property
    def frames(self) -> jax.Array:
        """The stacked camera frames of a :class:`~dva.envs.observations.PixelObservations` env."""
        if self.pixels is None:
            raise ValueError("a bare task's state has no frames: PixelObservations renders them")
        return self.pixels

    @property
    def done(self) -> jax.Array:
        """Episode ended on the last step, for either reason."""
        return self.terminated | self.truncated


class Task(abc.ABC):
    """A MuJoCo task with reward, termination and reset noise; see the module docstring.

    Subclasses give the model (``build_spec``) and the per-environment functions
    ``initial_state``, ``observation``, ``reward`` and ``is_terminated``.
    """

    name: ClassVar[str]
    episode_length: ClassVar[int] = 1000
    camera: ClassVar[str] = "track"  # the camera the pixel observations come from
    physics: str = "penalty"  # the default contact model (dva.tasks.physics); an instance holds its own
    # Penalty contacts (dflex's): 16 substeps at 60 Hz, parameters per robot.
    penalty_substeps: ClassVar[int] = 16
    penalty_contact: ClassVar[PenaltyContact] = PenaltyContact(ke=2e4, kd=1e3, kf=1e3, mu=0.9)
    # MuJoCo soft constraints: substeps and contact softness (solref = (time constant, damping
    # ratio), solimp); softer than MuJoCo's default 0.02 s keeps multi-step gradients bounded.
    mujoco_substeps: ClassVar[int] = 4
    contact_solref: ClassVar[tuple[float, float]] = (0.02, 1.0)
    contact_solimp: ClassVar[tuple[float, ...]] = (0.9, 0.95, 0.001, 0.5, 2.0)
    converged_iterations: ClassVar[int] = 100  # the forward solve of physics="mujoco"
    # Armature (reflected rotor inertia) on every joint, the root's included, as dflex sets it;
    # None keeps the MJCF's values.
    armature: ClassVar[float | None] = None

    def __init__(self, physics: str | None = None) -> None:
        physics = physics or type(self).physics
        check_physics(physics)
        self.physics = physics
        self.substeps: int = self.penalty_substeps if physics == "penalty" else self.mujoco_substeps
        spec = self.build_spec()
        add_scene(spec)
        if self.armature is not None:
            for joint in spec.joints:
                joint.armature = self.armature
        for geom in spec.geoms:
            geom.solref = self.contact_solref
            geom.solimp = self.contact_solimp
        for pair in spec.pairs:
            pair.solref = self.contact_solref
            pair.solimp = self.contact_solimp
        spec.option.timestep = CONTROL_DT / self.substeps
        # One solver iteration: the solver's while_loop is not reverse-differentiable otherwise
        # (physics="mujoco" adds a converged solve outside the gradient; penalty has no solve).
        spec.option.iterations = 1
        spec.option.ls_iterations = 4
        # Pyramidal friction cones: MJX's elliptic cones take sqrt(0) for idle contacts, which
        # makes every gradient NaN.
        spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
        if physics == "penalty":  # contacts, limits, springs and damping become explicit forces
            spec.option.disableflags |= (
                mujoco.mjtDisableBit.mjDSBL_CONTACT
                | mujoco.mjtDisableBit.mjDSBL_LIMIT
                | mujoco.mjtDisableBit.mjDSBL_EULERDAMP
            )
        self.mj_model: mujoco.MjModel = spec.compile()
        if physics == "penalty":
            self.contact_points = floor_contact_points(self.mj_model)
            self.joints = joint_forces(self.mj_model, self.penalty_contact.limit_kd)
            self.tree = KinematicTree.from_model(self.mj_model)
            check_joint_transmissions(self.mj_model)
            # Applied by penalty_forces instead; MuJoCo's passive forces would count them twice.
            self.mj_model.dof_damping[:] = 0.0
            self.mj_model.jnt_stiffness[:] = 0.0
        self.model: mjx.Model = mjx.put_model(self.mj_model)
        if physics == "mujoco":
            converged = spec.compile()
            converged.opt.iterations = self.converged_iterations
            converged.opt.ls_iterations = 50
            self.converged_model: mjx.Model = mjx.put_model(converged)
        self._data0 = mjx.make_data(self.model)
        self.action_dim: int = self.mj_model.nu
        qpos, qvel = self.initial_state(jax.random.PRNGKey(0))
        obs = self.observation(self._data0.replace(qpos=qpos, qvel=qvel), jnp.zeros(self.action_dim))
        self.obs_dim: int = int(obs.shape[-1])

    # ---- what each task defines -------------------------------------------------------------
    @abc.abstractmethod
    def build_spec(self) -> mujoco.MjSpec:
        """The robot's MJCF as an editable spec (floor, lights and materials are added after)."""

    @abc.abstractmethod
    def initial_state(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """A random initial ``(qpos, qvel)`` for one environment."""

    @abc.abstractmethod
    def observation(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """The low-dimensional state observation (SHAC's contents) of one environment."""

    @abc.abstractmethod
    def reward(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """The reward of one environment after a step with ``action`` (clipped to [-1, 1])."""

    @abc.abstractmethod
    def is_terminated(self, data: mjx.Data) -> jax.Array:
        """Whether one environment has failed (a bool scalar)."""

    # ---- the batched API --------------------------------------------------------------------
    def reset(self, key: jax.Array, num_envs: int) -> EnvState:
        """Fresh episodes for ``num_envs`` environments."""
        if not isinstance(num_envs, int) or num_envs < 1:
            raise DvaUsageError(f"num_envs must be a positive int, got {num_envs!r}")
        keys = jax.random.split(key, num_envs)
        env_keys, reset_keys = jax.vmap(jax.random.split, out_axes=1)(keys)
        data, obs = jax.vmap(self._reset_one)(reset_keys)
        zeros = jnp.zeros((num_envs,), bool)
        return EnvState(
            data=data,
            obs=obs,
            final_obs=obs,
            final_qpos=data.qpos,
            reward=jnp.zeros((num_envs,), obs.dtype),
            terminated=zeros,
            truncated=zeros,
            step_count=jnp.zeros((num_envs,), jnp.int32),
            prev_action=jnp.zeros((num_envs, self.action_dim), obs.dtype),
            key=env_keys,
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Advance every environment by one control step (1/60 s), auto-resetting finished ones."""
        num_envs = state.step_count.shape[0]
        if action.shape != (num_envs, self.action_dim):
            raise DvaUsageError(
                f"action has shape {tuple(action.shape)}; task {self.name!r} with {num_envs} envs "
                f"needs ({num_envs}, {self.action_dim})"
            )
        if not isinstance(action, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(action))):
            raise DvaUsageError(f"action contains non-finite values (NaN or inf): {np.asarray(action)}")
        action = jnp.clip(action, -1.0, 1.0)
        data = jax.vmap(self.physics_step)(state.data, action)
        obs = jax.vmap(self.observation)(data, action)
        reward = jax.vmap(self.reward)(data, action)
        bounded = lambda x: jnp.all(jnp.abs(x) < 1e6, axis=-1)  # NaN fails this too
        finite = jnp.all(jnp.isfinite(obs), axis=-1) & jnp.isfinite(reward) & bounded(data.qpos) & bounded(data.qvel)
        # A diverged simulation is a failure: reset it rather than poison the batch with NaN.
        terminated = jax.vmap(self.is_terminated)(data) | ~finite
        step_count = state.step_count + 1
        truncated = (step_count >= self.episode_length) & ~terminated
        done = terminated | truncated

        env_keys, reset_keys = jax.vmap(jax.random.split, out_axes=1)(state.key)
        reset_data, reset_obs = jax.vmap(self._reset_one)(reset_keys)
        final_qpos = data.qpos
        data = jax.tree.map(lambda r, d: _where_env(done, r, d), reset_data, data)
        return state.replace(  # a wrapper's fields (pixels) pass through; the wrapper updates them
            data=data,
            obs=_where_env(done, reset_obs, obs),
            final_obs=jnp.where(finite[:, None], obs, 0.0),
            final_qpos=final_qpos,
            reward=jnp.where(finite, reward, 0.0),
            terminated=terminated,
            truncated=truncated,
            step_count=jnp.where(done, 0, step_count),
            prev_action=_where_env(done, jnp.zeros_like(action), action),
            key=env_keys,
        )

    def physics_step(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        """``substeps`` physics steps of one environment with the control held at ``action``."""
        data = data.replace(ctrl=action)
        # Full float32 matrix products: GPUs would otherwise run them in TF32, whose gradients
        # through long rollouts are too coarse.
        with jax.default_matmul_precision("highest"):
            if self.physics == "penalty":
                forces = lambda qpos, qvel, bodies: penalty_forces(
                    qpos, qvel, bodies, self.contact_points, self.penalty_contact, self.joints
                )
                return penalty_step(self.model, self.tree, data, self.substeps, forces)
            substep = lambda d, _: (implicit_gradient_substep(self.model, self.converged_model, d), None)
            return jax.lax.scan(substep, data, None, length=self.substeps)[0]

    def _reset_one(self, key: jax.Array) -> tuple[mjx.Data, jax.Array]:
        qpos, qvel = self.initial_state(key)
        data = self._data0.replace(qpos=qpos, qvel=qvel)
        return data, self.observation(data, jnp.zeros(self.action_dim))

    # ---- helpers ------------------------------------------------------------------------------
    def qpos0(self) -> jax.Array:
        """The model's reference joint positions."""
        return jnp.asarray(self.mj_model.qpos0)


def _where_env(mask: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    """Per-env select: ``mask`` is (N,), ``a`` and ``b`` are (N, ...)."""
    return jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b)


def load_asset_spec(filename: str) -> mujoco.MjSpec:
    """Parse one of the MJCF files shipped in ``dva/tasks/assets``."""
    xml = resources.files("dva.tasks").joinpath("assets", filename).read_text()
    return mujoco.MjSpec.from_string(xml)


def add_scene(spec: mujoco.MjSpec) -> None:
    """Add the shared scene: checkered floor (the only thing robots collide with) and lights.

    The floor is mid grey and blue so that the orange/blue/green robots stand out; two directional
    lights (no position, so they suit tracking cameras anywhere on the floor).
    """
    spec.add_texture(
        name="checker",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        width=256,
        height=256,
        rgb1=[0.32, 0.36, 0.42],
        rgb2=[0.18, 0.2, 0.25],
    )
    material = spec.add_material(name="floor")
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "checker"
    material.texrepeat = [1.0, 1.0]
    material.texuniform = True
    world = spec.worldbody
    world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[100.0, 100.0, 0.1],
        material="floor",
        contype=0,
        conaffinity=1,
    )
    world.add_light(
        name="key",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[0, 0, 5],
        dir=[0.3, 0.5, -1.0],
        diffuse=[0.75, 0.75, 0.75],
        specular=[0.2, 0.2, 0.2],
        castshadow=False,
    )
    world.add_light(
        name="fill",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[0, 0, 5],
        dir=[-0.4, -0.2, -1.0],
        diffuse=[0.3, 0.3, 0.3],
        specular=[0.0, 0.0, 0.0],
        castshadow=False,
    )
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]

"""Presets: each algorithm's hyperparameters per task, as plain data (the code that runs them is in
:mod:`dva.algorithms`; :func:`dva.algorithms.make_config` assembles a config from these)."""

from __future__ import annotations

from typing import Literal

from dva.envs.factory import dmc_domain_task, unit_rewards

PresetName = Literal["paper", "cpu"]
PRESETS: tuple[str, ...] = ("paper", "cpu")

# ---- the short-horizon actor-critic family (D.Va, SHAC, DPG on state, visual SHAC) -----------------
# The paper's Table 7 (+ epochs from its code, as the learning-rate decay length). The Table has
# no Half-Cheetah row: its values are the authors' code's Cheetah configuration (the Hopper's
# networks, the Ant's critic learning rate 2e-3, for D.Va and visual SHAC alike). The quadruped
# uses the Ant's row, Cart-pole balance the swing-up's (the paper gives none of their own).
SHAC_PAPER: dict[str, dict] = {
    "cartpole_swingup": dict(
        trunk=64,
        actor_hidden=(64, 64),
        critic_hidden=(64, 64),
        critic_lr=2e-4,
        target_alpha=0.2,
        lr_decay_iterations=4000,
    ),
    "cartpole_balance": dict(
        trunk=64,
        actor_hidden=(64, 64),
        critic_hidden=(64, 64),
        critic_lr=2e-4,
        target_alpha=0.2,
        lr_decay_iterations=4000,
    ),
    "hopper": dict(
        trunk=128,
        actor_hidden=(128, 64, 32),
        critic_hidden=(64, 64),
        critic_lr=2e-4,
        target_alpha=0.2,
        lr_decay_iterations=30000,
    ),
    "cheetah": dict(
        trunk=128,
        actor_hidden=(128, 64, 32),
        critic_hidden=(64, 64),
        critic_lr=2e-3,
        target_alpha=0.2,
        lr_decay_iterations=30000,
    ),
    "ant": dict(
        trunk=128,
        actor_hidden=(128, 64, 32),
        critic_hidden=(64, 64),
        critic_lr=2e-3,
        target_alpha=0.2,
        lr_decay_iterations=30000,
    ),
    "quadruped": dict(
        trunk=128,
        actor_hidden=(128, 64, 32),
        critic_hidden=(64, 64),
        critic_lr=2e-3,
        target_alpha=0.2,
        lr_decay_iterations=30000,
    ),
    "humanoid": dict(
        trunk=256,
        actor_hidden=(256, 128),
        critic_hidden=(128, 128),
        critic_lr=5e-4,
        target_alpha=0.995,
        lr_decay_iterations=60000,
    ),
}
# SHAC on the state decays its learning rates over its reference code's 2000 iterations (the rows
# above are D.Va's, whose pixel actors train for longer).
LEGGED_TASKS = ("hopper", "cheetah", "ant", "humanoid", "quadruped")
SHAC_STATE_PAPER: dict[str, dict] = {task: dict(lr_decay_iterations=2000) for task in LEGGED_TASKS}
# Visual SHAC's own horizons and env counts (the paper's: 32/32/8/32 steps, 64/64/32/32 envs on
# Cart-pole/Hopper/Ant/Humanoid).
VISUAL_SHAC_PAPER: dict[str, dict] = {"ant": dict(horizon=8, num_envs=32), "humanoid": dict(num_envs=32)}
# The CPU preset: the same method and networks at what a 2-core CPU affords — 16 envs, 48² images
# and a 16-step horizon, so an iteration costs a fraction of the paper's (the pixel encoder is most
# of it: docs/results.md#where-dvas-time-goes-on-the-cpu) and the actor updates twice as often per
# env step.
SHAC_CPU = dict(num_envs=16, image_size=48, horizon=16, lr_decay_iterations=1000)
# The learning rates decay over about the run a task is measured with: on the legged robots 4000
# iterations of SHAC on the state (≈ 17 minutes; docs/results.md#hopper-shac-on-the-state).
SHAC_CPU_TASKS: dict[str, dict] = {task: dict(lr_decay_iterations=4000) for task in LEGGED_TASKS}
# An actor on pixels learns over more iterations than one on the state: 7000 on the legged robots
# (about two hours on one core; docs/results.md#hopper-dva-from-pixels), 14000 on the Humanoid
# (its long run: docs/results.md#the-humanoid-from-pixels-one-long-run), and on Cart-pole the
# iterations of the 15-minute main job (docs/results.md#cart-pole-from-pixels-the-main-job).
SHAC_CPU_PIXEL_TASKS: dict[str, dict] = {
    **{task: dict(lr_decay_iterations=7000) for task in LEGGED_TASKS},
    "humanoid": dict(lr_decay_iterations=14000),
    # The Cheetah from pixels keeps the paper's batch (64 envs × 32 steps, its decay), only at 48²:
    # at 16 × 16 `dva-privileged` flipped onto its back and stayed there; at the paper's batch `dva`
    # runs within two CPU hours (docs/results.md#cheetah-dva-from-pixels).
    "cheetah": dict(num_envs=64, horizon=32, lr_decay_iterations=SHAC_PAPER["cheetah"]["lr_decay_iterations"]),
    **{task: dict(lr_decay_iterations=4500) for task in ("cartpole_swingup", "cartpole_balance")},
}
# The privileged variants (`dva-privileged`, `drqv2-privileged`): the pixel encoder also learns to
# predict the normalised simulator state, at this weight under every preset and on every task
# (docs/algorithms.md; its effect on D.Va: docs/results.md#hopper-dva-from-pixels).
STATE_PREDICTION_WEIGHT = 10.0


# ---- the off-policy pixel baselines (DrQ-v2, CURL) -----------------------------------------------
# This project's tasks pay up to ≈ 10 per control step; dm_control's, for which DrQ-v2's and
# CURL's learning rates and CURL's initial temperature were tuned, at most 1. Their critics
# therefore learn 0.1 × the reward on our tasks (returns are logged unscaled).
OFF_POLICY_REWARD_SCALE = 0.1

# ---- DrQ-v2 (docs/algorithms.md) ----------------------------------------------------------------------
DRQV2_PAPER: dict[str, dict] = {
    "cartpole_swingup": dict(num_envs=16, updates_per_iteration=8),
    "cartpole_balance": dict(num_envs=16, updates_per_iteration=8),
    **{task: dict(num_envs=32, updates_per_iteration=16) for task in ("hopper", "cheetah", "ant", "quadruped")},
    "humanoid": dict(num_envs=32, updates_per_iteration=16, lr=8e-5, std_decay_steps=2_000_000, feature_dim=100),
}
# The CPU preset keeps the method (augmentation, clipped double Q, n-step returns, action repeat,
# the std schedule) at a size one core updates several times a second: 48² images, batch 64, 8
# updates per round of the 16 envs (one per 2 agent steps, DrQ-v2's own rate; at action repeat 2
# one per 4 env steps), 256-wide MLPs, a 100k-step replay
# (690 MB of 48² frames) and the exploration std decaying over the env steps a short CPU run takes
# (docs/results.md#drq-v2-and-curl-on-cart-pole-balance).
DRQV2_CPU = dict(
    num_envs=16,
    image_size=48,
    batch_size=64,
    updates_per_iteration=8,
    hidden=(256, 256),
    replay_size=100_000,
    std_decay_steps=20_000,
)
# On the legged robots 4 updates per round (one per 4 agent steps): of 4, 8 and 16 it ends highest
# on the Hopper in 30 minutes on one core, two seeds; its noise decay stays at 20k env steps, which
# 50k and 100k did not beat (docs/results.md#the-baselines-settings-for-the-budget-on-the-hopper).
DRQV2_CPU_LEGGED = dict(DRQV2_CPU, updates_per_iteration=4)


# On dm_control's own tasks (rewards in [0, 1]) DrQ-v2 runs as its authors ran it: the reward
# unscaled, 16 envs with 8 updates per round (its one update per 2 agent steps), and under either
# preset its per-task exploration schedule, linear(1.0, 0.1, S) over S agent steps (S 100k on its
# "easy" tasks, 500k "medium", 2M "hard"; here in env steps, × its action repeat of 2).
DRQV2_DMC_EASY = {
    ("cartpole", "balance"), ("cartpole", "balance_sparse"), ("cartpole", "swingup"), ("ball_in_cup", "catch"),
    ("finger", "spin"), ("hopper", "stand"), ("pendulum", "swingup"), ("walker", "stand"), ("walker", "walk"),
}  # fmt: skip
DRQV2_DMC_HARD = {("humanoid", "stand"), ("humanoid", "walk"), ("humanoid", "run")}


def drqv2_dmc_std_decay_steps(task: str) -> int:
    """DrQ-v2's exploration-std decay on the dm_control task ``task`` (``dmc:<domain>-<task>``), in env steps."""
    key = dmc_domain_task(task)
    agent_steps = 100_000 if key in DRQV2_DMC_EASY else 2_000_000 if key in DRQV2_DMC_HARD else 500_000
    return 2 * agent_steps


def drqv2_preset(task: str, preset: str) -> dict:
    """DrQ-v2's hyperparameters of ``task`` under ``preset``."""
    if unit_rewards(task):  # dm_control's tasks: as its authors ran DrQ-v2 there
        values = dict(DRQV2_PAPER["cartpole_swingup"], **(DRQV2_CPU if preset == "cpu" else {}))
        return dict(values, reward_scale=1.0, std_decay_steps=drqv2_dmc_std_decay_steps(task))
    row = DRQV2_PAPER.get(task, DRQV2_PAPER["hopper"])  # a task without a row: the legged robots'
    cpu = DRQV2_CPU_LEGGED if task in LEGGED_TASKS else DRQV2_CPU
    return dict(row, reward_scale=OFF_POLICY_REWARD_SCALE, **(cpu if preset == "cpu" else {}))


# ---- CURL (docs/algorithms.md) ---------------------------------------------------------------------------
# The paper's settings are the same on every task. The CPU preset, like DrQ-v2's: 48² images,
# 4 updates per round, 256-wide MLPs.
CURL_CPU = dict(image_size=48, updates_per_iteration=4, hidden=(256, 256))


def curl_preset(task: str, preset: str) -> dict:
    """CURL's hyperparameters under ``preset`` (task-independent)."""
    reward_scale = 1.0 if unit_rewards(task) else OFF_POLICY_REWARD_SCALE
    return dict(CURL_CPU if preset == "cpu" else {}, reward_scale=reward_scale)


# ---- DreamerV3 (docs/algorithms.md) --------------------------------------------------------------------
# The paper's settings are the same on every task (network sizes: the reference's "S" model). The
# CPU preset keeps the method — RSSM with 32 × 32 categorical latents and unimix, symlog two-hot
# heads, free bits, λ-returns with return normalisation, the slow critic, 4 envs — at a size a
# CPU core can afford: 128-wide networks, CNN depth 16, 8 × 32 sequences of 48² frames, a train
# ratio of 16 (one update per 4 steps of the 4 envs: DrQ-v2's CPU pace in env steps per second;
# `python benchmarks/dreamer_update.py` times an update), a 100k-step replay, and learning rates
# above the reference's for this smaller model (docs/results.md#dreamerv3-on-the-state-cart-pole).
DREAMERV3_CPU = dict(
    model_lr=6e-4,
    actor_lr=8e-5,
    critic_lr=8e-5,
    deter=128,
    units=128,
    mlp_units=128,  # the state's encoder and decoder: the heads' 2 × 128, not the reference's 5 × 1024
    mlp_layers=2,
    cnn_depth=16,
    image_size=48,
    batch_size=8,
    batch_length=32,
    train_ratio=16.0,
    replay_size=100_000,
)


# On the state the actor's learning rate is 2e-4 (docs/results.md#dreamerv3-on-the-state-cart-pole:
# at 8e-5 a seed learned balance and drifted back); the pixel agent, whose world model limits it
# on a CPU, keeps 8e-5.
DREAMERV3_STATE_CPU = dict(DREAMERV3_CPU, actor_lr=2e-4)


# On the legged robots' pixels a train ratio of 256 (four updates per step of the 4 envs): of 16, 64
# and 256 it ends highest on the Hopper in 30 minutes on one core, two seeds, though it takes the
# fewest env steps (docs/results.md#the-baselines-settings-for-the-budget-on-the-hopper).
DREAMERV3_CPU_LEGGED = dict(DREAMERV3_CPU, train_ratio=256.0)


def dreamerv3_preset(task: str, preset: str, observation: Literal["pixels", "state"] = "pixels") -> dict:
    """DreamerV3's hyperparameters of ``task`` under ``preset`` for its ``observation``."""
    if preset != "cpu":
        return {}
    if observation == "state":
        return dict(DREAMERV3_STATE_CPU)
    return dict(DREAMERV3_CPU_LEGGED if task in LEGGED_TASKS else DREAMERV3_CPU)


# ---- TD-MPC2 (docs/algorithms.md) ----------------------------------------------------------------------
# The paper's preset is the reference's defaults (its 5M model) on every task. The CPU preset keeps
# the method (SimNorm latents, two-hot heads, a Q ensemble's random pairs, MPPI with a policy
# prior, ρ-weighted 3-step rollouts, one update per agent step) at the reference's smallest
# latent (128) with two Q members as its "1M" model, 128-wide networks, batch 64, and a planner
# of 128 samples (6 from the prior), 16 elites and 3 refits. Pixels stay at the reference's 64²:
# 48² leave its encoder a 2×2 grid, from which it did not learn balance
# (docs/results.md#td-mpc2-cart-pole-balance). A 100k-step replay, as the other CPU presets'.
TDMPC2_CPU = dict(
    replay_size=100_000,
    latent_dim=128,
    mlp_dim=128,
    num_q=2,
    batch_size=64,
    num_samples=128,
    num_elites=16,
    num_pi_trajs=6,
    mppi_iterations=3,
)


# On the legged robots' pixels two updates per agent step: of 0.5, 1 and 2 it ends highest on the
# Hopper in 30 minutes on one core, two seeds, though it takes the fewest env steps
# (docs/results.md#the-baselines-settings-for-the-budget-on-the-hopper).
TDMPC2_CPU_LEGGED = dict(TDMPC2_CPU, updates_per_iteration=8)


def tdmpc2_preset(task: str, preset: str, observation: Literal["pixels", "state"] = "pixels") -> dict:
    """TD-MPC2's hyperparameters of ``task`` under ``preset`` for its ``observation``."""
    if preset != "cpu":
        return {}
    return dict(TDMPC2_CPU_LEGGED if task in LEGGED_TASKS and observation == "pixels" else TDMPC2_CPU)


# ---- state-to-visual DAgger (docs/algorithms.md) -------------------------------------------------------
# The student has D.Va's networks for the task (SHAC_PAPER's trunk and actor); the paper's 64 envs
# × 32 steps, or the CPU preset's 16 × 16 at 48² with a 20k-observation replay (415 MB).
DAGGER_CPU = dict(num_envs=16, horizon=16, image_size=48, replay_size=20_000, updates_per_iteration=8)


def dagger_preset(task: str, preset: str) -> dict:
    """DAgger's hyperparameters of ``task`` under ``preset``."""
    row = SHAC_PAPER.get(task, {})  # a task without a row: SHACConfig's defaults
    student = {key: row[key] for key in ("trunk", "actor_hidden") if key in row}
    return dict(student, **(DAGGER_CPU if preset == "cpu" else {}))


ActorInput = Literal["state", "pixels", "differentiable-pixels"]


def shac_preset(task: str, preset: str, actor_input: ActorInput = "state") -> dict:
    """The SHAC-family hyperparameters of ``task`` under ``preset`` for an actor on ``actor_input``:
    the state (SHAC, DPG), Warp's pixels (D.Va) or differentiably rendered pixels (visual SHAC).
    Names and task are checked by the caller."""
    values = dict(SHAC_PAPER.get(task, {}))  # a task without a row: SHACConfig's defaults (Cart-pole's)
    if actor_input == "state":
        values.update(SHAC_STATE_PAPER.get(task, {}))
    if actor_input == "differentiable-pixels":
        values.update(VISUAL_SHAC_PAPER.get(task, {}))
    if preset == "cpu":
        per_task = SHAC_CPU_TASKS if actor_input == "state" else SHAC_CPU_PIXEL_TASKS
        values.update(SHAC_CPU, **per_task.get(task, {}))
    return values


def privileged(preset_values: dict) -> dict:
    """A preset's values with the state-prediction loss on (the ``-privileged`` variants)."""
    return dict(preset_values, state_prediction=STATE_PREDICTION_WEIGHT)

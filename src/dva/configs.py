"""Presets: each algorithm's hyperparameters per task, as plain data (the code that runs them is in
:mod:`dva.algorithms`; :func:`dva.algorithms.make_config` assembles a config from these)."""

from __future__ import annotations

from typing import Literal

from dva.envs.registry import dmc_domain_task, is_dmc

PresetName = Literal["paper", "cpu"]
PRESETS: tuple[str, ...] = ("paper", "cpu")

# ---- the short-horizon actor-critic family (D.Va, SHAC, DPG on state, visual SHAC) -----------------
# The paper's Table 7 (+ epochs from its code, as the learning-rate decay length). Half-Cheetah
# and the quadruped use the Hopper/Ant rows, Cart-pole balance the swing-up's (the paper gives
# none of their own).
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
        critic_lr=2e-4,
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
# SHAC on the state decays its learning rates over its reference runs' 2000 iterations (the rows
# above are D.Va's, whose pixel actors train for longer).
LEGGED_TASKS = ("hopper", "cheetah", "ant", "humanoid", "quadruped")
SHAC_STATE_PAPER: dict[str, dict] = {task: dict(lr_decay_iterations=2000) for task in LEGGED_TASKS}
# Visual SHAC's own horizons and env counts (the paper's: 32/32/8/32 steps, 64/64/32/32 envs on
# Cart-pole/Hopper/Ant/Humanoid).
VISUAL_SHAC_PAPER: dict[str, dict] = {"ant": dict(horizon=8, num_envs=32), "humanoid": dict(num_envs=32)}
# What a 2-core CPU can afford: the same method and networks, fewer envs, smaller images (the
# conv encoder dominates an iteration on CPU; docs/results.md) and a 16-step horizon: half the cost per
# iteration and twice the updates per env step (Cart-pole from pixels: return 600-900 after
# 100k steps, where h = 32 was still at the collapsed ~110).
SHAC_CPU = dict(num_envs=16, image_size=48, horizon=16, lr_decay_iterations=1000)
# The legged robots learn for longer: a 1000-iteration decay left SHAC on Hopper (state) at the
# final learning rate after 4 of its 30 minutes, its evaluations stuck at 1000–1500 after a 3052
# peak; 4000 iterations ≈ 17 minutes of SHAC on state.
SHAC_CPU_TASKS: dict[str, dict] = {task: dict(lr_decay_iterations=4000) for task in LEGGED_TASKS}
# An actor on pixels needs more iterations than one on the state: D.Va on Hopper with the 4000
# decay reached 1541 / 1056 / 747 in 2 hours (seeds 1 / 2 / 0), with a decay over 7000
# iterations 3783 / 1136 (seeds 4 / 3, measured on the previous Hopper model) — an iteration takes ≈ 1 s on 2 cores.
# On Cart-pole the decay spans the 15-minute main job (≈ 4500 iterations of 0.2 s on 2 cores):
# decayed over 1000 iterations the actor sat at the final learning rate for most of the run and
# its evaluations fell back (1730 at 5 minutes, 770 at 10); one core, seed 0, 15 minutes: median
# of the last ten evaluations 1360 with the 1000-iteration decay, 1680 with 4500.
# The Humanoid's pixel run is 8 hours: its decay spans 14k iterations, the whole run when an
# iteration took ≈ 2 s on one core, ≈ 4.7 hours at today's ≈ 1.2 s (its 2-hour runs, 3.4k
# iterations into a 7000-iteration decay, were still rising at the end).
SHAC_CPU_PIXEL_TASKS: dict[str, dict] = {
    **{task: dict(lr_decay_iterations=7000) for task in LEGGED_TASKS},
    "humanoid": dict(lr_decay_iterations=14000),
    **{task: dict(lr_decay_iterations=4500) for task in ("cartpole_swingup", "cartpole_balance")},
}
# The privileged variants (`dva-privileged`, `drqv2-privileged`): the pixel encoder also learns to
# predict the normalised simulator state, at this weight under every preset and on every task
# (docs/algorithms.md; its effect on D.Va: docs/results.md#hopper-from-pixels).
STATE_PREDICTION_WEIGHT = 10.0


# ---- the off-policy pixel baselines (DrQ-v2, CURL) -----------------------------------------------
# Our tasks pay up to ≈ 10 per control step (Cart-pole's 10 − …; Hopper ≈ 8 at 7500 per episode);
# DMC's rewards, for which DrQ-v2's and CURL's learning rates and CURL's initial temperature were
# tuned, are in [0, 1]. Their critics therefore learn 0.1 × the reward (returns are logged unscaled).
OFF_POLICY_REWARD_SCALE = 0.1

# ---- DrQ-v2 (docs/algorithms.md) ----------------------------------------------------------------------
DRQV2_PAPER: dict[str, dict] = {
    "cartpole_swingup": dict(num_envs=16, updates_per_iteration=8),
    "cartpole_balance": dict(num_envs=16, updates_per_iteration=8),
    **{task: dict(num_envs=32, updates_per_iteration=16) for task in ("hopper", "cheetah", "ant", "quadruped")},
    "humanoid": dict(num_envs=32, updates_per_iteration=16, lr=8e-5, std_decay_steps=2_000_000, feature_dim=100),
}
# The CPU preset keeps the method (augmentation, clipped double Q, n-step returns, action repeat,
# the std schedule) at a size one core updates several times a second: 48² images, batch 64 (an
# update is ≈ 90 MFLOP of convolutions per sample: batch 128 made one update per second), 8 updates
# per round (one per 4 env steps; DrQ-v2's is one per 2), 256-wide MLPs, a 100k-step replay
# (690 MB of 48² frames) and the std decay over the 20k env steps a 20-minute run takes (over
# 100k the first runs' exploration was still std 0.9 at their end, their policy untrained).
DRQV2_CPU = dict(
    num_envs=16,
    image_size=48,
    batch_size=64,
    updates_per_iteration=8,
    hidden=(256, 256),
    replay_size=100_000,
    std_decay_steps=20_000,
)


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
    if is_dmc(task):
        values = dict(DRQV2_PAPER["cartpole_swingup"], **(DRQV2_CPU if preset == "cpu" else {}))
        return dict(values, reward_scale=1.0, std_decay_steps=drqv2_dmc_std_decay_steps(task))
    row = DRQV2_PAPER.get(task, DRQV2_PAPER["hopper"])  # a task without a row: the legged robots'
    return dict(row, reward_scale=OFF_POLICY_REWARD_SCALE, **(DRQV2_CPU if preset == "cpu" else {}))


# ---- CURL (docs/algorithms.md) ---------------------------------------------------------------------------
# The paper's settings are the same on every task. The CPU preset, like DrQ-v2's: 48² images,
# 4 updates per round, 256-wide MLPs.
CURL_CPU = dict(image_size=48, updates_per_iteration=4, hidden=(256, 256))


def curl_preset(task: str, preset: str) -> dict:
    """CURL's hyperparameters under ``preset`` (task-independent)."""
    return dict(CURL_CPU if preset == "cpu" else {}, reward_scale=1.0 if is_dmc(task) else OFF_POLICY_REWARD_SCALE)


# ---- DreamerV3 (docs/algorithms.md) --------------------------------------------------------------------
# The paper's settings are the same on every task (network sizes: the reference's "S" model). The
# CPU preset keeps the method — RSSM with 32 × 32 categorical latents and unimix, symlog two-hot
# heads, free bits, λ-returns with return normalisation, the slow critic, 4 envs — at a size a
# CPU core can afford. Measured on one core of the 2-core CI box (Cart-pole): one update of the
# paper-sized model on 16 × 32 sequences of 64² images takes 8.8 s; with 128-wide networks, CNN
# depth 16 and 8 × 32 sequences 3.4 s, at 48² (the other CPU presets' size) 2.2 s. So: that
# model, and a train ratio of 16 (one update per 4 steps of the 4 envs, 32 env steps: ≈ 14 env
# steps/s, DrQ-v2's CPU pace; the paper's 512 would be 0.5 env steps/s), a 100k-step replay.
# Learning rates 6e-4 (model) and 8e-5 (actor, critic), above the reference's 1e-4 / 3e-5 for
# this smaller model: on balance from the state (seed 1, 15 minutes) these ended at a median of
# the last ten 1945, the reference's peaked at 1733 and fell to 867 (docs/results.md).
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


# On the state the actor learns faster still: with the actor at 8e-5 the balance runs learned and
# then drifted back (seed 0: best 2338, median of the last ten 1310), its Gaussian's std still
# ≈ 0.8 after 2k updates; at 2e-4 both seeds end learned (median of the last ten 1778 / 1905,
# docs/results.md). The pixel agent, whose world model is what limits it on a CPU, keeps 8e-5.
DREAMERV3_STATE_CPU = dict(DREAMERV3_CPU, actor_lr=2e-4)


def dreamerv3_preset(task: str, preset: str, observation: Literal["pixels", "state"] = "pixels") -> dict:
    """DreamerV3's hyperparameters under ``preset`` for its ``observation`` (task-independent)."""
    if preset != "cpu":
        return {}
    return dict(DREAMERV3_STATE_CPU if observation == "state" else DREAMERV3_CPU)


# ---- TD-MPC2 (docs/algorithms.md) ----------------------------------------------------------------------
# The paper's preset is the reference's defaults (its 5M model) on every task. At that size one
# iteration on Cart-pole (state, 4 envs) takes 10.3 s on a shared CPU core, 5.4 s of it planning.
# The CPU preset keeps the method (SimNorm latents, two-hot heads, a Q ensemble's random pairs,
# MPPI with a policy prior, ρ-weighted 3-step rollouts, one update per agent step) at the
# reference's smallest latent (128) with two Q members as its "1M" model, 128-wide networks,
# batch 64, and a planner of 128 samples (6 from the prior), 16 elites and 3 refits: 0.31 s per
# iteration of 4 envs (0.14 s planning, 0.06 s per update) on a shared core. With 256-wide
# networks, batch 128 and 256 samples × 4 refits an iteration took 0.93 s and swing-up from the
# state was still below random after 5k env steps (10 minutes). Pixels stay at the reference's
# 64²: 48² leave its encoder a 2×2 grid (a 128-entry latent), and balance stayed below 1.5× random
# for 47k env steps; at 64² (a 4×4 grid, 512 entries) it passed 1.9× random at 28k, for twice
# the time per iteration. A 100k-step replay, as the other CPU presets': the reference's million
# 64² frames would take 12 GB.
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


def tdmpc2_preset(task: str, preset: str) -> dict:
    """TD-MPC2's hyperparameters under ``preset`` (task-independent)."""
    return dict(TDMPC2_CPU) if preset == "cpu" else {}


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

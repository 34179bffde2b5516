"""``dva train`` plumbing: logs, checkpoints, resume that continues the same curve, bad input."""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import shutil
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from dva.algorithms import ALGORITHMS, build_agent, config_from_dict, make_config
from dva.analysis.compare import saved_iteration
from dva.envs.factory import EVALUATION_EPISODES, make_env
from dva.errors import DvaUsageError
from dva.runner import training
from dva.runner.checkpoint import checkpoint_manager
from dva.runner.compiled import build, compiled, initial_state, load_run
from dva.runner.training import TrainingDiverged

SMALL = dict(num_envs=4, horizon=8, critic_minibatches=2, actor_hidden=(16,), critic_hidden=(16,))


def train(*args, eval_episodes=None, **kwargs):
    """:func:`dva.runner.training.train` evaluating one episode per training env, on those envs:
    what these tests check does not depend on the evaluation's size, and a second batch of envs
    would only add its compile and run time (the 16-episode batch is tested on its own below)."""
    return training.train(*args, eval_episodes=eval_episodes, **kwargs)


def rows(run_dir):
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def test_train_resume_continues_the_curve(tmp_path):
    run_dir = tmp_path / "run"
    train(
        "cartpole_swingup",
        "shac",
        preset="cpu",
        iterations=3,
        run_dir=run_dir,
        eval_every=3,
        checkpoint_every=2,
        **SMALL,
    )
    first = rows(run_dir)
    assert [int(r["iteration"]) for r in first] == [0, 1, 2, 3]  # 0: the untrained policy's return
    assert [int(r["env_steps"]) for r in first] == [0, 32, 64, 96]
    assert first[0]["eval_return"] != "" and first[1]["eval_return"] == ""
    assert first[-1]["eval_return"] != ""  # evaluated at iteration 3
    assert (run_dir / "checkpoints" / "3").is_dir() and (run_dir / "tensorboard").is_dir()
    # The latest finished episode's return carries across the resume until an episode ends (none
    # does within these iterations): the last row's, set here to a value no iteration logs.
    lines = (run_dir / "progress.csv").read_text().splitlines()
    last = dict(zip(lines[0].split(","), lines[-1].split(","))) | {"train_return": "123.5"}
    (run_dir / "progress.csv").write_text("\n".join([*lines[:-1], ",".join(last.values())]) + "\n")
    train("cartpole_swingup", iterations=2, run_dir=run_dir, resume=True, eval_every=3, checkpoint_every=2)
    resumed = rows(run_dir)
    assert [int(r["iteration"]) for r in resumed] == [0, 1, 2, 3, 4, 5]
    assert [r["train_return"] for r in resumed[3:]] == ["123.5"] * 3
    assert resumed[4]["eval_return"] == "" and resumed[5]["eval_return"] != ""  # runs end on an evaluation
    # By the clock instead: an hour between evaluations gives only the last; none, every iteration.
    # No task or algorithm given: the run's own (`dva train --resume --run-dir RUN`).
    train(None, iterations=2, run_dir=run_dir, resume=True, eval_every=None, eval_minutes=60.0)
    train("cartpole_swingup", iterations=2, run_dir=run_dir, resume=True, eval_every=None, eval_minutes=1e-9)
    assert [r["eval_return"] != "" for r in rows(run_dir)[6:]] == [False, True, True, True]
    times = [float(r["wall_time"]) for r in resumed]
    assert times == sorted(times)  # the clock continues across the resume
    # Each start and resume records the machine it trained on, from its first iteration.
    machines = (run_dir / "machines.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in machines] == ["iteration 0", "iteration 3", "iteration 5", "iteration 7"]
    assert all("cores" in line and "JAX" in line for line in machines)
    # A restored state is committed to the device in every leaf (zero-size ones too), as a fresh
    # one is: one signature for the compiled iteration.
    spec, agent, restored = load_run(run_dir, evaluation_episodes=None)
    assert all(leaf.committed for leaf in jax.tree.leaves(restored))
    # The two runs (and the loaded one) share one agent, and its iteration was compiled once for
    # both: the restored state has the fresh state's signature.
    assert agent is build(spec, evaluation_episodes=None)
    assert compiled(agent).iteration._cache_size() == 1


class StoppedClock:
    """``time.perf_counter`` stopped: time passes only where a test advances it, so what the run's
    clock counts does not depend on how fast this machine trains."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def stopped_clock(monkeypatch):
    clock = StoppedClock()
    monkeypatch.setattr(time, "perf_counter", clock)
    return clock


def test_a_resumes_set_up_and_compilation_are_off_the_clock(tmp_path, monkeypatch, stopped_clock):
    """A resumed curve continues from its checkpoint's wall-clock: with the resume's set-up taking
    an hour (on a stopped clock that nothing else moves), its first row is where the checkpoint's
    was."""
    run_dir = tmp_path / "run"
    train("cartpole_swingup", "shac", iterations=2, run_dir=run_dir, eval_every=None, checkpoint_every=2, **SMALL)
    slow_start = training.starting_state

    def starting_state(*args):
        stopped_clock.advance(3600.0)
        return slow_start(*args)

    monkeypatch.setattr(training, "starting_state", starting_state)
    train("cartpole_swingup", iterations=1, run_dir=run_dir, resume=True, eval_every=None)
    times = [float(r["wall_time"]) for r in rows(run_dir)]
    assert len(times) == 4 and times[3] == times[2], times


def test_evaluations_are_kept_off_the_runs_clock(tmp_path, monkeypatch, stopped_clock):
    """The logged wall-clock (and so the ``minutes`` budget) counts set-up, compilation and
    training, not evaluating: with every evaluation taking a minute (on a stopped clock that
    nothing else moves), the rows of a run evaluated every iteration all read the same time."""

    def slow_evaluations(agent):
        functions = compiled(agent)

        def evaluate(*args):
            stopped_clock.advance(60.0)
            return functions.evaluate(*args)

        return functions._replace(evaluate=evaluate)

    monkeypatch.setattr("dva.runner.training.compiled", slow_evaluations)
    run_dir = tmp_path / "run"
    train("cartpole_swingup", "shac", preset="cpu", iterations=3, run_dir=run_dir, eval_every=1, **SMALL)
    logged = rows(run_dir)
    assert all(r["eval_return"] != "" for r in logged)
    times = [float(r["wall_time"]) for r in logged]
    assert times == [0.0] * 4, times


@pytest.mark.parametrize("algo", [algo for algo in ALGORITHMS if algo != "dagger"])  # DAgger's is SHAC's + a replay
def test_a_run_starts_from_the_types_a_checkpoint_restores(algo):
    """Orbax restores no weak types (arrays made from Python scalars): a run must not start from
    any, or its resume compiles the iteration anew (measured: twice, 2 × 68 s for Cart-pole SHAC)."""
    agent = build_agent("cartpole_balance", algo, make_config("cartpole_balance", algo, "cpu"))
    shapes = jax.eval_shape(functools.partial(initial_state, agent), jax.random.PRNGKey(0))
    assert not [
        jax.tree_util.keystr(path) for path, leaf in jax.tree_util.tree_flatten_with_path(shapes)[0] if leaf.weak_type
    ]


def test_corrupt_checkpoint_and_bad_input_errors(tmp_path):
    run_dir = tmp_path / "run"
    train("cartpole_swingup", "shac", preset="cpu", iterations=1, run_dir=run_dir, checkpoint_every=1, **SMALL)
    for item in (run_dir / "checkpoints" / "1").rglob("*"):
        if item.is_file():
            item.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="checkpoint .* is corrupt or incompatible"):
        train("cartpole_swingup", iterations=1, run_dir=run_dir, resume=True)
    with pytest.raises(ValueError, match="already holds a run"):
        train("cartpole_swingup", "shac", preset="cpu", iterations=1, run_dir=run_dir, **SMALL)
    shutil.rmtree(run_dir)
    with pytest.raises(ValueError, match="no run to resume"):
        train("cartpole_swingup", iterations=1, run_dir=run_dir, resume=True)
    with pytest.raises(ValueError, match="unknown algo 'ppo'"):
        make_config("cartpole_swingup", "ppo", "cpu")
    with pytest.raises(ValueError, match="unknown task .walker."):
        make_config("walker", "dva", "cpu")
    with pytest.raises(ValueError, match="unknown preset .gpu."):
        make_config("cartpole_swingup", "dva", "gpu")
    assert make_config("ant", "shac-pixels", "paper").horizon == 8  # visual SHAC's own horizon
    with pytest.raises(ValueError, match="'gradient' defines the algorithm 'dva'"):
        make_config("cartpole_swingup", "dva", "cpu", gradient="full")
    with pytest.raises(ValueError, match="unknown dva config field 'horizn'; allowed: .*horizon"):
        make_config("cartpole_swingup", "dva", "cpu", horizn=8)


def test_cpu_preset_gives_pixel_actors_a_longer_decay():
    decay = {algo: make_config("hopper", algo, "cpu").lr_decay_iterations for algo in ("shac", "dva", "shac-pixels")}
    assert decay == {"shac": 4000, "dva": 7000, "shac-pixels": 7000}
    # Cart-pole: the state actor's 1000, the pixel actor's decay spanning the 15-minute main job
    assert make_config("cartpole_swingup", "shac", "cpu").lr_decay_iterations == 1000
    assert make_config("cartpole_swingup", "dva", "cpu").lr_decay_iterations == 4500
    assert make_config("humanoid", "dva", "cpu").lr_decay_iterations == 14000  # over its 8-hour run
    assert make_config("hopper", "dva", "paper").lr_decay_iterations == 30000
    assert make_config("hopper", "dva", "cpu", lr_decay_iterations=50).lr_decay_iterations == 50


def test_the_cheetahs_cpu_preset_on_pixels_is_the_papers_batch_at_48_pixels():
    """The Cheetah's pixel actors keep the paper's 64 envs × 32 steps (and its decay) at the CPU
    preset's image size; its state actor keeps the CPU preset's batch."""
    for algo in ("dva", "dva-privileged"):
        assert make_config("cheetah", algo, "cpu") == dataclasses.replace(
            make_config("cheetah", algo, "paper"), image_size=48
        )
    state = make_config("cheetah", "shac", "cpu")
    assert (state.num_envs, state.horizon) == (16, 16)


def test_dva_is_the_papers_method_and_the_privileged_variants_add_the_state_prediction_loss():
    """dva never has the state-prediction loss (under any preset, and no flag turns it on);
    dva-privileged and drqv2-privileged have it at the same weight on every task and preset, and
    only a positive weight; the rest of their configs are dva's and drqv2's."""
    weight = lambda task, algo, preset="cpu": make_config(task, algo, preset).state_prediction
    tasks = ("cartpole_swingup", "hopper", "cheetah", "ant", "humanoid", "quadruped")
    for preset in ("cpu", "paper"):
        assert [weight(task, "dva", preset) for task in tasks] == [0.0] * 6
        assert [weight(task, "drqv2", preset) for task in tasks] == [0.0] * 6
        assert [weight(task, "dva-privileged", preset) for task in tasks] == [10.0] * 6
        assert [weight(task, "drqv2-privileged", preset) for task in tasks] == [10.0] * 6
        for plain in ("dva", "drqv2"):
            extended = dataclasses.replace(make_config("hopper", f"{plain}-privileged", preset), state_prediction=0.0)
            assert extended == make_config("hopper", plain, preset)
    assert weight("hopper", "shac") == weight("ant", "shac-pixels") == 0.0
    with pytest.raises(ValueError, match="state_prediction = 1.0 is not allowed for dva; .*--algo dva-privileged"):
        make_config("hopper", "dva", "cpu", state_prediction=1.0)
    with pytest.raises(
        ValueError, match="state_prediction = 0.0 is not allowed for drqv2-privileged; use a number > 0"
    ):
        make_config("hopper", "drqv2-privileged", "cpu", state_prediction=0.0)
    assert make_config("hopper", "dva-privileged", "cpu", state_prediction=2.0).state_prediction == 2.0


def test_the_paper_preset_is_the_authors_configuration_of_each_robot():
    """--preset paper for dva, as the authors' D.Va configs set it per robot (learning rates, target
    critic α, decay iterations, networks); the Cheetah, which the paper's Table 7 leaves out, takes
    the Hopper's networks and the Ant's critic learning rate, as their Cheetah config does."""
    authors = {  # actor lr, critic lr, target α, decay iterations, actor MLP, critic MLP
        "cartpole_swingup": (2e-3, 2e-4, 0.2, 4000, (64, 64), (64, 64)),
        "hopper": (2e-3, 2e-4, 0.2, 30000, (128, 64, 32), (64, 64)),
        "cheetah": (2e-3, 2e-3, 0.2, 30000, (128, 64, 32), (64, 64)),
        "ant": (2e-3, 2e-3, 0.2, 30000, (128, 64, 32), (64, 64)),
        "humanoid": (2e-3, 5e-4, 0.995, 60000, (256, 128), (128, 128)),
    }
    for task, values in authors.items():
        c = make_config(task, "dva", "paper")
        ours = (c.actor_lr, c.critic_lr, c.target_alpha, c.lr_decay_iterations, c.actor_hidden, c.critic_hidden)
        assert ours == values, task
        assert (c.num_envs, c.horizon, c.image_size, c.frame_stack, c.betas, c.clip_grad_norm) == (
            64,
            32,
            84,
            3,
            (0.7, 0.95),
            1.0,
        )


def test_configs_from_older_runs_load_under_the_new_field_names():
    config = config_from_dict(
        "shac",
        {
            "observation": "state",
            "gradient": "full",
            "grad_clip": 2.0,
            "max_grad_norm": 5.0,
            "iterations": 7,
            "actor_hidden": [16, 8],
            "actor_backward_chunk": None,
        },
    )
    assert (config.clip_grad_norm, config.abort_grad_norm, config.lr_decay_iterations) == (2.0, 5.0, 7)
    assert config.actor_hidden == (16, 8)
    assert config.actor_backward_chunk == 0  # None was the kept backward passes; they go on resume


def test_diverging_gradient_stops_training_and_keeps_the_last_good_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    train("cartpole_swingup", "shac", preset="cpu", iterations=2, run_dir=run_dir, checkpoint_every=1, **SMALL)
    spec = json.loads((run_dir / "run.json").read_text())
    spec["config"]["abort_grad_norm"] = 1e-9  # every gradient now counts as exploding
    (run_dir / "run.json").write_text(json.dumps(spec))
    with pytest.raises(
        TrainingDiverged, match=r"actor gradient norm .* is NaN or above abort_grad_norm = 1e-09 at iteration 3"
    ):
        train("cartpole_swingup", iterations=5, run_dir=run_dir, resume=True, checkpoint_every=1)
    assert checkpoint_manager(run_dir).latest_step() == 2
    assert saved_iteration(run_dir) == 2  # where dva compare and dva analyze gradnorm resume it
    assert saved_iteration(tmp_path / "no run") is None
    assert [int(r["iteration"]) for r in rows(run_dir)] == [0, 1, 2]


def test_off_policy_resume_restores_the_replay_buffer(tmp_path):
    """DrQ-v2 through the same loop: its replay buffer is part of the checkpointed state."""
    run_dir = tmp_path / "run"
    tiny = dict(
        num_envs=2,
        image_size=16,
        batch_size=4,
        hidden=(8,),
        feature_dim=8,
        replay_size=64,
        seed_steps=4,
        updates_per_iteration=1,
    )
    train(
        "cartpole_balance",
        "drqv2",
        preset="cpu",
        iterations=2,
        run_dir=run_dir,
        eval_every=2,
        checkpoint_every=2,
        **tiny,
    )
    train("cartpole_balance", iterations=2, run_dir=run_dir, resume=True, eval_every=4, checkpoint_every=4)
    log = rows(run_dir)
    assert [int(r["iteration"]) for r in log] == list(range(5))
    # The seed phase (in init) fills one 6-step sequence per env (2 earlier frames + o_t + 3 steps):
    # 6 rounds × 2 envs × action repeat 2 = 24 env steps before the first iteration.
    assert [int(r["env_steps"]) for r in log] == [24 + 4 * i for i in range(5)]
    assert all(r["critic_loss"] not in ("", "nan") for r in log[1:]) and log[-1]["eval_return"] != ""
    _, agent, state = load_run(run_dir, evaluation_episodes=None)
    assert int(state.iteration) == 4 and int(state.replay.current_index) == 6 + 4  # seed rounds + iterations
    frames = np.asarray(state.replay.experience.frame[:, :10])
    assert frames.reshape(2, 10, -1).max(axis=-1).min() > 0  # every step of both envs was kept


def test_dagger_counts_its_teachers_time_and_env_steps(tmp_path, monkeypatch):
    # The teacher's config is the earlier tests' (SMALL on swing-up): its agent and compiled
    # iteration are reused from them (training._agent), as a resume would.
    teacher = train(
        "cartpole_swingup", "shac", preset="cpu", iterations=2, run_dir=tmp_path / "teacher", eval_every=None, **SMALL
    )
    teacher_end = rows(teacher)[-1]
    student = train(
        "cartpole_swingup",
        "dagger",
        preset="cpu",
        iterations=2,
        run_dir=tmp_path / "student",
        eval_every=2,
        teacher=str(teacher),
        num_envs=4,
        horizon=8,
        image_size=16,
        batch_size=16,
        replay_size=200,
        updates_per_iteration=1,
        actor_hidden=(16,),
        trunk=16,
    )
    log = rows(student)
    assert [int(r["env_steps"]) for r in log] == [int(teacher_end["env_steps"]) + 32 * i for i in range(3)]
    assert float(log[0]["wall_time"]) == pytest.approx(float(teacher_end["wall_time"]))
    assert float(log[-1]["wall_time"]) > float(teacher_end["wall_time"]) and log[-1]["bc_loss"] != ""
    with pytest.raises(ValueError, match="DAgger needs a teacher on the state"):
        train(
            "cartpole_swingup",
            "dagger",
            preset="cpu",
            iterations=1,
            run_dir=tmp_path / "bad",
            teacher=str(student),
            num_envs=4,
            horizon=8,
            image_size=16,
            batch_size=16,
            replay_size=200,
        )

    # A teacher trained within the same call (here a stand-in that takes 2 s) is counted once: the
    # student's clock starts at the teacher's logged end, not 2 s later.
    def train_teacher(algo, config, *args):
        time.sleep(2.0)
        return dataclasses.replace(config, teacher=str(teacher))

    monkeypatch.setattr(training, "train_teacher", train_teacher)
    in_call = train(
        "cartpole_swingup",
        "dagger",
        preset="cpu",
        iterations=1,
        run_dir=tmp_path / "in_call",
        eval_every=None,
        num_envs=4,
        horizon=8,
        image_size=16,
        batch_size=16,
        replay_size=200,
        actor_hidden=(16,),
        trunk=16,
    )
    assert float(rows(in_call)[0]["wall_time"]) == pytest.approx(float(teacher_end["wall_time"]))


def test_track_logs_config_curve_and_video_to_wandb_offline(tmp_path, monkeypatch):
    """``--track``: the W&B run (offline) holds the run's config, the last logged numbers at their
    env-step count and the policy video; a resumed run reopens the same W&B run."""
    import imageio

    from dva.runner.tracking import WandbTracker

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    run_dir = tmp_path / "run"
    tracker = WandbTracker("dva-test")
    train("cartpole_swingup", "shac", iterations=2, run_dir=run_dir, eval_every=2, tracker=tracker, **SMALL)
    last, run = rows(run_dir)[-1], tracker.run
    assert run.config["task"] == "cartpole_swingup" and run.config["algo"] == "shac"
    assert run.summary["eval_return"] == pytest.approx(float(last["eval_return"]))
    assert run.summary["env_steps"] == int(last["env_steps"]) == 64
    imageio.mimwrite(run_dir / "policy.mp4", np.zeros((4, 16, 16, 3), np.uint8), fps=10)
    tracker.log_video(run_dir / "policy.mp4")
    run_id = run.id
    tracker.finish()
    assert list((run_dir / "wandb").glob(f"offline-run-*-{run_id}/files/media/videos/*.mp4"))
    train("cartpole_swingup", iterations=1, run_dir=run_dir, resume=True, eval_every=None, tracker=tracker)
    assert tracker.run.id == run_id
    tracker.finish()


def test_a_run_written_by_version_0_2_0_resumes_under_the_variant_it_trained(tmp_path):
    """tests/fixtures/dva_run_0.2.0: a run of version 0.2.0 (its run.json, Orbax checkpoint and
    progress.csv as that version wrote them), D.Va with the state-prediction loss, which was then
    the algorithm ``dva``. It resumes as dva-privileged from its checkpoint, and progress.csv keeps
    its columns and rows."""
    run_dir = tmp_path / "run"
    shutil.copytree(Path(__file__).parent / "fixtures" / "dva_run_0.2.0", run_dir)
    header = (run_dir / "progress.csv").read_text().splitlines()[0]
    before = rows(run_dir)
    with pytest.raises(ValueError, match="holds a dva-privileged run on cartpole_swingup, not dva"):
        train("cartpole_swingup", "dva", run_dir=run_dir, resume=True, iterations=1)
    train("cartpole_swingup", run_dir=run_dir, resume=True, iterations=1, eval_every=1)
    assert json.loads((run_dir / "run.json").read_text())["algo"] == "dva"  # the file is left as written
    spec, _, state = load_run(run_dir, evaluation_episodes=None)
    assert (spec.algo, spec.config.state_prediction, int(state.iteration)) == ("dva-privileged", 10.0, 3)
    assert (run_dir / "progress.csv").read_text().splitlines()[0] == header
    after = rows(run_dir)
    assert after[:3] == before and after[3]["iteration"] == "3" and float(after[3]["state_prediction_loss"]) > 0


@pytest.mark.parametrize(
    ("algo", "config"),
    [
        ("shac", SMALL),
        ("dva", dict(SMALL, image_size=16, trunk=16)),
        ("drqv2", dict(num_envs=4, image_size=16, batch_size=8, hidden=(16,), feature_dim=8, replay_size=400,
                       seed_steps=32, updates_per_iteration=1)),
    ],
)  # fmt: skip
def test_the_same_seed_gives_the_same_numbers(tmp_path, algo, config):
    """Two runs of one seed on one machine log the same progress: every return and loss of every
    iteration equal (only the times differ)."""
    logged = []
    for name in ("first", "second"):
        run_dir = train("cartpole_swingup", algo, seed=7, iterations=3, run_dir=tmp_path / name, eval_every=1, **config)
        logged.append(
            [{k: v for k, v in row.items() if k not in ("wall_time", "iteration_time")} for row in rows(run_dir)]
        )
    assert logged[0] == logged[1] and len(logged[0]) == 4


def test_every_evaluation_runs_sixteen_episodes_on_envs_of_its_own():
    from dva.runner.evaluation import evaluate_policy

    few = make_env("cartpole_swingup", 4)
    evaluation = few.evaluation_env()
    assert EVALUATION_EPISODES == 16 and evaluation.num_envs == 16 and evaluation.evaluation_env() is evaluation
    zero_force = jax.jit(lambda key: evaluate_policy(few, lambda o, m, k: (jax.numpy.zeros((16, 1)), m), key))
    returns = np.asarray(zero_force(jax.random.PRNGKey(0)))
    assert returns.shape == (16,) and np.all(np.isfinite(returns)) and returns.std() > 0  # 16 reset draws
    sixteen = make_env("cartpole_swingup", 16)
    assert sixteen.evaluation_env() is sixteen  # a pure wrapper: evaluations start from fresh resets anyway
    assert make_env("cartpole_swingup", 4, evaluation_episodes=None).evaluation_env().num_envs == 4
    with pytest.raises(DvaUsageError, match="evaluation_episodes = 0 is not allowed; use a whole number ≥ 1"):
        make_env("cartpole_swingup", 4, evaluation_episodes=0)
    with pytest.raises(DvaUsageError, match="evaluation_episodes = True is not allowed; use a whole number ≥ 1"):
        make_env("cartpole_swingup", 4, evaluation_episodes=True)


def test_sampled_evaluation_replays_the_training_action_rule(tmp_path, monkeypatch):
    """``dva eval --sampled``: each action ``tanh(μ + σε)`` as in training, seeded; refused, naming
    the algorithms that have the rule, for one without."""
    from dva.algorithms import sampling_algorithms
    from dva.runner import compiled as compiled_module
    from dva.runner.compiled import evaluate_run

    run_dir = tmp_path / "run"
    train("cartpole_swingup", "shac", iterations=1, run_dir=run_dir, eval_every=None, **SMALL)
    spec, agent, state = load_run(run_dir)
    policy = agent.policy(state)
    observation = agent.env.observe(agent.env.reset(jax.random.PRNGKey(1)))
    mean, log_std = agent.actor.apply(policy[0], agent.actor_input(observation, policy[1]))
    noise = jax.random.normal(jax.random.PRNGKey(2), mean.shape)
    np.testing.assert_allclose(
        agent.sample(policy, observation, jax.random.PRNGKey(2)), np.tanh(mean + np.exp(log_std) * noise), atol=1e-6
    )
    deterministic = evaluate_run(run_dir, seed=3)[1]
    sampled, again = (evaluate_run(run_dir, seed=3, sampled=True)[1] for _ in range(2))
    np.testing.assert_array_equal(sampled, again)  # seeded
    assert np.abs(sampled - deterministic).max() > 1e-3  # σ = e⁻¹ moves the cart
    assert set(sampling_algorithms()) == {"dva", "dva-privileged", "shac", "shac-pixels", "dpg-state"}
    drqv2_run = (dataclasses.replace(spec, algo="drqv2"), None, None)
    monkeypatch.setattr(compiled_module, "load_run", lambda *args: drqv2_run)
    with pytest.raises(DvaUsageError, match="--sampled: drqv2 acts without a sampled action rule; the algorithms"):
        evaluate_run(run_dir, sampled=True)

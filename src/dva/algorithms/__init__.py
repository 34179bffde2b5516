"""The algorithms behind one :class:`~dva.algorithms.base.Agent` protocol, and their registry.

D.Va, SHAC, DPG on state and visual SHAC are one trainer (:mod:`dva.algorithms.shac`) with
different observations and gradients; DrQ-v2 and CURL (:mod:`dva.algorithms.drqv2`,
:mod:`dva.algorithms.curl`) are the off-policy pixel baselines on a shared collection loop
(:mod:`dva.algorithms.off_policy`); DreamerV3 (:mod:`dva.algorithms.dreamerv3`) learns a world
model and acts from its recurrent state; TD-MPC2 (:mod:`dva.algorithms.tdmpc2`) learns an implicit
world model and plans over it. :func:`build_agent` puts an algorithm together with its task
and pixel wrapper; :func:`make_config` with its preset (:mod:`dva.configs`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal

from dva.algorithms.base import Agent, TeacherRun
from dva.algorithms.curl import CURL, CURLConfig
from dva.algorithms.dagger import DAggerConfig, make_dagger
from dva.algorithms.dreamerv3 import DreamerV3, DreamerV3Config
from dva.algorithms.drqv2 import DrQV2, DrQV2Config
from dva.algorithms.shac import SHAC, SHACConfig
from dva.algorithms.tdmpc2 import TDMPC2, TDMPC2Config
from dva.configs import (
    PRESETS,
    curl_preset,
    dagger_preset,
    dreamerv3_preset,
    drqv2_preset,
    privileged,
    shac_preset,
    tdmpc2_preset,
)
from dva.envs.factory import EVALUATION_EPISODES, RendererKind, check_env_name, make_env
from dva.envs.observations import DifferentiableEnv
from dva.errors import DvaUsageError


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """A registry entry: how to configure and build one algorithm."""

    description: str
    config_type: type
    make_agent: Callable[..., Agent]  # (env, config) → agent; with a teacher_algo, (env, config, teacher)
    preset: Callable[[str, str], dict]  # (task, preset) → config values
    defining: dict[str, Any]  # config values that make it this algorithm (not overridable)
    renderer: Callable[[Any], RendererKind]  # which renderer its config needs
    # The algorithm of the finished run it learns from (DAgger: a SHAC teacher), named by its
    # config's `teacher` run directory; a run without one trains one first for `teacher_minutes`.
    teacher_algo: str | None = None
    # What to try when a run diverges, in the algorithm's own flags.
    divergence_hint: str = "lower learning rates"
    # The `dva train --GROUP.FIELD` flags that override its config (every field but `defining`);
    # algorithms sharing a config class share a group. `flag_aliases` gives some a short flag too.
    flag_group: str = ""
    flag_aliases: dict[str, str] = dataclasses.field(default_factory=dict)
    # The algorithm to use for another value of a defining field (named in the error).
    alternatives: dict[str, str] = dataclasses.field(default_factory=dict)
    # Fields whose value must be > 0 (what makes a `-privileged` variant one).
    positive: tuple[str, ...] = ()


def _shac_renderer(config: SHACConfig) -> RendererKind:
    """Warp's pixels for D.Va; the differentiable renderer where the gradient goes through pixels."""
    if config.observation == "state":
        return None
    return "soft" if config.gradient == "full" else "warp"


def _pixels_or_state(config: DreamerV3Config | TDMPC2Config) -> RendererKind:
    return "warp" if config.observation == "pixels" else None


DREAMER_HINT = "lower learning rates (--dreamerv3.model-lr, --dreamerv3.actor-lr, --dreamerv3.critic-lr)"
TDMPC2_HINT = "a lower learning rate (--tdmpc2.lr) or gradient clip (--tdmpc2.grad-clip)"
SHAC_HINT = "a lower learning rate (--shac.actor-lr), a shorter horizon (--shac.horizon) or --shac.state-grad-clip"
ALGORITHMS: dict[str, Algorithm] = {
    "dva": Algorithm(
        "D.Va, the paper's method: actor on pixels, gradient decoupled from the observation",
        SHACConfig,
        SHAC,
        lambda task, preset: shac_preset(task, preset, "pixels"),
        dict(observation="pixels", gradient="decoupled", state_prediction=0.0),
        _shac_renderer,
        divergence_hint=SHAC_HINT,
        flag_group="shac",
        alternatives=dict(state_prediction="dva-privileged", gradient="shac-pixels", observation="shac"),
    ),
    "dva-privileged": Algorithm(
        "D.Va whose pixel encoder also learns to predict the simulator's state (an extension)",
        SHACConfig,
        SHAC,
        lambda task, preset: privileged(shac_preset(task, preset, "pixels")),
        dict(observation="pixels", gradient="decoupled"),
        _shac_renderer,
        divergence_hint=SHAC_HINT,
        flag_group="shac",
        positive=("state_prediction",),
    ),
    "shac": Algorithm(
        "SHAC: actor on the state, full gradient",
        SHACConfig,
        SHAC,
        shac_preset,
        dict(observation="state", gradient="full"),
        _shac_renderer,
        divergence_hint=SHAC_HINT,
        flag_group="shac",
    ),
    "dpg-state": Algorithm(
        "decoupled gradient, actor on the state (paper Fig 13)",
        SHACConfig,
        SHAC,
        shac_preset,
        dict(observation="state", gradient="decoupled"),
        _shac_renderer,
        divergence_hint=SHAC_HINT,
        flag_group="shac",
    ),
    "shac-pixels": Algorithm(
        "visual SHAC: actor on differentiably rendered pixels, full gradient",
        SHACConfig,
        SHAC,
        lambda task, preset: shac_preset(task, preset, "differentiable-pixels"),
        dict(observation="pixels", gradient="full"),
        _shac_renderer,
        divergence_hint=SHAC_HINT,
        flag_group="shac",
    ),
    "drqv2": Algorithm(
        "DrQ-v2: DDPG from pixels with random-shift augmentation",
        DrQV2Config,
        DrQV2,
        drqv2_preset,
        dict(state_prediction=0.0),
        lambda config: "warp",
        divergence_hint="a lower learning rate (--drqv2.lr)",
        flag_group="drqv2",
        alternatives=dict(state_prediction="drqv2-privileged"),
    ),
    "drqv2-privileged": Algorithm(
        "DrQ-v2 whose encoder also learns to predict the simulator's state (as dva-privileged's)",
        DrQV2Config,
        DrQV2,
        lambda task, preset: privileged(drqv2_preset(task, preset)),
        {},
        lambda config: "warp",
        divergence_hint="a lower learning rate (--drqv2.lr)",
        flag_group="drqv2",
        positive=("state_prediction",),
    ),
    "curl": Algorithm(
        "CURL: SAC from pixels with a contrastive auxiliary loss",
        CURLConfig,
        CURL,
        curl_preset,
        {},
        lambda config: "warp",
        divergence_hint="a lower learning rate (--curl.lr)",
        flag_group="curl",
    ),
    "dagger": Algorithm(
        "state-to-visual DAgger: a pixel student imitates a SHAC teacher on the state",
        DAggerConfig,
        make_dagger,
        dagger_preset,
        {},
        lambda config: "warp",
        teacher_algo="shac",
        divergence_hint="a lower learning rate (--dagger.lr)",
        flag_group="dagger",
        flag_aliases={"teacher": "--teacher"},
    ),
    "dreamerv3": Algorithm(
        "DreamerV3: a world model from pixels (RSSM), actor and critic in imagination",
        DreamerV3Config,
        DreamerV3,
        dreamerv3_preset,
        dict(observation="pixels", frame_stack=1),
        _pixels_or_state,
        divergence_hint=DREAMER_HINT,
        flag_group="dreamerv3",
    ),
    "dreamerv3-state": Algorithm(
        "DreamerV3 on the state: the same agent with an MLP encoder and decoder of the state vector",
        DreamerV3Config,
        DreamerV3,
        lambda task, preset: dreamerv3_preset(task, preset, "state"),
        dict(observation="state", frame_stack=1),
        _pixels_or_state,
        divergence_hint=DREAMER_HINT,
        flag_group="dreamerv3",
    ),
    "tdmpc2": Algorithm(
        "TD-MPC2: an implicit world model from pixels (SimNorm latents), MPPI planning with a policy prior",
        TDMPC2Config,
        TDMPC2,
        tdmpc2_preset,
        dict(observation="pixels"),
        _pixels_or_state,
        divergence_hint=TDMPC2_HINT,
        flag_group="tdmpc2",
    ),
    "tdmpc2-state": Algorithm(
        "TD-MPC2 on the state: the same agent with an MLP encoder of the state vector",
        TDMPC2Config,
        TDMPC2,
        lambda task, preset: tdmpc2_preset(task, preset, "state"),
        dict(observation="state"),
        _pixels_or_state,
        divergence_hint=TDMPC2_HINT,
        flag_group="tdmpc2",
    ),
}
# The names `dva train --algo` accepts: a Literal built from the registry (tyro's choices); to a
# type checker, which cannot evaluate it, a str.
if TYPE_CHECKING:
    AlgoName = str
else:
    AlgoName = Literal[tuple(ALGORITHMS)]
assert all(entry.flag_group for entry in ALGORITHMS.values())
# The algorithms that run on dm_control's tasks: all but the SHAC family, which differentiates
# this project's physics, and those that learn from a (SHAC) teacher.
DMC_ALGOS = tuple(
    name for name, entry in ALGORITHMS.items() if entry.config_type is not SHACConfig and entry.teacher_algo is None
)

# run.json files written before fields were renamed still load.
RENAMED_FIELDS: dict[type, dict[str, str]] = {
    SHACConfig: {"grad_clip": "clip_grad_norm", "max_grad_norm": "abort_grad_norm", "iterations": "lr_decay_iterations"}
}


def check_algo(algo: str) -> Algorithm:
    """The registry entry of ``algo``, or a clear error naming the choices."""
    if algo not in ALGORITHMS:
        raise DvaUsageError(f"unknown algo {algo!r}; choose one of: {', '.join(ALGORITHMS)}")
    return ALGORITHMS[algo]


def sampling_algorithms() -> list[str]:
    """The algorithms whose agents act in training by sampling from their policy
    (:class:`~dva.algorithms.base.SamplingAgent`): what ``dva eval --sampled`` replays."""
    return [name for name, entry in ALGORITHMS.items() if callable(getattr(entry.make_agent, "sample", None))]


def make_config(task: str, algo: str, preset: str, **overrides) -> Any:
    """The configuration of ``algo`` on ``task`` under ``preset``, with ``overrides`` (None: keep)."""
    check_env_name(task)
    entry = check_algo(algo)
    if preset not in PRESETS:
        raise DvaUsageError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    overrides = {key: value for key, value in overrides.items() if value is not None}
    fields = {field.name for field in dataclasses.fields(entry.config_type)}
    for key in overrides:
        if key in entry.defining:
            other = f"; for another, --algo {entry.alternatives[key]}" if key in entry.alternatives else ""
            raise DvaUsageError(
                f"{key} = {overrides[key]!r} is not allowed for {algo}; use {entry.defining[key]!r} "
                f"({key!r} defines the algorithm {algo!r}{other})"
            )
        if key not in fields:
            raise DvaUsageError(
                f"unknown {algo} config field {key!r}; allowed: {', '.join(sorted(fields - set(entry.defining)))}"
            )
    config = entry.config_type(**{**entry.preset(task, preset), **entry.defining, **overrides})
    for key in entry.positive:
        if not getattr(config, key) > 0:
            raise DvaUsageError(f"{key} = {getattr(config, key)!r} is not allowed for {algo}; use a number > 0")
    return config


def config_from_dict(algo: str, values: dict) -> Any:
    """A config back from ``run.json`` (lists become tuples; old field names are renamed)."""
    config_type = check_algo(algo).config_type
    renamed = RENAMED_FIELDS.get(config_type, {})
    values = {
        renamed.get(key, key): tuple(value) if isinstance(value, list) else value for key, value in values.items()
    }
    return config_type(**values)


def saved_algo(algo: str, config: Any) -> str:
    """The registry entry a saved run of ``algo`` with ``config`` belongs to now: where the config
    differs from a defining value that another entry takes (a ``dva`` run written when D.Va's CPU
    preset carried the state-prediction loss), that entry."""
    entry = check_algo(algo)
    for key, value in entry.defining.items():
        if getattr(config, key) != value and key in entry.alternatives:
            return entry.alternatives[key]
    return algo


def build_agent(
    task_name: str,
    algo: str,
    config: Any,
    physics: str | None = None,
    mesh=None,
    teacher: TeacherRun | None = None,
    evaluation_episodes: int | None = EVALUATION_EPISODES,
) -> Agent:
    """``algo`` with ``config`` on ``task_name``: the task, its pixel wrapper (whose renderer lives
    as long as the agent) and the agent; ``mesh``: the devices its environments split over;
    ``teacher``: the run it learns from, for an algorithm with a ``teacher_algo``
    (:func:`dva.runner.compiled.load_teacher` loads one); ``evaluation_episodes``: how many
    episodes an evaluation runs (None: one per env, on the training envs)."""
    entry = check_algo(algo)
    if (entry.teacher_algo is None) != (teacher is None):
        needs = f"a {entry.teacher_algo} teacher run" if entry.teacher_algo else "no teacher"
        raise DvaUsageError(f"teacher = {teacher and teacher.algo!r}: {algo} takes {needs}")
    env = make_env(
        task_name,
        config.num_envs,
        renderer=entry.renderer(config),
        image_size=config.image_size,
        frame_stack=config.frame_stack,
        action_repeat=getattr(config, "action_repeat", 1),  # configs without one act every control step
        physics=physics,
        mesh=mesh,
        evaluation_episodes=evaluation_episodes,
    )
    if algo not in DMC_ALGOS and not isinstance(env, DifferentiableEnv):
        raise DvaUsageError(
            f"{algo} needs this project's differentiable tasks; on {task_name} use: {', '.join(DMC_ALGOS)}"
        )
    return entry.make_agent(env, config) if teacher is None else entry.make_agent(env, config, teacher)

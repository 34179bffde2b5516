"""The protocol every algorithm implements, so that one training loop (:func:`dva.runner.training.train`)
serves them all: budget, progress bar, logs, evaluation, checkpoints, resume, divergence guard."""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple, Protocol, TypeVar, runtime_checkable

import jax
import jax.numpy as jnp

from dva.envs.observations import Env, Observation

State = TypeVar("State")  # a pytree holding everything an iteration reads and writes
Policy = TypeVar("Policy")  # a pytree: the parameters (and statistics) acting needs


class AgentConfig(Protocol):
    """What every algorithm's config is: a frozen dataclass (saved in ``run.json``) that says how
    many environments the agent runs."""

    __dataclass_fields__: ClassVar[dict[str, Any]]

    @property
    def num_envs(self) -> int: ...


class Metrics(NamedTuple):
    """What one iteration reports to the training loop (scalars; a pytree)."""

    healthy: jax.Array  # False stops training at the last checkpoint (a NaN or exploding update)
    finished_return_sum: jax.Array  # the returns of the training episodes that ended in the iteration
    finished_episodes: jax.Array  # how many ended
    logged: dict[str, jax.Array]  # the agent's own numbers, by its metric_names: logged to CSV and TensorBoard
    stop: jax.Array | None = None  # True ends the run normally (the agent's own stopping rule), if it has one


class Agent(Protocol[State, Policy]):
    """An algorithm: a pure, jittable ``iteration`` over a pytree state, returning the new state and
    its :class:`Metrics`, plus its policy. The state counts its iterations in ``state.iteration``.
    """

    @property
    def env(self) -> Env:
        """What the agent trains in (its renderer stays alive with it)."""

    @property
    def config(self) -> AgentConfig:
        """The algorithm's config (its own dataclass), saved in ``run.json``."""

    @property
    def metric_names(self) -> tuple[str, ...]:
        """The metrics of :meth:`iteration` the loop logs, besides the ones every agent returns."""

    @property
    def prior_cost(self) -> tuple[float, int]:
        """(seconds, env steps) spent before it started (DAgger's teacher)."""

    @property
    def batch_fields(self) -> tuple[str, ...]:
        """The state's fields that hold the environment batch (leading num_envs axis), which a run
        on several devices splits over them (:mod:`dva.runner.sharding`); () if it does not split."""

    def __hash__(self) -> int:
        """Agents are stateless: the loop caches their compiled functions per agent."""

    @property
    def env_steps_per_iteration(self) -> int:
        """Control steps of the task per iteration, over all envs (action repeats included)."""

    @property
    def default_iterations(self) -> int:
        """The run's length when neither an iteration count nor a time budget is given."""

    def init(self, key: jax.Array) -> State:
        """Fresh networks, optimisers, environments (and buffers)."""

    def iteration(self, state: State) -> tuple[State, Metrics]:
        """One training iteration (the loop jits it and donates ``state``)."""

    def policy(self, state: State) -> Policy:
        """The parameters :meth:`act` needs (a pytree), taken from the training state."""

    def act(self, policy: Policy, observation: Observation) -> jax.Array:
        """The deterministic action in [−1, 1] for a batch of observations (evaluation)."""

    def abort_reason(self, logged: dict[str, Any]) -> str:
        """Why an unhealthy iteration stops training (from its :attr:`Metrics.logged`), naming the
        value and the limit."""


@runtime_checkable
class RecurrentAgent(Protocol):
    """An agent whose policy remembers (DreamerV3's latent state): evaluation carries its memory
    from step to step, starting each episode from :meth:`initial_memory`. Its :meth:`Agent.act`
    is the action from a fresh memory."""

    def initial_memory(self, num_envs: int) -> Any:
        """The memory (a pytree with a leading env axis) at the start of an episode."""

    def act_recurrent(
        self, policy: Any, observation: Observation, memory: Any, key: jax.Array
    ) -> tuple[jax.Array, Any]:
        """The evaluation action for a batch of observations, and the updated memory (``key``: for
        a memory that is sampled, as DreamerV3's latent state)."""


@runtime_checkable
class SamplingAgent(Protocol):
    """An agent whose training acts by sampling from its policy (SHAC and D.Va: ``tanh(μ + σε)``):
    its training-episode returns are this rule's, and ``dva eval --sampled`` replays it."""

    def sample(self, policy: Any, observation: Observation, key: jax.Array) -> jax.Array:
        """The training action for a batch of observations, its noise drawn from ``key``."""


def nan_loss_reason(logged: dict[str, Any], names: tuple[str, ...]) -> str:
    """Why an update with a NaN or infinite loss stops training: every loss in ``names`` with its value."""
    losses = ", ".join(f"{name} {float(logged[name]):.3g}" for name in names)
    return f"a NaN or infinite loss ({losses})"


def all_finite(values: dict[str, jax.Array]) -> jax.Array:
    """Whether every value is finite: the ``healthy`` of an agent whose every loss must be."""
    return jnp.all(jnp.array([jnp.isfinite(value) for value in values.values()]))


class TeacherRun(NamedTuple):
    """A finished run another agent learns from (DAgger's teacher): its algorithm, agent, policy
    parameters, and the (seconds, env steps) it cost, which the learner's curve continues from."""

    algo: str
    agent: Agent
    policy: Any
    cost: tuple[float, int]

"""The one exception type for bad input, and the check of the algorithms' numeric options."""

from __future__ import annotations

import dataclasses
import math


class DvaUsageError(ValueError):
    """A value dva does not allow (a task, an option, a budget, a run directory): its message names
    the value and what is allowed, and the command line prints it as one line. Every other
    exception is a bug somewhere and keeps its traceback."""


# The ranges of the algorithms' float options, by name: checked before a run starts (check_numbers).
_POSITIVE = ("lr", "eps", "clip", "clip_grad_norm", "abort_grad_norm", "temperature", "train_ratio", "min_std",
             "max_std", "teacher_minutes", "lr_scale", "stop_bc_loss", "reward_scale")  # fmt: skip
_NON_NEGATIVE = (
    "pre_tanh_penalty",
    "state_prediction",
    "free_nats",
    "scale",
    "coef",
    "entropy",
    "std_start",
    "std_end",
)
_DISCOUNTS = ("gamma", "lam")  # (0, 1]
_FRACTIONS = ("alpha", "tau", "unimix", "fraction", "decay", "ema", "rho", "betas")  # [0, 1]
_BELOW_ONE = ("stop_loss_decay", "dropout", "betas")  # [0, 1)
_NO_LIMIT = ("clip", "clip_grad_norm", "abort_grad_norm")  # inf: no limit


def _matches(name: str, patterns: tuple[str, ...]) -> bool:
    return name.endswith(patterns)


def check_numbers(config: object) -> None:
    """A one-line :class:`DvaUsageError` for the first float option of the dataclass ``config``
    that is NaN, infinite (but a limit, where inf means none) or outside its range: learning
    rates, clips and temperatures > 0; weights and scales ≥ 0; discounts in (0, 1]; rates,
    fractions and Adam's betas in [0, 1] (betas and dropout below 1)."""
    for field in dataclasses.fields(config):  # type: ignore[arg-type]
        name, value = field.name, getattr(config, field.name)
        values = value if isinstance(value, tuple) else (value,)
        if not values or not all(isinstance(v, float) and not isinstance(v, bool) for v in values):
            continue
        allowed = "a finite number"
        if _matches(name, _DISCOUNTS):
            allowed, ok = "a number in (0, 1]", all(0 < v <= 1 for v in values)
        elif _matches(name, _BELOW_ONE):
            allowed, ok = "a number in [0, 1)", all(0 <= v < 1 for v in values)
        elif _matches(name, _FRACTIONS):
            allowed, ok = "a number in [0, 1]", all(0 <= v <= 1 for v in values)
        elif _matches(name, _POSITIVE):
            allowed, ok = "a number > 0", all(v > 0 for v in values)
        elif _matches(name, _NON_NEGATIVE):
            allowed, ok = "a number ≥ 0", all(v >= 0 for v in values)
        else:
            ok = True
        infinite_ok = _matches(name, _NO_LIMIT)
        if not ok or any(math.isnan(v) or (math.isinf(v) and not infinite_ok) for v in values):
            shown = "inf for no limit, or " + allowed if infinite_ok else allowed
            raise DvaUsageError(f"{name} = {value!r} is not allowed; use {shown}")

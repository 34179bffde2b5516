"""Statistics over seeds, the same wherever a result is summarised: the sample standard
deviation and a seeded percentile-bootstrap interval of the mean (rliable's method for an
interval estimate over few runs), so that a report regenerates identically, and how a cell shows
them, the same in the report and in ``dva compare``'s summary."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

Values = Sequence[float] | npt.NDArray

BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def sample_std(values: Values) -> float:
    """The standard deviation over seeds with Bessel's correction (ddof 1); 0 for one seed."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def bootstrap_interval(values: Values, level: float = 0.95) -> tuple[float, float]:
    """The percentile-bootstrap ``level`` interval of the mean of ``values``: the seeds resampled
    with replacement :data:`BOOTSTRAP_RESAMPLES` times from a fixed seed."""
    samples = np.asarray(values, dtype=float)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = samples[rng.integers(0, len(samples), (BOOTSTRAP_RESAMPLES, len(samples)))].mean(axis=1)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(means, [tail, 100 - tail])
    return float(low), float(high)


def whole(value: float) -> str:
    """A return rounded to a whole number ("-0" shown as "0")."""
    return "0" if round(value) == 0 else f"{value:.0f}"


def mean_and_std_text(mean: float, std: float, seeds: int) -> str:
    """The mean ± the sample std over seeds in whole numbers; the value alone for one seed."""
    return whole(mean) if seeds == 1 else f"{whole(mean)} ± {std:.0f}"


def interval_text(low: float, high: float, seeds: int) -> str:
    """An interval of the mean as "[low, high]"; "–" for one seed, whose resamples are all that seed
    (an interval of zero width says nothing about the spread)."""
    return "–" if seeds < 2 else f"[{whole(low)}, {whole(high)}]"

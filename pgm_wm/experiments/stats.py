r"""Intervals for multi-seed results: a two-level (seeds × test windows) bootstrap.

A results table of the book compares trained models on held-out test windows. Two sources of
randomness make a single number unreliable:

* the **training run** (initialisation, minibatch order, imputation masks): captured by
  training every model with several seeds ``s = 1..S``;
* the **test set** (which windows happened to be held out): captured by resampling windows.

For an error measure stored per seed and per test window, ``values[s, w]``, we resample seeds
with replacement and, independently, windows with replacement, and recompute the statistic
(Eq. boot-stat):

.. math:: \hat\theta^{(b)} = g\Big(\frac{1}{SW}\sum_{i=1}^{S}\sum_{j=1}^{W}
          v_{s^{(b)}_i,\, w^{(b)}_j}\Big),

with :math:`g(x) = \sqrt{x}` for an RMSE from squared errors and :math:`g(x) = x` for a mean
NLL. The 95 % interval is the percentile interval of :math:`\hat\theta^{(1..B)}`.

Comparisons are *paired over windows*: both models are scored on the same resampled windows
(they saw the same test data), while their seeds are resampled independently (their training
runs are independent). :func:`paired_ratio` gives the interval of the ratio of two RMSEs; a
conclusion "A beats B" survives when the whole interval lies below 1.

Everything here is plain numpy and deterministic for a given ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Interval", "bootstrap_statistic", "rmse_interval", "mean_interval", "paired_ratio", "paired_mean_ratio"]


@dataclass(frozen=True)
class Interval:
    """A point estimate with a percentile bootstrap interval ``[lo, hi]``."""

    point: float
    lo: float
    hi: float

    def excludes(self, value: float) -> bool:
        """True if ``value`` lies outside ``[lo, hi]``."""
        return value < self.lo or value > self.hi

    def as_list(self) -> list[float]:
        return [self.point, self.lo, self.hi]

    def format(self, fmt: str = ".3g", scale: float = 1.0) -> str:
        """``"point [lo, hi]"`` with each number multiplied by ``scale``."""
        p, lo, hi = (format(scale * x, fmt) for x in (self.point, self.lo, self.hi))
        return f"{p} [{lo}, {hi}]"


def _check_values(name: str, values: object) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 1:
        raise ValueError(f"{name}: expected a non-empty (seeds, windows) array, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return v


def _check_level(level: float, n_boot: int) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: must be in (0, 1), got {level}")
    if not isinstance(n_boot, int) or n_boot < 10:
        raise ValueError(f"n_boot: must be an integer >= 10, got {n_boot!r}")


def _resample_means(v: np.ndarray, rng: np.random.Generator, n_boot: int,
                    windows: np.ndarray | None = None) -> np.ndarray:
    """Bootstrap replicates of the grand mean of ``v[s, w]``: ``(n_boot,)``.

    ``windows`` (``(n_boot, W)`` indices) fixes the window resampling, for paired comparisons.
    The grand mean over resampled (seed, window) pairs factorizes: it is the mean over the
    resampled seeds of each seed's mean over the resampled windows.
    """
    S, W = v.shape
    seeds = rng.integers(0, S, size=(n_boot, S))
    if windows is None:
        windows = rng.integers(0, W, size=(n_boot, W))
    # per replicate b: mean_j v[:, w_bj] -> (n_boot, S), then pick the resampled seeds
    per_seed = np.stack([v[:, w].mean(axis=1) for w in windows])          # (n_boot, S)
    return np.take_along_axis(per_seed, seeds, axis=1).mean(axis=1)


def bootstrap_statistic(values: object, transform: Callable[[np.ndarray], np.ndarray] = lambda x: x,
                        n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> Interval:
    """Eq. (boot-stat) for ``values: (seeds, windows)``: ``transform`` of the grand mean with a
    two-level percentile bootstrap interval."""
    v = _check_values("values", values)
    _check_level(level, n_boot)
    rng = np.random.default_rng(seed)
    reps = transform(_resample_means(v, rng, n_boot))
    alpha = (1.0 - level) / 2.0
    lo, hi = np.quantile(reps, [alpha, 1.0 - alpha])
    return Interval(float(transform(np.asarray(v.mean()))), float(lo), float(hi))


def rmse_interval(sq_err: object, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> Interval:
    """RMSE :math:`\\sqrt{\\text{mean}}` of per-(seed, window) mean squared errors, with its interval."""
    v = _check_values("sq_err", sq_err)
    if (v < 0).any():
        raise ValueError("sq_err: squared errors must be non-negative")
    return bootstrap_statistic(v, np.sqrt, n_boot, level, seed)


def mean_interval(values: object, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> Interval:
    """Grand mean of per-(seed, window) values (e.g. an NLL), with its interval."""
    return bootstrap_statistic(values, lambda x: x, n_boot, level, seed)


def _paired_mean_ratio(names: tuple[str, str], values_a: object, values_b: object, n_boot: int, level: float,
                       seed: int) -> tuple[float, np.ndarray, float]:
    """Point ratio mean(a) / mean(b), its bootstrap replicates (windows resampled jointly, seeds
    independently) and ``alpha``; ``names`` are the arguments' names for the errors."""
    a = _check_values(names[0], values_a)
    b = _check_values(names[1], values_b)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"{names[1]}: expected {a.shape[1]} windows (the same as {names[0]}), got {b.shape[1]}")
    if (a < 0).any() or (b < 0).any():
        raise ValueError(f"{names[0]}: values must be non-negative")
    _check_level(level, n_boot)
    rng = np.random.default_rng(seed)
    windows = rng.integers(0, a.shape[1], size=(n_boot, a.shape[1]))
    ra = _resample_means(a, rng, n_boot, windows)
    rb = _resample_means(b, rng, n_boot, windows)
    tiny = np.finfo(np.float64).tiny
    return float(a.mean() / max(b.mean(), tiny)), ra / np.maximum(rb, tiny), (1.0 - level) / 2.0


def paired_ratio(sq_err_a: object, sq_err_b: object, n_boot: int = 2000, level: float = 0.95,
                 seed: int = 0) -> Interval:
    """Ratio RMSE(a) / RMSE(b) with an interval, windows resampled jointly (paired), seeds of the
    two models resampled independently. Below 1 means ``a`` has the lower error."""
    point, reps, alpha = _paired_mean_ratio(("sq_err_a", "sq_err_b"), sq_err_a, sq_err_b, n_boot, level, seed)
    lo, hi = np.sqrt(np.quantile(reps, [alpha, 1.0 - alpha]))
    return Interval(float(np.sqrt(point)), float(lo), float(hi))


def paired_mean_ratio(values_a: object, values_b: object, n_boot: int = 2000, level: float = 0.95,
                      seed: int = 0) -> Interval:
    """Ratio mean(a) / mean(b) of two non-negative per-(seed, window) measures (e.g. closed-loop
    costs per seed and task), paired over windows as :func:`paired_ratio`: windows (tasks) are
    resampled jointly, the two models' seeds independently. Below 1 means ``a`` is lower."""
    point, reps, alpha = _paired_mean_ratio(("values_a", "values_b"), values_a, values_b, n_boot, level, seed)
    lo, hi = np.quantile(reps, [alpha, 1.0 - alpha])
    return Interval(point, float(lo), float(hi))

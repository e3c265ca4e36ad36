"""Smooth random excitation signals shared by the simulators (pure, seeded numpy).

All functions take a ``numpy.random.Generator`` and return float64 arrays of
shape ``(n, T)`` (or ``(n, T, d)`` where stated), sampled every ``dt`` seconds;
signals are held constant between samples (zero-order hold) by the simulators.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sum_of_sines", "random_steps", "lowpass", "ou_process", "drop_burn_in"]


def sum_of_sines(
    rng: np.random.Generator,
    n: int,
    T: int,
    dt: float,
    n_sines: int,
    freq_range: tuple[float, float],
    amp_range: tuple[float, float],
) -> np.ndarray:
    r"""Random multisine :math:`s(t) = \sum_{k=1}^{K} a_k \sin(2\pi f_k t + \varphi_k)`.

    With :math:`f_k \sim U(\text{freq\_range})` in Hz, :math:`a_k \sim U(\text{amp\_range})`,
    :math:`\varphi_k \sim U(0, 2\pi)`, drawn independently per sequence. Returns ``(n, T)``.
    """
    t = np.arange(T) * dt
    f = rng.uniform(*freq_range, size=(n, n_sines, 1))
    a = rng.uniform(*amp_range, size=(n, n_sines, 1))
    phi = rng.uniform(0.0, 2.0 * np.pi, size=(n, n_sines, 1))
    return (a * np.sin(2.0 * np.pi * f * t + phi)).sum(axis=1)


def random_steps(
    rng: np.random.Generator,
    n: int,
    T: int,
    dt: float,
    hold_range: tuple[float, float],
    level_low: np.ndarray | float,
    level_high: np.ndarray | float,
    d: int | None = None,
) -> np.ndarray:
    """Piecewise-constant signal: a level ``~ U(level_low, level_high)`` held for ``~ U(hold_range)`` s.

    Returns ``(n, T)``, or ``(n, T, d)`` when ``d`` is given (the switching
    times are shared by the ``d`` channels; ``level_low``/``level_high`` may
    then be arrays of shape ``(d,)``).
    """
    shape_level = (n,) if d is None else (n, d)
    out = np.empty((n, T) if d is None else (n, T, d))
    max_changes = int(np.ceil(T * dt / hold_range[0])) + 2
    holds = rng.uniform(*hold_range, size=(n, max_changes))
    levels = rng.uniform(level_low, level_high, size=(max_changes,) + shape_level)
    switch_steps = np.floor(np.cumsum(holds, axis=1) / dt).astype(np.int64)  # (n, max_changes)
    t = np.arange(T)
    # index of the current level: number of switches that happened at or before t
    idx = (switch_steps[:, None, :] <= t[None, :, None]).sum(axis=2)  # (n, T)
    rows = np.arange(n)[:, None]
    if d is None:
        out[:] = levels[idx, rows]
    else:
        out[:] = levels[idx, rows, :]
    return out


def lowpass(x: np.ndarray, dt: float, tau: float, order: int = 2, axis: int = 1) -> np.ndarray:
    r"""Cascade of ``order`` first-order low-pass filters along ``axis``.

    Each stage is the exact discretisation of :math:`\tau \dot y = x - y` for a
    piecewise-constant input, :math:`y_{t+1} = y_t + (1 - e^{-dt/\tau})(x_t - y_t)`,
    started at :math:`y_0 = x_0`. Two stages give a critically damped smoothing.
    """
    alpha = 1.0 - np.exp(-dt / tau)
    y = np.moveaxis(np.array(x, dtype=np.float64, copy=True), axis, 0)
    for _ in range(order):
        out = np.empty_like(y)
        out[0] = y[0]
        for t in range(1, y.shape[0]):
            out[t] = out[t - 1] + alpha * (y[t - 1] - out[t - 1])
        y = out
    return np.moveaxis(y, 0, axis)


def ou_process(
    rng: np.random.Generator, shape: tuple[int, ...], dt: float, tau: float, sigma: float
) -> np.ndarray:
    r"""Ornstein-Uhlenbeck noise along axis 1, stationary from the start.

    Exact discretisation of :math:`d\xi = -\xi/\tau\, dt + \sigma\sqrt{2/\tau}\, dW`:
    :math:`\xi_{t+1} = \rho\, \xi_t + \sigma \sqrt{1-\rho^2}\, \epsilon_t`,
    :math:`\rho = e^{-dt/\tau}`, :math:`\xi_0 \sim N(0, \sigma^2)`; the stationary
    standard deviation is ``sigma``. ``shape = (n, T, ...)``.
    """
    rho = np.exp(-dt / tau)
    eps = rng.standard_normal(shape)
    out = np.empty(shape)
    out[:, 0] = sigma * eps[:, 0]
    scale = sigma * np.sqrt(1.0 - rho**2)
    for t in range(1, shape[1]):
        out[:, t] = rho * out[:, t - 1] + scale * eps[:, t]
    return out


def drop_burn_in(rng: np.random.Generator, record: dict[str, np.ndarray], actions: np.ndarray, burn: int,
                 obs_noise: float) -> dict[str, np.ndarray]:
    """Drop the first ``burn`` frames of a valve-arm run and add the angle observations.

    ``record``: states ``(n, burn + T, ...)`` including ``angle (n, burn + T, 2)``;
    ``actions (n, burn + T, d)``. Returns the cropped states, ``actions`` and
    ``obs = angle + obs_noise * N(0, 1)`` (drawn from ``rng`` after everything else).
    """
    out = {key: val[:, burn:] for key, val in record.items()}
    out["actions"] = actions[:, burn:]
    out["obs"] = out["angle"] + obs_noise * rng.standard_normal(out["angle"].shape)
    return out

r"""2-D constant-velocity tracking (chapter 1): noisy positions of a manoeuvring point.

The data are drawn from exactly the linear-Gaussian model a Kalman filter
assumes, so the filter is the optimal estimator here and learned noise
parameters can be compared with the true ones stored in the metadata.

State :math:`s_t = (p_x, p_y, v_x, v_y)` in metres and metres per second,
sampled every :math:`\Delta` seconds (white-noise acceleration model):

.. math::

    s_{t+1} = F s_t + w_t,\quad
    F = \begin{pmatrix} I_2 & \Delta I_2 \\ 0 & I_2 \end{pmatrix},\quad
    w_t \sim N\!\left(0,\; q \begin{pmatrix} \Delta^3/3\, I_2 & \Delta^2/2\, I_2 \\
    \Delta^2/2\, I_2 & \Delta\, I_2 \end{pmatrix}\right),

.. math::

    y_t = H s_t + v_t,\quad H = (I_2\;\; 0),\quad v_t \sim N(0, r^2 I_2),

with :math:`s_0 \sim N(0, \operatorname{diag}(\sigma_p^2, \sigma_p^2, \sigma_v^2, \sigma_v^2))`.
Observations are missing independently with probability ``p_missing`` and,
in addition, over one contiguous gap of ``gap_length`` steps per sequence
(placed at random after the first 10 steps); the first step is always observed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "cv_matrices", "simulate_tracking", "generate"]

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    "dt": 0.1,          # s
    "q": 0.5,           # m^2/s^3, white-noise acceleration spectral density
    "r": 1.0,           # m, observation noise standard deviation
    "sigma_p0": 5.0,    # m, initial position spread
    "sigma_v0": 1.0,    # m/s, initial velocity spread
    "p_missing": 0.1,
    "gap_length": 15,
}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (50, 100, 1101),
    "test": (50, 100, 1102),
}


def cv_matrices(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition ``F`` ``(4, 4)`` and process covariance ``Q`` ``(4, 4)`` of the model above."""
    i2 = np.eye(2)
    F = np.block([[i2, dt * i2], [np.zeros((2, 2)), i2]])
    Q = q * np.block([[dt**3 / 3 * i2, dt**2 / 2 * i2], [dt**2 / 2 * i2, dt * i2]])
    return F, Q


def simulate_tracking(seed: int, n: int, T: int, params: dict | None = None) -> dict[str, np.ndarray]:
    """Draw ``n`` sequences of length ``T``; pure function of its arguments.

    Returns float64/bool arrays: ``states (n, T, 4)``, ``obs (n, T, 2)`` (0 where
    missing), ``clean (n, T, 2)`` (true positions), ``valid (n, T)``.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    rng = np.random.default_rng(seed)
    F, Q = cv_matrices(p["dt"], p["q"])
    LQ = np.linalg.cholesky(Q)
    s = np.empty((n, T, 4))
    s[:, 0] = rng.standard_normal((n, 4)) * np.array([p["sigma_p0"]] * 2 + [p["sigma_v0"]] * 2)
    w = rng.standard_normal((n, T, 4)) @ LQ.T
    for t in range(1, T):
        s[:, t] = s[:, t - 1] @ F.T + w[:, t - 1]
    clean = s[:, :, :2]
    obs = clean + p["r"] * rng.standard_normal((n, T, 2))
    valid = rng.random((n, T)) >= p["p_missing"]
    L = int(p["gap_length"])
    if L > 0:
        start = rng.integers(10, T - L, size=n)
        t = np.arange(T)
        valid &= ~((t[None] >= start[:, None]) & (t[None] < start[:, None] + L))
    valid[:, 0] = True
    obs = np.where(valid[..., None], obs, 0.0)
    return {"states": s, "obs": obs, "clean": clean, "valid": valid}


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": float32/bool array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays: dict[str, np.ndarray] = {}
    splits_meta = {}
    for split, (n, T, seed) in SPLITS.items():
        out = simulate_tracking(seed, n, T, p)
        arrays[f"{split}__obs"] = out["obs"].astype(np.float32)
        arrays[f"{split}__valid"] = out["valid"]
        arrays[f"{split}__targets"] = out["clean"].astype(np.float32)
        arrays[f"{split}__hidden__state"] = out["states"].astype(np.float32)
        splits_meta[split] = {"n": n, "T": T, "seed": seed}
    meta = {
        "generator": {"name": "pgm_wm.datasets.tracking.simulate_tracking", "version": VERSION,
                      "params": p},
        "splits": splits_meta,
        "dt": p["dt"],
        "units": {"obs": "m", "targets": "m", "state": "m, m, m/s, m/s"},
        "obs_names": ["x", "y"],
        "action_names": [],
        "target_names": ["x_true", "y_true"],
        "hidden_names": {"state": ["x", "y", "vx", "vy"]},
        "description": "2-D constant-velocity (white-noise acceleration) target, noisy positions, "
                       "about 10% of positions missing plus one 15-step gap per sequence.",
    }
    return arrays, meta

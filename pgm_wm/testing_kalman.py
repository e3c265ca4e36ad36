"""The independent Kalman reference that tests and the Chapter-1 notebook share: filterpy's
``KalmanFilter`` (update before predict, ``None`` for a missing measurement).

Needs filterpy (a test/notebook dependency, not one of the package's). The coordinator
re-exports these functions from :mod:`pgm_wm.testing`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["FilterpyRun", "filterpy_filter", "filterpy_rts"]


class FilterpyRun(NamedTuple):
    """Per-step filterpy outputs of one sequence: posterior means ``(T, n)`` and covariances
    ``(T, n, n)``, one-step predictions after each step (``next_means``, ``next_covs``) and the
    log-likelihood terms ``(T,)`` (0 at missing steps)."""

    means: np.ndarray
    covs: np.ndarray
    next_means: np.ndarray
    next_covs: np.ndarray
    log_likelihoods: np.ndarray


def _make(F, H, Q, R, x0, P0, B=None):
    from filterpy.kalman import KalmanFilter

    n, m = np.shape(F)[0], np.shape(H)[0]
    kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=0 if B is None else np.shape(B)[1])
    kf.F, kf.H, kf.Q, kf.R = np.asarray(F), np.asarray(H), np.asarray(Q), np.asarray(R)
    kf.x, kf.P = np.array(x0, dtype=float), np.array(P0, dtype=float)
    if B is not None:
        kf.B = np.asarray(B)
    return kf


def filterpy_filter(zs, valid, F, H, Q, R, x0, P0, B=None, us=None) -> FilterpyRun:
    """Run filterpy over one sequence ``zs: (T, m)`` with ``valid: (T,)`` bool (False = missing)
    and optional control ``us: (T, k)``: for each step update (skipped where missing), record,
    then predict."""
    kf = _make(F, H, Q, R, x0, P0, B)
    means, covs, nmeans, ncovs, lls = [], [], [], [], []
    for i, (z, ok) in enumerate(zip(np.asarray(zs), np.asarray(valid))):
        kf.update(z if ok else None)
        means.append(kf.x.copy())
        covs.append(kf.P.copy())
        lls.append(kf.log_likelihood if ok else 0.0)
        kf.predict(u=None if us is None else np.asarray(us)[i])
        nmeans.append(kf.x.copy())
        ncovs.append(kf.P.copy())
    return FilterpyRun(np.array(means), np.array(covs), np.array(nmeans), np.array(ncovs), np.array(lls))


def filterpy_rts(means, covs, F, Q) -> tuple[np.ndarray, np.ndarray]:
    """filterpy's RTS smoother over filtered ``means (T, n)``, ``covs (T, n, n)``: ``(means, covs)``."""
    kf = _make(F, np.zeros((1, np.shape(F)[0])), Q, np.eye(1), np.zeros(np.shape(F)[0]), np.eye(np.shape(F)[0]))
    xs, Ps, _, _ = kf.rts_smoother(np.asarray(means), np.asarray(covs))
    return xs, Ps

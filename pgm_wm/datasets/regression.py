"""Ridge regression with an intercept, the one linear read-out of the datasets' structure checks
(:mod:`pgm_wm.datasets.diagnostics`, :mod:`pgm_wm.datasets.structure`, the ``pam_arm``
converter); numpy only, no dependency on the loader."""

from __future__ import annotations

import numpy as np

__all__ = ["ridge_rmse"]


def ridge_rmse(X: np.ndarray, Y: np.ndarray, X_test: np.ndarray, Y_test: np.ndarray, lam: float = 1e-8) -> float:
    r"""Fit ridge regression with intercept on standardised ``X (N, p)`` -> ``Y (N, q)``; test RMSE.

    :math:`W = (Z^\top Z + \lambda N I)^{-1} Z^\top Y` with ``Z`` the standardised
    features plus a column of ones; the RMSE is over all entries of ``Y_test``.
    """
    mu, sd = X.mean(0), X.std(0) + 1e-12
    Z = np.c_[(X - mu) / sd, np.ones(len(X))]
    W = np.linalg.solve(Z.T @ Z + lam * len(Z) * np.eye(Z.shape[1]), Z.T @ Y)
    pred = np.c_[(X_test - mu) / sd, np.ones(len(X_test))] @ W
    return float(np.sqrt(((pred - Y_test) ** 2).mean()))

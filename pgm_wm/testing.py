r"""Oracles and random test objects shared by the tests and the notebooks' checks.

Everything here is seeded through an explicit ``torch.Generator`` and defaults to float64, so a
check that compares a fast routine with its reference is reproducible and not limited by
float32 rounding.

* :func:`random_spd`, :func:`random_gaussian` — random symmetric positive-definite matrices and
  dense Gaussians (the oracle representation, Chapter 1).
* :func:`random_factorized_belief` — a random valid factorized belief (Chapter 3, Eq.
  rkn-factorized): positive variances and a side covariance with
  :math:`|\sigma^s| < \sqrt{\sigma^u\sigma^l}`.
* :func:`block_matrix` — assemble ``[[B11, B12], [B21, B22]]`` (e.g. from diagonal blocks).

* :func:`filterpy_filter`, :func:`filterpy_rts` / :class:`FilterpyRun` — the independent
  Kalman reference of Chapter 1: filterpy's ``KalmanFilter`` (update before predict, ``None`` for
  a missing measurement) run sequence by sequence. Needs filterpy (a test and notebook
  dependency, imported on use, not one of the package's).
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

import torch
from torch import Tensor

from .factorized import FactorizedBelief
from .gaussian import Gaussian

__all__ = ["random_spd", "random_gaussian", "random_factorized_belief", "block_matrix", "FilterpyRun",
           "filterpy_filter", "filterpy_rts"]


def _batch(batch: int | Sequence[int]) -> tuple[int, ...]:
    b = (batch,) if isinstance(batch, int) else tuple(batch)
    if any(int(x) <= 0 for x in b):
        raise ValueError(f"batch: sizes must be positive, got {b}")
    return b


def random_spd(n: int, batch: int | Sequence[int] = (), generator: torch.Generator | None = None,
               dtype: torch.dtype = torch.float64, min_eig: float = 0.1) -> Tensor:
    r"""Random SPD matrices ``(*batch, n, n)``: :math:`X X^\top / n + \lambda_{min} I` with
    standard normal :math:`X`, so every eigenvalue is at least ``min_eig``."""
    if n <= 0:
        raise ValueError(f"n: must be positive, got {n}")
    if not min_eig > 0:
        raise ValueError(f"min_eig: must be positive, got {min_eig}")
    x = torch.randn(*_batch(batch), n, n, generator=generator, dtype=dtype)
    return x @ x.transpose(-1, -2) / n + min_eig * torch.eye(n, dtype=dtype)


def random_gaussian(n: int, batch: int | Sequence[int] = (), generator: torch.Generator | None = None,
                    dtype: torch.dtype = torch.float64) -> Gaussian:
    """A random dense Gaussian: standard normal mean, :func:`random_spd` covariance."""
    mean = torch.randn(*_batch(batch), n, generator=generator, dtype=dtype)
    return Gaussian(mean, random_spd(n, batch, generator, dtype))


def random_factorized_belief(batch: int | Sequence[int], m: int, generator: torch.Generator | None = None,
                             dtype: torch.dtype = torch.float64, max_corr: float = 0.8,
                             scale: float = 1.0) -> FactorizedBelief:
    r"""A random factorized belief over :math:`2m` latents: :math:`\sigma^u, \sigma^l \sim U(0.5, 1.5)`,
    :math:`\sigma^s = \rho\sqrt{\sigma^u\sigma^l}` with :math:`\rho \sim U(-\text{max\_corr},
    \text{max\_corr})` and mean ``scale`` times standard normal (drawn in that order)."""
    if not 0 <= max_corr < 1:
        raise ValueError(f"max_corr: must be in [0, 1), got {max_corr}")
    b = _batch(batch)
    su = 0.5 + torch.rand(*b, m, generator=generator, dtype=dtype)
    sl = 0.5 + torch.rand(*b, m, generator=generator, dtype=dtype)
    ss = max_corr * (su * sl).sqrt() * (2 * torch.rand(*b, m, generator=generator, dtype=dtype) - 1)
    return FactorizedBelief(scale * torch.randn(*b, 2 * m, generator=generator, dtype=dtype), su, sl, ss)


def block_matrix(b11: Tensor, b12: Tensor, b21: Tensor, b22: Tensor) -> Tensor:
    """``[[b11, b12], [b21, b22]]`` for blocks ``(..., m, m)`` -> ``(..., 2m, 2m)``."""
    shapes = {tuple(b.shape) for b in (b11, b12, b21, b22)}
    if len(shapes) != 1 or b11.ndim < 2:
        raise ValueError(f"b11: the four blocks need one common shape (..., m, m), got {sorted(shapes)}")
    return torch.cat([torch.cat([b11, b12], -1), torch.cat([b21, b22], -1)], -2)


# ----------------------------------------------------------------------------- the filterpy reference (Chapter 1)


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

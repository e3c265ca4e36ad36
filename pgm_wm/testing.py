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

The filterpy reference (a textbook Kalman filter from an independent implementation) is added
at the end of this file by the Chapter 1 work.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .factorized import FactorizedBelief
from .gaussian import Gaussian

__all__ = ["random_spd", "random_gaussian", "random_factorized_belief", "block_matrix"]


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

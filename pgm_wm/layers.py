r"""Small neural-network building blocks shared by every chapter's models.

* :func:`mlp` — the one multilayer perceptron (a regression head or a feature trunk).
* :class:`GaussianHead` — the one "features -> diagonal Gaussian" decoder of the recurrent and
  feed-forward baselines (two MLPs, variance through :func:`elup1`).
* Positive maps for learned variances, with **one variance-floor policy**: a smooth
  non-negative map plus a floor, ``variance = g(x) + min_var``, so that a variance is
  bounded away from 0 for *every* finite input (a zero variance breaks the Kalman update and
  the likelihood). :func:`elup1` uses :math:`g = \mathrm{elu} + 1` (Eq. rkn-encoder),
  :func:`positive_variance` uses :math:`g = \mathrm{softplus}` (Eq. ba-update). Without an
  explicit ``min_var`` the floor is :func:`variance_floor` of the dtype,
  :math:`\sqrt{\text{tiny}}` (1.1e-19 in float32, 1.5e-154 in float64): far below any
  variance a model can mean, yet its reciprocal and square are still finite normal numbers.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_last_dims

__all__ = ["mlp", "GaussianHead", "variance_floor", "elup1", "positive_variance"]


def mlp(
    in_dim: int,
    hidden: Sequence[int],
    out_dim: int | None = None,
    activation: type[nn.Module] = nn.ReLU,
) -> nn.Sequential:
    """A multilayer perceptron ``in_dim -> hidden... [-> out_dim]``.

    Each hidden width adds ``Linear -> activation``. With ``out_dim`` a final ``Linear`` layer
    without activation follows (a regression head); with ``out_dim=None`` the network ends with
    the last hidden layer's activation (a feature trunk of size ``hidden[-1]``).
    """
    if out_dim is None and len(hidden) == 0:
        raise ValueError("hidden: a trunk without out_dim needs at least one hidden layer")
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), activation()]
        d = h
    if out_dim is not None:
        layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def variance_floor(dtype: torch.dtype) -> float:
    r"""The default variance floor of a floating dtype: :math:`\sqrt{\text{finfo(dtype).tiny}}`."""
    if not dtype.is_floating_point:
        raise ValueError(f"dtype: expected a floating dtype, got {dtype}")
    return math.sqrt(torch.finfo(dtype).tiny)


def _floored(v: Tensor, min_var: float | None) -> Tensor:
    if min_var is None:
        min_var = variance_floor(v.dtype)
    elif not min_var > 0:
        raise ValueError(f"min_var: must be positive, got {min_var}")
    return v + min_var


def elup1(x: Tensor, min_var: float | None = None) -> Tensor:
    r"""``elu(x) + 1 + min_var``: the smooth map onto :math:`(0, \infty)` of the RKN's variances.

    ``elu(x) + 1`` equals ``x + 1`` for ``x > 0`` and ``exp(x)`` for ``x <= 0``; the second
    branch is evaluated as ``exp(x)`` (written ``(exp(x) - 1) + 1`` it cancels to 0 in float32
    below ``x = -16.6``). ``exp(x)`` itself underflows to 0 below about ``-104`` in float32, so the
    floor ``min_var`` (default :func:`variance_floor`) keeps the result positive for every finite
    input (issue: encoder variances of inputs scaled by 1e4).
    """
    return _floored(torch.where(x > 0, x + 1.0, torch.exp(x.clamp(max=0.0))), min_var)


def positive_variance(raw: Tensor, min_var: float | None = None) -> Tensor:
    r"""Map an unconstrained network output to a variance: :math:`\mathrm{softplus}(x) + v_{min}`.

    Softplus is smooth, strictly positive and grows only linearly for large inputs (``exp``
    would overflow and make the precision :math:`1/\sigma` vanish exponentially fast); the floor
    ``min_var`` (default :func:`variance_floor`) bounds every element's precision by
    :math:`1/v_{min}`, so no element can take all the weight or divide by zero in Eq. (ba-update).
    """
    return _floored(F.softplus(raw), min_var)


class GaussianHead(nn.Module):
    r"""Decoder of a deterministic feature vector: ``h -> (mean, var)``, ``var = elup1(·)``.

    Two MLPs (:func:`mlp`) with hidden sizes ``hidden`` (mean) and ``var_hidden`` (variance,
    default: the same), the counterpart of :class:`pgm_wm.rkn.BeliefDecoder` for a recurrent or
    feed-forward network. ``h: (..., in_dim)`` -> ``mean, var: (..., out_dim)``.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        hidden: Sequence[int] = (64,),
        var_hidden: Sequence[int] | None = None,
        activation: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        if in_dim <= 0 or out_dim <= 0:
            raise ValueError(f"out_dim: need in_dim > 0 and out_dim > 0, got {in_dim}, {out_dim}")
        self.in_dim, self.out_dim = in_dim, out_dim
        self.mean_net = mlp(in_dim, hidden, out_dim, activation)
        self.var_net = mlp(in_dim, hidden if var_hidden is None else var_hidden, out_dim, activation)

    def forward(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """``h: (..., in_dim)`` -> ``(mean, var)`` each ``(..., out_dim)``."""
        check_last_dims("h", h, (self.in_dim,))
        return self.mean_net(h), elup1(self.var_net(h))

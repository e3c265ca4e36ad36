r"""Dense Gaussian algebra: the three identities every chapter of the book reuses.

Chapter 1 derives them; every later model is a specialization.

* **Marginalizing linear Gaussian causes** — Eq. (gauss-marginal). If
  :math:`y = \sum_i A_i u_i + b + \varepsilon` with independent
  :math:`u_i \sim \mathcal N(\mu_i, \Sigma_i)` and :math:`\varepsilon \sim \mathcal N(0, Q)`, then

  .. math:: y \sim \mathcal N\Big(\sum_i A_i \mu_i + b,\; Q + \sum_i A_i \Sigma_i A_i^\top\Big).

  The Kalman predict step is the case of one cause (the state); the action-conditional,
  hidden-parameter and multi-time-scale models add more causes.

* **The joint of a linear-Gaussian model** — Eq. (gauss-joint). With
  :math:`x \sim \mathcal N(\mu, \Sigma)` and :math:`y \mid x \sim \mathcal N(Hx + b, R)`,

  .. math:: \begin{bmatrix} x \\ y \end{bmatrix} \sim \mathcal N\left(
            \begin{bmatrix} \mu \\ H\mu + b \end{bmatrix},
            \begin{bmatrix} \Sigma & \Sigma H^\top \\ H \Sigma & H\Sigma H^\top + R \end{bmatrix}\right).

* **Conditioning (Bayes' rule)** — Eq. (gauss-condition). For a joint Gaussian over
  :math:`(x, y)` with blocks :math:`\Sigma_{xx}, \Sigma_{xy}, \Sigma_{yy}`,

  .. math:: x \mid y \sim \mathcal N\big(\mu_x + \Sigma_{xy}\Sigma_{yy}^{-1}(y - \mu_y),\;
            \Sigma_{xx} - \Sigma_{xy}\Sigma_{yy}^{-1}\Sigma_{yx}\big).

  The Kalman update is this formula applied to the joint above; its gain is
  :math:`K = \Sigma H^\top S^{-1}` with innovation covariance :math:`S = H\Sigma H^\top + R`.

* **Log-density** — Eq. (gauss-logpdf), and the evidence :math:`\log p(y)` of an observation,
  Eq. (gauss-evidence), which the Kalman filter sums into the log-likelihood.

All functions are batched over leading dimensions (``mean: (..., n)``, ``cov: (..., n, n)``;
leading dimensions broadcast), differentiable, and work in float32 or float64.

Implementation note: the private ``_*_core`` functions hold the arithmetic without any input
checks; the public functions validate their arguments once and then call them. The Kalman
filter (:mod:`pgm_wm.kalman`) validates a whole sequence once and calls the same cores inside
its time loop, so there is exactly one implementation of each identity.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_same_batch, check_same_dtype, check_spd, check_tensor
from .beliefs import Gaussian  # the class lives with the belief family; re-exported here
from ._linalg import (symmetrize as _sym, matvec as _matvec,
                      predict_core as _predict_core, condition_core as _condition_core)

__all__ = [
    "Gaussian",
    "log_density",
    "marginalize_linear",
    "joint_linear_gaussian",
    "condition_on_block",
    "condition",
    "condition_with_evidence",
]

# ---------------------------------------------------------------------------------------------
# Public, validated API
# ---------------------------------------------------------------------------------------------


def log_density(x: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    r"""Gaussian log-density, Eq. (gauss-logpdf):

    .. math:: \log\mathcal N(x\mid\mu,\Sigma) = -\tfrac12\big[(x-\mu)^\top\Sigma^{-1}(x-\mu)
              + \log\det\Sigma + n\log 2\pi\big].

    Shapes: ``x, mean: (..., n)``, ``cov: (..., n, n)``; returns ``(...)``.
    Computed with a Cholesky factor (no explicit inverse).
    """
    check_tensor("x", x, min_ndim=1)
    n = x.shape[-1]
    check_last_dims("mean", mean, (n,))
    check_last_dims("cov", cov, (n, n))
    check_same_batch(("x", "mean", "cov"), (x, mean, cov), (1, 1, 2))
    check_same_dtype(("x", "mean", "cov"), (x, mean, cov))
    check_finite("x", x.detach())
    check_finite("mean", mean.detach())
    check_finite("cov", cov.detach())
    return Gaussian(mean, cov).log_prob(x)


def marginalize_linear(
    causes: Sequence[tuple[Tensor | None, Gaussian]],
    noise_cov: Tensor | None = None,
    offset: Tensor | None = None,
    *,
    validate: bool = True,
) -> Gaussian:
    r"""Distribution of :math:`y = \sum_i A_i u_i + b + \varepsilon`, Eq. (gauss-marginal).

    Args:
        causes: pairs ``(A_i, u_i)`` with ``A_i: (..., m, n_i)`` (``None`` means identity) and
            independent Gaussian causes ``u_i`` of dimension ``n_i``.
        noise_cov: covariance ``Q: (..., m, m)`` of the independent noise :math:`\varepsilon`
            (positive semi-definite), or ``None`` for no noise.
        offset: known additive term ``b: (..., m)`` (e.g. a control input ``B u``), or ``None``.
        validate: check that ``noise_cov`` is symmetric positive semi-definite (one
            eigenvalue computation); shapes are always checked.

    Returns:
        :math:`\mathcal N(\sum_i A_i\mu_i + b,\; Q + \sum_i A_i\Sigma_iA_i^\top)`.
    """
    if len(causes) == 0:
        raise ValueError("causes: need at least one (A, Gaussian) pair")
    mean: Tensor | None = None
    cov: Tensor | None = None
    for i, item in enumerate(causes):
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise ValueError(f"causes[{i}]: expected a pair (A, Gaussian)")
        A, u = item
        if not isinstance(u, Gaussian):
            raise ValueError(f"causes[{i}]: expected a Gaussian, got {type(u).__name__}")
        if A is None:
            m_i, c_i = u.mean, u.cov
        else:
            check_last_dims(f"causes[{i}].A", A, (None, u.dim))
            m_i, c_i = _predict_core(u.mean, u.cov, A, None, None)
        if mean is not None and m_i.shape[-1] != mean.shape[-1]:
            raise ValueError(
                f"causes[{i}]: output dimension {m_i.shape[-1]} differs from the first cause's {mean.shape[-1]}"
            )
        mean = m_i if mean is None else mean + m_i
        cov = c_i if cov is None else cov + c_i
    assert mean is not None and cov is not None
    m = mean.shape[-1]
    if noise_cov is not None:
        check_last_dims("noise_cov", noise_cov, (m, m))
        if validate:
            check_spd("noise_cov", noise_cov.detach(), semidefinite=True)
        cov = cov + noise_cov
    if offset is not None:
        check_last_dims("offset", offset, (m,))
        mean = mean + offset
    return Gaussian(mean, _sym(cov))


def joint_linear_gaussian(
    prior: Gaussian, H: Tensor, R: Tensor, offset: Tensor | None = None
) -> Gaussian:
    r"""Joint of :math:`x \sim \mathcal N(\mu,\Sigma)` and :math:`y\mid x \sim \mathcal N(Hx+b, R)`,
    Eq. (gauss-joint). Returns a Gaussian over ``[x; y]`` of dimension ``n + m``.

    Shapes: ``H: (..., m, n)``, ``R: (..., m, m)``, ``offset: (..., m)``.
    """
    n = prior.dim
    check_last_dims("prior.cov", prior.cov, (n, n))
    check_last_dims("H", H, (None, n))
    m = H.shape[-2]
    check_last_dims("R", R, (m, m))
    y = marginalize_linear([(H, prior)], noise_cov=R, offset=offset, validate=False)
    cross = prior.cov @ H.transpose(-1, -2)  # Σ Hᵀ : (..., n, m)
    batch = torch.broadcast_shapes(prior.cov.shape[:-2], y.cov.shape[:-2], cross.shape[:-2])
    top = torch.cat([prior.cov.expand(*batch, n, n), cross.expand(*batch, n, m)], dim=-1)
    bottom = torch.cat(
        [cross.transpose(-1, -2).expand(*batch, m, n), y.cov.expand(*batch, m, m)], dim=-1
    )
    mb = torch.broadcast_shapes(prior.mean.shape[:-1], y.mean.shape[:-1])
    mean = torch.cat([prior.mean.expand(*mb, n), y.mean.expand(*mb, m)], dim=-1)
    return Gaussian(mean, torch.cat([top, bottom], dim=-2))


def condition_on_block(joint: Gaussian, n_first: int, y: Tensor) -> Gaussian:
    r"""Condition a joint Gaussian over ``[x; y]`` on its last block ``y``, Eq. (gauss-condition).

    ``x`` is the first ``n_first`` coordinates. The posterior covariance is the Schur
    complement :math:`\Sigma_{xx} - \Sigma_{xy}\Sigma_{yy}^{-1}\Sigma_{yx}`; computed with a
    Cholesky solve with :math:`\Sigma_{yy}` (never an explicit inverse).
    """
    n = n_first
    if not isinstance(n, int) or not 0 < n < joint.dim:
        raise ValueError(f"n_first: must be an integer in (0, {joint.dim}), got {n!r}")
    check_last_dims("y", y, (joint.dim - n,))
    mu_x, mu_y = joint.mean[..., :n], joint.mean[..., n:]
    s_xx = joint.cov[..., :n, :n]
    s_xy = joint.cov[..., :n, n:]
    s_yy = joint.cov[..., n:, n:]
    chol, info = torch.linalg.cholesky_ex(_sym(s_yy))
    if bool((info != 0).any()):
        raise ValueError("joint.cov: the observed block is not positive definite")
    # G = Σ_xy Σ_yy^{-1}  (solve Σ_yy Gᵀ = Σ_yx)
    gain = torch.cholesky_solve(s_xy.transpose(-1, -2), chol).transpose(-1, -2)
    mean = mu_x + _matvec(gain, y - mu_y)
    cov = s_xx - gain @ s_xy.transpose(-1, -2)
    return Gaussian(mean, _sym(cov))


def _check_observation(prior: Gaussian, H: Tensor, R: Tensor, y: Tensor, offset: Tensor | None) -> None:
    n = prior.dim
    check_last_dims("H", H, (None, n))
    m = H.shape[-2]
    check_last_dims("R", R, (m, m))
    check_last_dims("y", y, (m,))
    if offset is not None:
        check_last_dims("offset", offset, (m,))
    check_same_batch(
        ("y", "prior.mean", "prior.cov", "H", "R"), (y, prior.mean, prior.cov, H, R), (1, 1, 2, 2, 2)
    )


def condition_with_evidence(
    prior: Gaussian,
    H: Tensor,
    R: Tensor,
    y: Tensor,
    offset: Tensor | None = None,
    *,
    validate: bool = True,
) -> tuple[Gaussian, Tensor]:
    r"""Bayes' rule for a linear-Gaussian observation :math:`y\mid x\sim\mathcal N(Hx+b, R)`, with the evidence.

    Posterior :math:`p(x\mid y)` by Eq. (gauss-condition) applied to the joint Eq. (gauss-joint):

    .. math:: S = H\Sigma H^\top + R,\quad K = \Sigma H^\top S^{-1},\quad
              \mu^+ = \mu + K(y - H\mu - b),\quad \Sigma^+ = \Sigma - K S K^\top,

    and the evidence :math:`\log p(y) = \log\mathcal N(y\mid H\mu + b, S)` (Eq. gauss-evidence).
    Computed with the Cholesky factor of :math:`S` and two triangular solves, no inverse;
    :math:`\Sigma^+` in the Joseph form Eq. (kf-joseph), symmetric positive semi-definite
    (``_update_cov``).

    Shapes: ``H: (..., m, n)``, ``R: (..., m, m)``, ``y: (..., m)``, ``offset: (..., m)``.
    Returns ``(posterior, log p(y))`` with ``log p(y): (...)``.
    With ``validate`` (default) ``R`` must be symmetric positive definite, ``y``, ``H`` and the
    prior finite, and all tensors of one floating dtype (float32 or float64); each failure
    raises a ``ValueError`` naming the argument. ``validate=False`` skips every value check
    (a non-positive-definite ``S`` then gives NaN instead of an error).
    """
    _check_observation(prior, H, R, y, offset)
    if validate:
        check_same_dtype(("y", "prior.mean", "prior.cov", "H", "R"), (y, prior.mean, prior.cov, H, R))
        check_finite("prior.mean", prior.mean.detach())
        check_finite("prior.cov", prior.cov.detach())
        check_finite("H", H.detach())
        check_spd("R", R.detach())
        check_finite("y", y.detach())
    mean, cov, loglik, info = _condition_core(prior.mean, prior.cov, H, R, y, offset)
    if validate and bool((info != 0).any()):
        raise ValueError("prior.cov: the innovation covariance H Σ Hᵀ + R is not positive definite "
                         "although R is (the prior covariance or H contains NaN/inf or is too large)")
    return Gaussian(mean, cov), loglik


def condition(
    prior: Gaussian,
    H: Tensor,
    R: Tensor,
    y: Tensor,
    offset: Tensor | None = None,
    *,
    validate: bool = True,
) -> Gaussian:
    r"""Posterior :math:`p(x\mid y)` for :math:`y\mid x\sim\mathcal N(Hx+b,R)`, Eq. (gauss-condition).

    See :func:`condition_with_evidence`, which also returns :math:`\log p(y)`.
    """
    return condition_with_evidence(prior, H, R, y, offset, validate=validate)[0]

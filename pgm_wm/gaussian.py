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

import math
from typing import Sequence

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_same_batch, check_same_dtype, check_spd, check_tensor
from .beliefs import Gaussian  # the class lives with the belief family; re-exported here

__all__ = [
    "Gaussian",
    "log_density",
    "marginalize_linear",
    "joint_linear_gaussian",
    "condition_on_block",
    "condition",
    "condition_with_evidence",
]

_LOG_2PI = math.log(2.0 * math.pi)


def _sym(m: Tensor) -> Tensor:
    """Symmetric part ``(M + Mᵀ) / 2`` (removes floating-point asymmetry)."""
    return 0.5 * (m + m.transpose(-1, -2))


def _matvec(A: Tensor, x: Tensor) -> Tensor:
    """``A x`` for ``A: (..., m, n)``, ``x: (..., n)`` with broadcasting -> ``(..., m)``."""
    return (A @ x.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------------------------------------
# Unchecked arithmetic (one implementation of each identity)
# ---------------------------------------------------------------------------------------------


def _chol_logpdf(diff: Tensor, chol: Tensor) -> Tensor:
    r""":math:`\log\mathcal N(d\mid 0, LL^\top)` from ``diff: (..., m)`` and a Cholesky factor ``(..., m, m)``."""
    m = diff.shape[-1]
    sol = torch.linalg.solve_triangular(chol, diff.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * (sol.square().sum(-1) + logdet + m * _LOG_2PI)


def _addmm(C: Tensor, A: Tensor, B: Tensor, alpha: float = 1.0) -> Tensor:
    """``C + alpha · A @ B`` with broadcasting; a single fused BLAS call when all are 2-D."""
    if C.ndim == 2 and A.ndim == 2 and B.ndim == 2:
        return torch.addmm(C, A, B, alpha=alpha)
    AB = A @ B
    return C + AB if alpha == 1.0 else (C - AB if alpha == -1.0 else C + alpha * AB)


# Largest n_out * n_in for which A Σ Aᵀ is computed as one GEMM with a (n_out², n_in²) matrix.
_KRON_MAX = 64


def _sandwich_operator(A: Tensor) -> Tensor | None:
    r"""Matrix :math:`M` with :math:`\operatorname{vec}(A\Sigma A^\top) = \operatorname{vec}(\Sigma) M`
    for symmetric :math:`\Sigma`, or ``None`` when ``A`` is batched or too large.

    :math:`M` is the symmetrized Kronecker product :math:`\tfrac12(A\otimes A + (A\otimes A)P)`
    (``P`` swaps the two input indices), so rows ``(i, j)`` and ``(j, i)`` of the result are
    computed from identical coefficients and the output is symmetric. One small GEMM over the
    whole batch replaces two batched matrix products (much faster for small ``n`` on CPU).
    """
    if A.ndim != 2 or A.shape[0] * A.shape[1] > _KRON_MAX:
        return None
    p, q = A.shape
    kron = A[:, None, :, None] * A[None, :, None, :]          # [i, j, k, l] = A_ik A_jl
    kron = 0.5 * (kron + kron.transpose(2, 3))                 # symmetrize over (k, l)
    return kron.reshape(p * p, q * q).T.contiguous()           # (q², p²)


def _sandwich(A: Tensor, cov: Tensor, op: Tensor | None = None, Q: Tensor | None = None) -> Tensor:
    r""":math:`A\Sigma A^\top + Q` (symmetric) for ``A: (..., p, q)``, ``cov: (..., q, q)``; ``op``
    from :func:`_sandwich_operator` selects the single-GEMM path."""
    if op is None:
        out = _sym(A @ cov @ A.transpose(-1, -2))
        return out if Q is None else out + Q
    p, q = A.shape
    lead = cov.shape[:-2]
    flat = cov.reshape(*lead, q * q)
    if Q is None:
        return (flat @ op).reshape(*lead, p, p)
    Qf = Q.reshape(*Q.shape[:-2], p * p)
    if flat.ndim == 1 and Qf.ndim == 1:
        return torch.addmv(Qf, op.T, flat).reshape(p, p)
    return _addmm(Qf, flat, op).reshape(*torch.broadcast_shapes(lead, Q.shape[:-2]), p, p)


def _predict_mean(mean: Tensor, A: Tensor, offset: Tensor | None = None) -> Tensor:
    r"""Mean part of Eq. (gauss-marginal) with one cause: :math:`A\mu + b`, unchecked."""
    if A.ndim == 2:
        return mean @ A.T if offset is None else _addmm(offset, mean, A.T)
    m = _matvec(A, mean)
    return m if offset is None else m + offset


def _predict_cov(cov: Tensor, A: Tensor, Q: Tensor | None, op: Tensor | None = None) -> Tensor:
    r"""Covariance part of Eq. (gauss-marginal) with one cause: :math:`A\Sigma A^\top + Q`, unchecked.

    ``op`` is an optional precomputed :func:`_sandwich_operator` of ``A``.
    """
    return _sandwich(A, cov, op, Q)


def _predict_core(
    mean: Tensor,
    cov: Tensor,
    A: Tensor,
    Q: Tensor | None,
    offset: Tensor | None,
    op: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r"""One-cause Eq. (gauss-marginal): :math:`(A\mu + b,\; A\Sigma A^\top + Q)`, unchecked."""
    return _predict_mean(mean, A, offset), _predict_cov(cov, A, Q, op)


def _update_cov(
    cov: Tensor,
    H: Tensor,
    R: Tensor,
    weight: Tensor | None = None,
    op_H: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""Covariance half of Eq. (gauss-condition) in Kalman form, unchecked.

    With :math:`S = H\Sigma H^\top + R = LL^\top` (itself Eq. gauss-marginal) the transposed
    gain is :math:`K^\top = S^{-1}H\Sigma = L^{-\top}(L^{-1}H\Sigma)`, two triangular solves and
    no inverse. The posterior covariance is computed in the **Joseph form**, Eq. (kf-joseph),

    .. math:: \Sigma^+ = (I - KH)\,\Sigma\,(I - KH)^\top + K R K^\top ,

    which equals :math:`\Sigma - KSK^\top` exactly but is a sum of two positive semi-definite
    terms, so it stays positive where :math:`\Sigma - KSK^\top` cancels to zero or below
    (an observation variance far below the prior variance, in either dtype). The covariance
    does not depend on the observed value, so this half can run before (or without) the means.

    Args:
        cov: ``(..., n, n)``; H: ``(..., m, n)``; R: ``(..., m, m)``.
        weight: optional ``(...)`` 0/1 factor; where 0 the update is skipped exactly (:math:`K = 0`).
        op_H: optional :func:`_sandwich_operator` of ``H`` (speed only).

    Returns ``(Σ⁺, L, Kᵀ, info)``: ``L: (..., m, m)`` the Cholesky factor of :math:`S` (for the
    evidence), ``Kᵀ: (..., m, n)`` the transposed gain, ``info`` non-zero where :math:`S` is
    not positive definite.
    """
    HS = (cov @ H.transpose(-1, -2)).transpose(-1, -2)     # H Σ (Σ symmetric): one GEMM for 2-D H
    S = _sandwich(H, cov, op_H, R) if op_H is not None else _addmm(R, HS, H.transpose(-1, -2))
    chol, info = torch.linalg.cholesky_ex(S)               # reads the lower triangle only
    W = torch.linalg.solve_triangular(chol, HS, upper=False)                         # L⁻¹ H Σ
    Kt = torch.linalg.solve_triangular(chol.transpose(-1, -2), W, upper=True)        # S⁻¹ H Σ
    if weight is not None:
        Kt = Kt * weight[..., None, None]
    K = Kt.transpose(-1, -2)
    n = cov.shape[-1]
    A = torch.eye(n, dtype=cov.dtype, device=cov.device) - K @ H                     # I − K H
    return _sym(A @ cov @ A.transpose(-1, -2) + K @ R @ Kt), chol, Kt, info


def _update_mean(
    mean: Tensor, H: Tensor, y: Tensor, Kt: Tensor, offset: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    r"""Mean half of Eq. (gauss-condition): innovation :math:`\varepsilon = y - H\mu - b` and
    :math:`\mu^+ = \mu + K\varepsilon`, with ``Kt`` :math:`= K^\top` from :func:`_update_cov`.

    Returns ``(μ⁺, ε)``; one or two GEMMs over the batch when ``H`` and ``Kt`` are 2-D.
    """
    if offset is not None:
        y = y - offset
    innov = _addmm(y, mean, H.T, alpha=-1.0) if H.ndim == 2 else y - _matvec(H, mean)
    if Kt.ndim == 2:
        return _addmm(mean, innov, Kt), innov
    if Kt.ndim == 3 and mean.ndim == 2 and innov.ndim == 2:   # one small GEMM per batch row
        return torch.baddbmm(mean.unsqueeze(-2), innov.unsqueeze(-2), Kt).squeeze(-2), innov
    return mean + (innov.unsqueeze(-1) * Kt).sum(-2), innov


def _evidence(innov: Tensor, chol: Tensor) -> Tensor:
    r"""Eq. (gauss-evidence): :math:`\log\mathcal N(\varepsilon\mid 0, LL^\top)` for innovations
    ``(..., m)`` and Cholesky factors ``(..., m, m)`` (leading dimensions broadcast)."""
    return _chol_logpdf(innov, chol)


def _condition_core(
    mean: Tensor,
    cov: Tensor,
    H: Tensor,
    R: Tensor,
    y: Tensor,
    offset: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""Eq. (gauss-condition) in Kalman form plus the evidence Eq. (gauss-evidence), unchecked.

    .. math:: S = H\Sigma H^\top + R,\quad K = \Sigma H^\top S^{-1},\quad
              \mu^+ = \mu + K(y - H\mu - b),\quad \Sigma^+ = \Sigma - KSK^\top,\quad
              \log p(y) = \log\mathcal N(y\mid H\mu + b, S),

    = :func:`_update_cov` + :func:`_update_mean` + :func:`_evidence`.
    Returns ``(mean, cov, log p(y), info)``; ``info`` is non-zero where :math:`S` is not
    positive definite.
    """
    new_cov, chol, Kt, info = _update_cov(cov, H, R)
    new_mean, innov = _update_mean(mean, H, y, Kt, offset)
    return new_mean, new_cov, _evidence(innov, chol), info


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
    chol, info = torch.linalg.cholesky_ex(_sym(cov))
    if bool((info != 0).any()):
        raise ValueError("cov: matrix is not positive definite")
    return _chol_logpdf(x - mean, chol)


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

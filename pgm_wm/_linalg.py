r"""Unchecked dense Gaussian arithmetic (private): the one implementation of each identity of
Chapter 1, Eqs. (gauss-marginal), (gauss-condition) and (gauss-logpdf), shared by
:mod:`pgm_wm.gaussian` (which checks its arguments and calls these), the Kalman filters
(:mod:`pgm_wm.kalman`, :mod:`pgm_wm.kalman_parallel`) and their fast backends. No argument is
checked here; nothing here imports another pgm_wm module.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["LOG_2PI", "symmetrize", "matvec", "chol_logpdf", "addmm", "KRON_MAX", "sandwich_operator", "sandwich", "predict_mean", "predict_cov", "predict_core", "update_cov", "update_mean", "evidence", "condition_core"]

LOG_2PI = math.log(2.0 * math.pi)
""":math:`\\log 2\\pi`, the constant of every Gaussian log-density."""


def symmetrize(m: Tensor) -> Tensor:
    """Symmetric part ``(M + Mᵀ) / 2`` (removes floating-point asymmetry)."""
    return 0.5 * (m + m.transpose(-1, -2))


def matvec(A: Tensor, x: Tensor) -> Tensor:
    """``A x`` for ``A: (..., m, n)``, ``x: (..., n)`` with broadcasting -> ``(..., m)``."""
    return (A @ x.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------------------------------------
# Unchecked arithmetic (one implementation of each identity)
# ---------------------------------------------------------------------------------------------


def chol_logpdf(diff: Tensor, chol: Tensor) -> Tensor:
    r""":math:`\log\mathcal N(d\mid 0, LL^\top)` from ``diff: (..., m)`` and a Cholesky factor ``(..., m, m)``."""
    m = diff.shape[-1]
    sol = torch.linalg.solve_triangular(chol, diff.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * (sol.square().sum(-1) + logdet + m * LOG_2PI)


def addmm(C: Tensor, A: Tensor, B: Tensor, alpha: float = 1.0) -> Tensor:
    """``C + alpha · A @ B`` with broadcasting; a single fused BLAS call when all are 2-D."""
    if C.ndim == 2 and A.ndim == 2 and B.ndim == 2:
        return torch.addmm(C, A, B, alpha=alpha)
    AB = A @ B
    return C + AB if alpha == 1.0 else (C - AB if alpha == -1.0 else C + alpha * AB)


# Largest n_out * n_in for which A Σ Aᵀ is computed as one GEMM with a (n_out², n_in²) matrix.
KRON_MAX = 64


def sandwich_operator(A: Tensor) -> Tensor | None:
    r"""Matrix :math:`M` with :math:`\operatorname{vec}(A\Sigma A^\top) = \operatorname{vec}(\Sigma) M`
    for symmetric :math:`\Sigma`, or ``None`` when ``A`` is batched or too large.

    :math:`M` is the symmetrized Kronecker product :math:`\tfrac12(A\otimes A + (A\otimes A)P)`
    (``P`` swaps the two input indices), so rows ``(i, j)`` and ``(j, i)`` of the result are
    computed from identical coefficients and the output is symmetric. One small GEMM over the
    whole batch replaces two batched matrix products (much faster for small ``n`` on CPU).
    """
    if A.ndim != 2 or A.shape[0] * A.shape[1] > KRON_MAX:
        return None
    p, q = A.shape
    kron = A[:, None, :, None] * A[None, :, None, :]          # [i, j, k, l] = A_ik A_jl
    kron = 0.5 * (kron + kron.transpose(2, 3))                 # symmetrize over (k, l)
    return kron.reshape(p * p, q * q).T.contiguous()           # (q², p²)


def sandwich(A: Tensor, cov: Tensor, op: Tensor | None = None, Q: Tensor | None = None) -> Tensor:
    r""":math:`A\Sigma A^\top + Q` (symmetric) for ``A: (..., p, q)``, ``cov: (..., q, q)``; ``op``
    from :func:`sandwich_operator` selects the single-GEMM path."""
    if op is None:
        out = symmetrize(A @ cov @ A.transpose(-1, -2))
        return out if Q is None else out + Q
    p, q = A.shape
    lead = cov.shape[:-2]
    flat = cov.reshape(*lead, q * q)
    if Q is None:
        return (flat @ op).reshape(*lead, p, p)
    Qf = Q.reshape(*Q.shape[:-2], p * p)
    if flat.ndim == 1 and Qf.ndim == 1:
        return torch.addmv(Qf, op.T, flat).reshape(p, p)
    return addmm(Qf, flat, op).reshape(*torch.broadcast_shapes(lead, Q.shape[:-2]), p, p)


def predict_mean(mean: Tensor, A: Tensor, offset: Tensor | None = None) -> Tensor:
    r"""Mean part of Eq. (gauss-marginal) with one cause: :math:`A\mu + b`, unchecked."""
    if A.ndim == 2:
        return mean @ A.T if offset is None else addmm(offset, mean, A.T)
    m = matvec(A, mean)
    return m if offset is None else m + offset


def predict_cov(cov: Tensor, A: Tensor, Q: Tensor | None, op: Tensor | None = None) -> Tensor:
    r"""Covariance part of Eq. (gauss-marginal) with one cause: :math:`A\Sigma A^\top + Q`, unchecked.

    ``op`` is an optional precomputed :func:`sandwich_operator` of ``A``.
    """
    return sandwich(A, cov, op, Q)


def predict_core(
    mean: Tensor,
    cov: Tensor,
    A: Tensor,
    Q: Tensor | None,
    offset: Tensor | None,
    op: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r"""One-cause Eq. (gauss-marginal): :math:`(A\mu + b,\; A\Sigma A^\top + Q)`, unchecked."""
    return predict_mean(mean, A, offset), predict_cov(cov, A, Q, op)


def update_cov(
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
        op_H: optional :func:`sandwich_operator` of ``H`` (speed only).

    Returns ``(Σ⁺, L, Kᵀ, info)``: ``L: (..., m, m)`` the Cholesky factor of :math:`S` (for the
    evidence), ``Kᵀ: (..., m, n)`` the transposed gain, ``info`` non-zero where :math:`S` is
    not positive definite.
    """
    HS = (cov @ H.transpose(-1, -2)).transpose(-1, -2)     # H Σ (Σ symmetric): one GEMM for 2-D H
    S = sandwich(H, cov, op_H, R) if op_H is not None else addmm(R, HS, H.transpose(-1, -2))
    chol, info = torch.linalg.cholesky_ex(S)               # reads the lower triangle only
    W = torch.linalg.solve_triangular(chol, HS, upper=False)                         # L⁻¹ H Σ
    Kt = torch.linalg.solve_triangular(chol.transpose(-1, -2), W, upper=True)        # S⁻¹ H Σ
    if weight is not None:
        Kt = Kt * weight[..., None, None]
    K = Kt.transpose(-1, -2)
    n = cov.shape[-1]
    A = torch.eye(n, dtype=cov.dtype, device=cov.device) - K @ H                     # I − K H
    return symmetrize(A @ cov @ A.transpose(-1, -2) + K @ R @ Kt), chol, Kt, info


def update_mean(
    mean: Tensor, H: Tensor, y: Tensor, Kt: Tensor, offset: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    r"""Mean half of Eq. (gauss-condition): innovation :math:`\varepsilon = y - H\mu - b` and
    :math:`\mu^+ = \mu + K\varepsilon`, with ``Kt`` :math:`= K^\top` from :func:`update_cov`.

    Returns ``(μ⁺, ε)``; one or two GEMMs over the batch when ``H`` and ``Kt`` are 2-D.
    """
    if offset is not None:
        y = y - offset
    innov = addmm(y, mean, H.T, alpha=-1.0) if H.ndim == 2 else y - matvec(H, mean)
    if Kt.ndim == 2:
        return addmm(mean, innov, Kt), innov
    if Kt.ndim == 3 and mean.ndim == 2 and innov.ndim == 2:   # one small GEMM per batch row
        return torch.baddbmm(mean.unsqueeze(-2), innov.unsqueeze(-2), Kt).squeeze(-2), innov
    return mean + (innov.unsqueeze(-1) * Kt).sum(-2), innov


def evidence(innov: Tensor, chol: Tensor) -> Tensor:
    r"""Eq. (gauss-evidence): :math:`\log\mathcal N(\varepsilon\mid 0, LL^\top)` for innovations
    ``(..., m)`` and Cholesky factors ``(..., m, m)`` (leading dimensions broadcast)."""
    return chol_logpdf(innov, chol)


def condition_core(
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

    = :func:`update_cov` + :func:`update_mean` + :func:`evidence`.
    Returns ``(mean, cov, log p(y), info)``; ``info`` is non-zero where :math:`S` is not
    positive definite.
    """
    new_cov, chol, Kt, info = update_cov(cov, H, R)
    new_mean, innov = update_mean(mean, H, y, Kt, offset)
    return new_mean, new_cov, evidence(innov, chol), info

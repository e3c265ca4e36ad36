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

All functions are batched over leading dimensions (``mean: (..., n)``, ``cov: (..., n, n)``),
differentiable, and work in float32 or float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ._checks import check_last_dims, check_spd, check_tensor

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
    return 0.5 * (m + m.transpose(-1, -2))


@dataclass(frozen=True)
class Gaussian:
    """A (batch of) multivariate Gaussian belief(s) :math:`\\mathcal N(\\mu, \\Sigma)`.

    Attributes:
        mean: ``(..., n)``
        cov: ``(..., n, n)``, symmetric positive (semi-)definite.
    """

    mean: Tensor
    cov: Tensor

    def __post_init__(self) -> None:
        check_tensor("mean", self.mean, min_ndim=1)
        n = self.mean.shape[-1]
        check_last_dims("cov", self.cov, (n, n))

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]

    @property
    def var(self) -> Tensor:
        """Marginal variances, the diagonal of ``cov``: ``(..., n)``."""
        return torch.diagonal(self.cov, dim1=-2, dim2=-1)

    def validate(self, name: str = "belief") -> "Gaussian":
        """Check that ``cov`` is symmetric positive definite; raise ``ValueError`` naming ``name``."""
        check_spd(f"{name}.cov", self.cov)
        return self

    def log_prob(self, x: Tensor) -> Tensor:
        """Log-density :math:`\\log\\mathcal N(x\\mid\\mu,\\Sigma)`, Eq. (gauss-logpdf). Returns ``(...)``."""
        return log_density(x, self.mean, self.cov)

    def sample(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw ``n`` samples via the Cholesky factor: returns ``(n, ..., dim)``."""
        chol = torch.linalg.cholesky(_sym(self.cov))
        eps = torch.randn((n, *self.mean.shape), dtype=self.mean.dtype, generator=generator)
        return self.mean + (chol @ eps.unsqueeze(-1)).squeeze(-1)

    def where(self, keep_self: Tensor, other: "Gaussian") -> "Gaussian":
        """Select ``self`` where ``keep_self`` (shape ``(...)``) is True, else ``other``."""
        k = keep_self.to(torch.bool)
        return Gaussian(
            torch.where(k[..., None], self.mean, other.mean),
            torch.where(k[..., None, None], self.cov, other.cov),
        )


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
    chol, info = torch.linalg.cholesky_ex(_sym(cov))
    if bool((info != 0).any()):
        raise ValueError("cov: matrix is not positive definite")
    diff = (x - mean).unsqueeze(-1)
    batch = torch.broadcast_shapes(diff.shape[:-2], chol.shape[:-2])
    diff, chol = diff.expand(*batch, n, 1), chol.expand(*batch, n, n)
    sol = torch.linalg.solve_triangular(chol, diff, upper=False)
    maha = (sol.squeeze(-1) ** 2).sum(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * (maha + logdet + n * _LOG_2PI)


def marginalize_linear(
    causes: Sequence[tuple[Tensor | None, Gaussian]],
    noise_cov: Tensor | None = None,
    offset: Tensor | None = None,
) -> Gaussian:
    r"""Distribution of :math:`y = \sum_i A_i u_i + b + \varepsilon`, Eq. (gauss-marginal).

    Args:
        causes: pairs ``(A_i, u_i)`` with ``A_i: (..., m, n_i)`` (``None`` means identity) and
            independent Gaussian causes ``u_i`` of dimension ``n_i``.
        noise_cov: covariance ``Q: (..., m, m)`` of the independent noise :math:`\varepsilon`
            (positive semi-definite), or ``None`` for no noise.
        offset: known additive term ``b: (..., m)`` (e.g. a control input ``B u``), or ``None``.

    Returns:
        :math:`\mathcal N(\sum_i A_i\mu_i + b,\; Q + \sum_i A_i\Sigma_iA_i^\top)`.
    """
    if len(causes) == 0:
        raise ValueError("causes: need at least one (A, Gaussian) pair")
    mean: Tensor | None = None
    cov: Tensor | None = None
    for i, (A, u) in enumerate(causes):
        if not isinstance(u, Gaussian):
            raise ValueError(f"causes[{i}]: expected a Gaussian, got {type(u).__name__}")
        if A is None:
            m_i, c_i = u.mean, u.cov
        else:
            check_last_dims(f"causes[{i}].A", A, (None, u.dim))
            m_i = (A @ u.mean.unsqueeze(-1)).squeeze(-1)
            c_i = A @ u.cov @ A.transpose(-1, -2)
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
    check_last_dims("H", H, (None, n))
    m = H.shape[-2]
    check_last_dims("R", R, (m, m))
    y = marginalize_linear([(H, prior)], noise_cov=R, offset=offset)
    cross = prior.cov @ H.transpose(-1, -2)  # Σ Hᵀ : (..., n, m)
    batch = torch.broadcast_shapes(prior.cov.shape[:-2], y.cov.shape[:-2], cross.shape[:-2])
    top = torch.cat([prior.cov.expand(*batch, n, n), cross.expand(*batch, n, m)], dim=-1)
    bottom = torch.cat(
        [cross.transpose(-1, -2).expand(*batch, m, n), y.cov.expand(*batch, m, m)], dim=-1
    )
    mb = torch.broadcast_shapes(prior.mean.shape[:-1], y.mean.shape[:-1], batch)
    mean = torch.cat([prior.mean.expand(*mb, n), y.mean.expand(*mb, m)], dim=-1)
    return Gaussian(mean, torch.cat([top, bottom], dim=-2))


def condition_on_block(joint: Gaussian, n_first: int, y: Tensor) -> Gaussian:
    r"""Condition a joint Gaussian over ``[x; y]`` on its last block ``y``, Eq. (gauss-condition).

    ``x`` is the first ``n_first`` coordinates. Uses a Cholesky solve with
    :math:`\Sigma_{yy}` (never an explicit inverse).
    """
    n = n_first
    if not 0 < n < joint.dim:
        raise ValueError(f"n_first: must be in (0, {joint.dim}), got {n}")
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
    mean = mu_x + (gain @ (y - mu_y).unsqueeze(-1)).squeeze(-1)
    cov = s_xx - gain @ s_xy.transpose(-1, -2)
    return Gaussian(mean, _sym(cov))


def condition_with_evidence(
    prior: Gaussian, H: Tensor, R: Tensor, y: Tensor, offset: Tensor | None = None
) -> tuple[Gaussian, Tensor]:
    r"""Bayes' rule for a linear-Gaussian observation, with the evidence.

    Posterior :math:`p(x\mid y)` by Eq. (gauss-condition) in Kalman form,

    .. math:: S = H\Sigma H^\top + R,\quad K = \Sigma H^\top S^{-1},\quad
              \mu^+ = \mu + K(y - H\mu - b),\quad
              \Sigma^+ = (I-KH)\Sigma(I-KH)^\top + KRK^\top,

    (the last is the Joseph form, algebraically equal to :math:`(I-KH)\Sigma` but symmetric and
    positive semi-definite in floating point), and the evidence
    :math:`\log p(y) = \log\mathcal N(y\mid H\mu + b, S)` (Eq. gauss-evidence).

    Shapes: ``H: (..., m, n)``, ``R: (..., m, m)``, ``y: (..., m)``. Returns ``(posterior, log p(y))``.
    """
    n = prior.dim
    check_last_dims("H", H, (None, n))
    m = H.shape[-2]
    check_last_dims("R", R, (m, m))
    check_last_dims("y", y, (m,))
    Ht = H.transpose(-1, -2)
    PHt = prior.cov @ Ht
    S = _sym(H @ PHt + R)
    chol, info = torch.linalg.cholesky_ex(S)
    if bool((info != 0).any()):
        raise ValueError("R: the innovation covariance H Σ Hᵀ + R is not positive definite")
    pred = (H @ prior.mean.unsqueeze(-1)).squeeze(-1)
    if offset is not None:
        check_last_dims("offset", offset, (m,))
        pred = pred + offset
    innov = y - pred
    K = torch.cholesky_solve(PHt.transpose(-1, -2), chol).transpose(-1, -2)  # (..., n, m)
    mean = prior.mean + (K @ innov.unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(n, dtype=prior.cov.dtype, device=prior.cov.device)
    IKH = eye - K @ H
    cov = IKH @ prior.cov @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)
    batch = torch.broadcast_shapes(innov.shape[:-1], chol.shape[:-2])
    sol = torch.linalg.solve_triangular(
        chol.expand(*batch, m, m), innov.unsqueeze(-1).expand(*batch, m, 1), upper=False
    )
    maha = (sol.squeeze(-1) ** 2).sum(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    loglik = -0.5 * (maha + logdet + m * _LOG_2PI)
    return Gaussian(mean, _sym(cov)), loglik


def condition(
    prior: Gaussian, H: Tensor, R: Tensor, y: Tensor, offset: Tensor | None = None
) -> Gaussian:
    r"""Posterior :math:`p(x\mid y)` for :math:`y\mid x\sim\mathcal N(Hx+b,R)`, Eq. (gauss-condition).

    See :func:`condition_with_evidence`, which also returns :math:`\log p(y)`.
    """
    return condition_with_evidence(prior, H, R, y, offset)[0]

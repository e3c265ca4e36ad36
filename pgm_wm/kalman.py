r"""The Kalman filter and RTS smoother as repeated Gaussian marginalization and conditioning.

Model (Chapter 1, Eq. (ssm)):

.. math::
    z_{t+1} = F z_t + B u_t + \varepsilon_t,\quad \varepsilon_t\sim\mathcal N(0, Q), \qquad
    y_t = H z_t + \delta_t,\quad \delta_t\sim\mathcal N(0, R),

with the prior :math:`z_1 \sim \mathcal N(\mu_1, \Sigma_1)` given by ``init``.

* predict (Eq. kf-predict) = :func:`pgm_wm.gaussian.marginalize_linear` with one cause;
* update (Eq. kf-update) = :func:`pgm_wm.gaussian.condition_with_evidence`;
* a missing observation (``mask`` False) skips the update: the posterior equals the prior and
  the step contributes 0 to the log-likelihood;
* the RTS smoother (Eq. rts) runs backwards over the filtered and predicted beliefs.

Convention: ``init`` is the prior of the *first* state, so step ``t`` first updates with
``y_t`` and then predicts ``z_{t+1}``. (filterpy's ``batch_filter`` predicts first; pass
``kf_predict(x0)`` as ``init`` to match it.) Everything is batched over leading dimensions
and differentiable, so noise parameters can be learned by gradient ascent on
:attr:`KalmanFilterResult.log_likelihood`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import check_last_dims, check_mask, check_spd, check_tensor
from .gaussian import Gaussian, condition_with_evidence, marginalize_linear

__all__ = [
    "kf_predict",
    "kf_update",
    "kalman_filter",
    "rts_smoother",
    "KalmanFilterResult",
]


def kf_predict(
    belief: Gaussian, F: Tensor, Q: Tensor, B: Tensor | None = None, u: Tensor | None = None
) -> Gaussian:
    r"""Kalman predict step, Eq. (kf-predict): :math:`\mathcal N(F\mu + Bu,\; F\Sigma F^\top + Q)`.

    It is the marginalization :math:`p(z_{t+1}) = \int p(z_{t+1}\mid z_t)\,p(z_t)\,dz_t` of
    Eq. (gauss-marginal) with one Gaussian cause and a known additive input ``B u``.

    Shapes: ``F: (..., n, n)``, ``Q: (..., n, n)``, ``B: (..., n, k)``, ``u: (..., k)``.
    """
    n = belief.dim
    check_last_dims("F", F, (n, n))
    check_last_dims("Q", Q, (n, n))
    offset = None
    if (B is None) != (u is None):
        raise ValueError("B: B and u must be given together")
    if B is not None and u is not None:
        check_last_dims("B", B, (n, None))
        check_last_dims("u", u, (B.shape[-1],))
        offset = (B @ u.unsqueeze(-1)).squeeze(-1)
    return marginalize_linear([(F, belief)], noise_cov=Q, offset=offset)


def kf_update(
    belief: Gaussian, y: Tensor, H: Tensor, R: Tensor, mask: Tensor | None = None
) -> tuple[Gaussian, Tensor]:
    r"""Kalman update step, Eq. (kf-update): condition the prior on :math:`y = Hz + \delta`.

    Returns ``(posterior, log p(y | past))``. Where ``mask`` (shape ``(...)``, True = observed)
    is False, the posterior is the prior and the log-likelihood term is 0.
    """
    post, loglik = condition_with_evidence(belief, H, R, y)
    if mask is None:
        return post, loglik
    mask = check_mask("mask", mask, tuple(loglik.shape))
    return post.where(mask, belief), torch.where(mask, loglik, torch.zeros_like(loglik))


@dataclass(frozen=True)
class KalmanFilterResult:
    """Output of :func:`kalman_filter`.

    Attributes:
        filtered: posteriors :math:`p(z_t\\mid y_{1:t})`, mean ``(..., T, n)``, cov ``(..., T, n, n)``.
        predicted: priors :math:`p(z_t\\mid y_{1:t-1})` with the same shapes (``predicted[..., 0]``
            is ``init``), plus the one-step-ahead prior of :math:`z_{T+1}` in ``next_prior``.
        log_likelihoods: :math:`\\log p(y_t\\mid y_{1:t-1})` per step, ``(..., T)``; 0 at missing steps.
    """

    filtered: Gaussian
    predicted: Gaussian
    next_prior: Gaussian
    log_likelihoods: Tensor

    @property
    def log_likelihood(self) -> Tensor:
        """Total log-likelihood :math:`\\log p(y_{1:T})` (Eq. kf-loglik), shape ``(...)``."""
        return self.log_likelihoods.sum(-1)


def kalman_filter(
    y: Tensor,
    init: Gaussian,
    F: Tensor,
    H: Tensor,
    Q: Tensor,
    R: Tensor,
    mask: Tensor | None = None,
    B: Tensor | None = None,
    u: Tensor | None = None,
    validate: bool = True,
) -> KalmanFilterResult:
    r"""Run the Kalman filter over sequences ``y: (..., T, m)``.

    For :math:`t = 1..T`: update with :math:`y_t` (skipped where ``mask[..., t]`` is False), then
    predict :math:`z_{t+1}` using control ``u[..., t, :]`` if given. Parameters are constant in time
    and broadcast over the batch: ``F, Q: (..., n, n)``, ``H: (..., m, n)``, ``R: (..., m, m)``,
    ``B: (..., n, k)``, ``u: (..., T, k)``, ``mask: (..., T)`` bool (True = observed).

    With ``validate`` (default) the covariances are checked once: ``Q`` positive semi-definite,
    ``R`` and ``init.cov`` positive definite; a failure raises ``ValueError`` naming the argument.
    """
    check_tensor("y", y, min_ndim=2)
    n = init.dim
    T, m = y.shape[-2], y.shape[-1]
    check_last_dims("F", F, (n, n))
    check_last_dims("H", H, (m, n))
    check_last_dims("Q", Q, (n, n))
    check_last_dims("R", R, (m, m))
    if validate:
        check_spd("Q", Q, semidefinite=True)
        check_spd("R", R)
        check_spd("init.cov", init.cov)
    if mask is not None:
        mask = check_mask("mask", mask, tuple(y.shape[:-1]))
    if (B is None) != (u is None):
        raise ValueError("B: B and u must be given together")
    if u is not None:
        check_last_dims("u", u, (T, None))

    belief = init
    f_means, f_covs, p_means, p_covs, logliks = [], [], [], [], []
    for t in range(T):
        p_means.append(belief.mean)
        p_covs.append(belief.cov)
        post, ll = kf_update(belief, y[..., t, :], H, R, None if mask is None else mask[..., t])
        f_means.append(post.mean)
        f_covs.append(post.cov)
        logliks.append(ll)
        belief = kf_predict(post, F, Q, B, None if u is None else u[..., t, :])

    def stack(xs: list[Tensor], k: int) -> Tensor:
        shape = torch.broadcast_shapes(*(x.shape for x in xs))
        return torch.stack([x.expand(shape) for x in xs], dim=-1 - k)

    return KalmanFilterResult(
        filtered=Gaussian(stack(f_means, 1), stack(f_covs, 2)),
        predicted=Gaussian(stack(p_means, 1), stack(p_covs, 2)),
        next_prior=belief,
        log_likelihoods=stack(logliks, 0),
    )


def rts_smoother(result: KalmanFilterResult, F: Tensor) -> Gaussian:
    r"""Rauch–Tung–Striebel smoother, Eq. (rts): :math:`p(z_t \mid y_{1:T})` for all ``t``.

    Backwards for :math:`t = T-1, \dots, 1` with :math:`\Sigma^-_{t+1} = F\Sigma_tF^\top + Q`
    taken from ``result.predicted``:

    .. math:: G_t = \Sigma_t F^\top (\Sigma^-_{t+1})^{-1},\quad
              \mu^s_t = \mu_t + G_t(\mu^s_{t+1} - \mu^-_{t+1}),\quad
              \Sigma^s_t = \Sigma_t + G_t(\Sigma^s_{t+1} - \Sigma^-_{t+1})G_t^\top.

    It is Gaussian conditioning of the joint of :math:`(z_t, z_{t+1})` given :math:`y_{1:t}` on the
    smoothed :math:`z_{t+1}`. Returns a Gaussian with mean ``(..., T, n)`` and cov ``(..., T, n, n)``.
    """
    f, p = result.filtered, result.predicted
    n = f.dim
    check_last_dims("F", F, (n, n))
    T = f.mean.shape[-2]
    means = [f.mean[..., T - 1, :]]
    covs = [f.cov[..., T - 1, :, :]]
    Ft = F.transpose(-1, -2)
    for t in range(T - 2, -1, -1):
        P_f = f.cov[..., t, :, :]
        P_p = p.cov[..., t + 1, :, :]
        chol = torch.linalg.cholesky(0.5 * (P_p + P_p.transpose(-1, -2)))
        # G = P_f Fᵀ P_p^{-1}  ->  solve P_p Gᵀ = F P_fᵀ
        G = torch.cholesky_solve((P_f @ Ft).transpose(-1, -2), chol).transpose(-1, -2)
        m_s = f.mean[..., t, :] + (G @ (means[-1] - p.mean[..., t + 1, :]).unsqueeze(-1)).squeeze(-1)
        P_s = P_f + G @ (covs[-1] - P_p) @ G.transpose(-1, -2)
        means.append(m_s)
        covs.append(0.5 * (P_s + P_s.transpose(-1, -2)))
    means.reverse()
    covs.reverse()
    return Gaussian(torch.stack(means, dim=-2), torch.stack(covs, dim=-3))

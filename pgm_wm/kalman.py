r"""The Kalman filter and RTS smoother as repeated Gaussian marginalization and conditioning.

Model (Chapter 1, Eq. (ssm)):

.. math::
    z_{t+1} = F z_t + B u_t + \varepsilon_t,\quad \varepsilon_t\sim\mathcal N(0, Q), \qquad
    y_t = H z_t + \delta_t,\quad \delta_t\sim\mathcal N(0, R),

with the prior :math:`z_1 \sim \mathcal N(\mu_1, \Sigma_1)` given by ``init``.

* predict (Eq. kf-predict) = Eq. (gauss-marginal) with one cause, :func:`pgm_wm.gaussian.marginalize_linear`;
* update (Eq. kf-update) = Eq. (gauss-condition), :func:`pgm_wm.gaussian.condition_with_evidence`;
* a missing observation (``mask`` False) skips the update: the posterior equals the prior and
  the step contributes 0 to the log-likelihood (Eq. kf-loglik);
* the RTS smoother (Eq. rts) runs backwards over the filtered and predicted beliefs.

Convention: ``init`` is the prior of the *first* state, so step ``t`` first updates with
``y_t`` and then predicts ``z_{t+1}``. This is filterpy's ``batch_filter(..., update_first=True)``
with ``x = init.mean``, ``P = init.cov``. Everything is batched over leading dimensions and
differentiable, so noise parameters can be learned by gradient ascent on
:attr:`KalmanFilterResult.log_likelihood`.

Speed: :func:`kalman_filter` validates the whole sequence once and then runs the unchecked
arithmetic of :mod:`pgm_wm.gaussian` (``_update_cov``/``_update_mean`` for Eq. kf-update,
``_predict_cov``/``_predict_mean`` for Eq. kf-predict; :math:`F\Sigma F^\top` and
:math:`H\Sigma H^\top` as one small GEMM each). Because the covariances (the Riccati
recursion) do not depend on the observed values, the filter runs them in a first pass and the
means in a second pass, two or three GEMMs over the whole batch per step. Covariances that are
the same for every sequence (unbatched parameters, and no mask or the same mask for every
sequence) are computed and stored once; without a mask and without gradients, the recursion
stops as soon as the predicted covariance repeats bit for bit (the steady state) and the
remaining steps reuse it, which gives exactly the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import check_last_dims, check_mask, check_same_batch, check_spd, check_tensor
from .gaussian import (
    Gaussian,
    _LOG_2PI,
    _predict_core,
    _predict_cov,
    _predict_mean,
    _sandwich_operator,
    _sym,
    _update_cov,
    _update_mean,
    condition_with_evidence,
)

__all__ = [
    "kf_predict",
    "kf_update",
    "kalman_filter",
    "rts_smoother",
    "KalmanFilterResult",
]


def _control_offset(B: Tensor | None, u: Tensor | None, n: int) -> Tensor | None:
    """Check ``B: (..., n, k)`` and ``u: (..., k)`` and return ``B u`` (or ``None``)."""
    if (B is None) != (u is None):
        raise ValueError("B: B and u must be given together")
    if B is None or u is None:
        return None
    check_last_dims("B", B, (n, None))
    check_last_dims("u", u, (B.shape[-1],))
    return (B @ u.unsqueeze(-1)).squeeze(-1)


def kf_predict(
    belief: Gaussian,
    F: Tensor,
    Q: Tensor,
    B: Tensor | None = None,
    u: Tensor | None = None,
    *,
    validate: bool = True,
) -> Gaussian:
    r"""Kalman predict step, Eq. (kf-predict): :math:`\mathcal N(F\mu + Bu,\; F\Sigma F^\top + Q)`.

    It is the marginalization :math:`p(z_{t+1}) = \int p(z_{t+1}\mid z_t)\,p(z_t)\,dz_t` of
    Eq. (gauss-marginal) with one Gaussian cause and a known additive input ``B u``.

    Shapes: ``F: (..., n, n)``, ``Q: (..., n, n)``, ``B: (..., n, k)``, ``u: (..., k)``.
    With ``validate`` (default) ``Q`` must be symmetric positive semi-definite.
    """
    n = belief.dim
    check_last_dims("F", F, (n, n))
    check_last_dims("Q", Q, (n, n))
    if validate:
        check_spd("Q", Q.detach(), semidefinite=True)
    offset = _control_offset(B, u, n)
    mean, cov = _predict_core(belief.mean, belief.cov, F, Q, offset)
    return Gaussian(mean, cov)


def kf_update(
    belief: Gaussian,
    y: Tensor,
    H: Tensor,
    R: Tensor,
    mask: Tensor | None = None,
    *,
    validate: bool = True,
) -> tuple[Gaussian, Tensor]:
    r"""Kalman update step, Eq. (kf-update): condition the prior on :math:`y = Hz + \delta`.

    .. math:: S = H\Sigma^- H^\top + R,\quad K = \Sigma^- H^\top S^{-1},\quad
              \mu^+ = \mu^- + K(y - H\mu^-),\quad \Sigma^+ = \Sigma^- - KSK^\top.

    Returns ``(posterior, log p(y | past))`` with the log-likelihood term ``(...)``. Where
    ``mask`` (shape ``(...)``, True = observed) is False, the posterior is the prior and the
    log-likelihood term is 0 (the value of ``y`` there is ignored, NaN included).
    With ``validate`` (default) ``R`` must be symmetric positive definite.
    """
    if mask is not None:
        check_tensor("y", y, min_ndim=1)
        batch = torch.broadcast_shapes(y.shape[:-1], belief.batch_shape)
        mask = check_mask("mask", mask, tuple(batch))
        y = torch.where(mask[..., None], y, torch.zeros((), dtype=y.dtype))
    post, loglik = condition_with_evidence(belief, H, R, y, validate=validate)
    if mask is None:
        return post, loglik
    return post.where(mask, belief), torch.where(mask, loglik, torch.zeros_like(loglik))


@dataclass(frozen=True)
class KalmanFilterResult:
    """Output of :func:`kalman_filter`.

    Attributes:
        filtered: posteriors :math:`p(z_t\\mid y_{1:t})`, mean ``(..., T, n)``, cov ``(..., T, n, n)``.
        predicted: priors :math:`p(z_t\\mid y_{1:t-1})` with the same shapes (``predicted`` at
            ``t = 0`` is ``init``).
        next_prior: the one-step-ahead prior :math:`p(z_{T+1}\\mid y_{1:T})`, mean ``(..., n)``.
        log_likelihoods: :math:`\\log p(y_t\\mid y_{1:t-1})` per step, ``(..., T)``; 0 at missing steps.
    """

    filtered: Gaussian
    predicted: Gaussian
    next_prior: Gaussian
    log_likelihoods: Tensor

    @property
    def log_likelihood(self) -> Tensor:
        """Total log-likelihood :math:`\\log p(y_{1:T}) = \\sum_t \\log p(y_t\\mid y_{1:t-1})` (Eq. kf-loglik), shape ``(...)``."""
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

    For :math:`t = 1..T`: update with :math:`y_t` (Eq. kf-update; skipped where ``mask[..., t]``
    is False), then predict :math:`z_{t+1}` (Eq. kf-predict) using control ``u[..., t, :]`` if
    given. The per-step terms :math:`\log p(y_t\mid y_{1:t-1}) = \log\mathcal N(y_t\mid
    H\mu^-_t, S_t)` sum to the log-likelihood, Eq. (kf-loglik).

    Parameters are constant in time and broadcast over the batch: ``F, Q: (..., n, n)``,
    ``H: (..., m, n)``, ``R: (..., m, m)``, ``B: (..., n, k)``, ``u: (..., T, k)``,
    ``mask: (..., T)`` bool or 0/1 with exactly ``y.shape[:-1]`` (True = observed). Values of
    ``y`` at missing steps are ignored (they may be NaN) and do not affect gradients.

    With ``validate`` (default) the inputs are checked once: ``Q`` positive semi-definite,
    ``R`` and ``init.cov`` positive definite, ``y`` finite where observed; a failure raises
    ``ValueError`` naming the argument. Shapes are always checked. If an innovation covariance
    loses positive definiteness during the run (only possible with ``validate=False`` and bad
    inputs), a ``ValueError`` naming ``R`` is raised after the loop.
    """
    check_tensor("y", y, min_ndim=2)
    if not isinstance(init, Gaussian):
        raise ValueError(f"init: expected a Gaussian, got {type(init).__name__}")
    n = init.dim
    T, m = y.shape[-2], y.shape[-1]
    if T < 1:
        raise ValueError(f"y: expected at least one time step, got shape {tuple(y.shape)}")
    check_last_dims("F", F, (n, n))
    check_last_dims("H", H, (m, n))
    check_last_dims("Q", Q, (n, n))
    check_last_dims("R", R, (m, m))
    for name, x in (("F", F), ("H", H), ("Q", Q), ("R", R), ("init.mean", init.mean), ("init.cov", init.cov)):
        if x.dtype != y.dtype:
            raise ValueError(f"{name}: dtype {x.dtype} differs from y's dtype {y.dtype}")
    if mask is not None:
        mask = check_mask("mask", mask, tuple(y.shape[:-1]))
    offsets: Tensor | None = None
    if (B is None) != (u is None):
        raise ValueError("B: B and u must be given together")
    if B is not None and u is not None:
        check_last_dims("B", B, (n, None))
        check_last_dims("u", u, (T, B.shape[-1]))
        offsets = (B.unsqueeze(-3) @ u.unsqueeze(-1)).squeeze(-1)  # (..., T, n)
    names = ["y", "init.mean", "init.cov", "F", "H", "Q", "R"]
    tensors = [y[..., 0, :], init.mean, init.cov, F, H, Q, R]
    if offsets is not None:
        names.append("u")
        tensors.append(offsets[..., 0, :])
    batch = check_same_batch(names, tensors, (1, 1, 2, 2, 2, 2, 2, 1)[: len(names)])
    if validate:
        check_spd("Q", Q.detach(), semidefinite=True)
        check_spd("R", R.detach())
        check_spd("init.cov", init.cov.detach())
        observed = y if mask is None else y[mask]
        if not bool(torch.isfinite(observed).all()):
            raise ValueError("y: contains NaN or infinite values at observed steps")
    if mask is not None:
        # zero the ignored entries so that NaNs there cannot reach values or gradients
        y = torch.where(mask[..., None], y, torch.zeros((), dtype=y.dtype))

    w_steps = None
    if mask is not None:
        flat_mask = mask.reshape(-1, T)
        if bool((flat_mask == flat_mask[:1]).all()):
            # the same steps are missing in every sequence: the covariances stay shared
            w_steps = flat_mask[0].to(y.dtype).unbind(0)
        else:
            w_steps = mask.to(y.dtype).movedim(-1, 0).unbind(0)
    op_F = _sandwich_operator(F)   # F Σ Fᵀ as one small GEMM (None: ordinary matmuls)
    op_H = _sandwich_operator(H)   # H Σ Hᵀ likewise

    # Pass 1, the covariances (the Riccati recursion, Eqs. kf-update and kf-predict for Σ).
    # They do not depend on the observed values, only on the parameters and the mask, so they
    # run first; when neither is batched, one covariance sequence serves the whole batch.
    # Without a mask the recursion is time-invariant: once the predicted covariance repeats
    # bit for bit (the steady state, typically after tens to hundreds of steps) every later
    # step would recompute exactly the same numbers, so they are reused. This is skipped when a
    # gradient is needed, so that autograd sees the full recursion.
    needs_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (init.cov, F, H, Q, R)
    )
    detect_steady = mask is None and not needs_grad
    cov = init.cov
    p_covs, f_covs, chols, gains, infos = [], [], [], [], []
    steady = None
    for t in range(T):
        p_covs.append(cov)
        if steady is None:
            post, chol, Kt, info = _update_cov(cov, H, R, None if w_steps is None else w_steps[t], op_H)
            nxt = _predict_cov(post, F, Q, op_F)
            if detect_steady and torch.equal(nxt, cov):
                steady = (post, chol, Kt, info)
        else:
            post, chol, Kt, info = steady
            nxt = cov
        f_covs.append(post)
        chols.append(chol)
        gains.append(Kt)
        infos.append(info)
        cov = nxt
    if bool((_stack(infos, 0) != 0).any()):
        raise ValueError("R: an innovation covariance H Σ Hᵀ + R was not positive definite")

    # Pass 2, the means: linear in the data. The batch is flattened to N rows and time is put
    # first, so that each step is two or three GEMMs on contiguous (N, ·) matrices.
    N = math.prod(batch)

    def flat(x: Tensor, k: int) -> Tensor:
        """(*b, *event) with k event dims -> (N, *event); unbatched x is returned as is."""
        if x.ndim == k:
            return x
        event = x.shape[x.ndim - k:]
        return x.expand(*batch, *event).reshape(N, *event)

    y_tm = flat(y, 2).transpose(0, 1).contiguous() if y.ndim > 2 else y.unsqueeze(1)   # (T, N, m)
    u_tm = None
    if offsets is not None:
        u_tm = flat(offsets, 2).transpose(0, 1) if offsets.ndim > 2 else offsets.unsqueeze(1)
    Fm, Hm = flat(F, 2), flat(H, 2)
    mean = init.mean.expand(*batch, n).reshape(N, n)
    means, innovations = [], []   # means: prior, posterior, prior, ... (2T + 1 entries)
    for t in range(T):
        means.append(mean)
        Kt = gains[t]
        mean, innov = _update_mean(mean, Hm, y_tm[t], Kt if Kt.ndim == 2 else flat(Kt, 2))
        means.append(mean)
        innovations.append(innov)
        mean = _predict_mean(mean, Fm, None if u_tm is None else u_tm[t])
    means.append(mean)

    # Eq. (kf-loglik): log p(y_t | y_{1:t-1}) = log N(ε_t | 0, S_t) for all steps at once.
    innov_tm = torch.stack(innovations, 0)                 # (T, N, m)
    L = _stack(chols, 2, time_dim=0)                        # (T, *bc, m, m)
    logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)   # (T, *bc)
    if L.ndim == 3:   # one factor per step serves the whole batch: N right-hand sides per solve
        sol = torch.linalg.solve_triangular(L, innov_tm.transpose(-1, -2), upper=False)
        quad = sol.square().sum(-2)                          # (T, N)
        logdet = logdet.unsqueeze(-1)
    else:             # a factor per step and sequence
        Lf = L.expand(T, *batch, m, m).reshape(T, N, m, m)
        quad = _forward_substitution(Lf, innov_tm).square().sum(-1)
        logdet = logdet.expand(T, *batch).reshape(T, N)
    log_likelihoods = (-0.5 * (quad + logdet + m * _LOG_2PI)).T.reshape(*batch, T)
    if mask is not None:
        log_likelihoods = log_likelihoods * mask.to(log_likelihoods.dtype)

    stacked = torch.stack(means, 0).reshape(2 * T + 1, *batch, n).movedim(0, -2)   # (*batch, 2T+1, n)
    return KalmanFilterResult(
        filtered=_stack_gaussian(stacked[..., 1::2, :], f_covs),
        predicted=_stack_gaussian(stacked[..., 0:-1:2, :], p_covs),
        next_prior=Gaussian(stacked[..., -1, :], cov.expand(*batch, n, n)),
        log_likelihoods=log_likelihoods,
    )


def _forward_substitution(L: Tensor, b: Tensor) -> Tensor:
    """``L⁻¹ b`` for lower-triangular ``L: (..., m, m)``, ``b: (..., m)``.

    For small ``m`` this loops over the rows with elementwise operations on the whole batch at
    once (``m²/2`` operations in total), instead of one LAPACK call per matrix, which is much
    faster for the millions of 2×2 factors of a long masked batch.
    """
    m = L.shape[-1]
    if m > 8:
        return torch.linalg.solve_triangular(L, b.unsqueeze(-1), upper=False).squeeze(-1)
    rows: list[Tensor] = []
    for i in range(m):
        acc = b[..., i]
        for j in range(i):
            acc = acc - L[..., i, j] * rows[j]
        rows.append(acc / L[..., i, i])
    return torch.stack(rows, dim=-1)


def _stack(xs: list[Tensor], k: int, time_dim: int | None = None) -> Tensor:
    """Stack per-step tensors (broadcast to a common shape) with ``k`` event dims along a new
    time axis at ``-1 - k`` (or at ``time_dim``)."""
    shape = torch.broadcast_shapes(*(x.shape for x in xs))
    return torch.stack([x.expand(shape) for x in xs], dim=-1 - k if time_dim is None else time_dim)


def _stack_gaussian(mean: Tensor, covs: list[Tensor]) -> Gaussian:
    """Beliefs with mean ``(..., T, n)`` and per-step covariances stacked to ``(..., T, n, n)``.

    Covariances that are shared across the batch (all-observed sequences with unbatched
    parameters) are stored once and returned as a broadcast view, not copied per sequence.
    """
    cov = _stack(covs, 2)
    batch = torch.broadcast_shapes(mean.shape[:-2], cov.shape[:-3])
    n, T = mean.shape[-1], mean.shape[-2]
    return Gaussian(mean.expand(*batch, T, n), cov.expand(*batch, T, n, n))


def rts_smoother(result: KalmanFilterResult, F: Tensor) -> Gaussian:
    r"""Rauch–Tung–Striebel smoother, Eq. (rts): :math:`p(z_t \mid y_{1:T})` for all ``t``.

    Backwards for :math:`t = T-1, \dots, 1` with :math:`\Sigma^-_{t+1} = F\Sigma_tF^\top + Q`
    and :math:`\mu^-_{t+1}` (including any control input) taken from ``result.predicted``:

    .. math:: G_t = \Sigma_t F^\top (\Sigma^-_{t+1})^{-1},\quad
              \mu^s_t = \mu_t + G_t(\mu^s_{t+1} - \mu^-_{t+1}),\quad
              \Sigma^s_t = \Sigma_t + G_t(\Sigma^s_{t+1} - \Sigma^-_{t+1})G_t^\top.

    It is Gaussian conditioning (Eq. gauss-condition) of the joint of :math:`(z_t, z_{t+1})`
    given :math:`y_{1:t}` on :math:`z_{t+1}`, averaged over the smoothed belief of
    :math:`z_{t+1}`. ``F: (..., n, n)`` must be the transition used by the filter.
    Returns a Gaussian with mean ``(..., T, n)`` and cov ``(..., T, n, n)``.
    """
    if not isinstance(result, KalmanFilterResult):
        raise ValueError(f"result: expected a KalmanFilterResult, got {type(result).__name__}")
    f, p = result.filtered, result.predicted
    n = f.dim
    check_last_dims("F", F, (n, n))
    T = f.mean.shape[-2]
    Fs = F.unsqueeze(-3)  # broadcast over time
    # Covariances shared by the batch (broadcast views from kalman_filter) are processed once.
    f_cov, p_cov = _compact(f.cov, 3), _compact(p.cov, 3)
    # All gains at once (they depend only on the filter output): G_t = Σ_t Fᵀ (Σ⁻_{t+1})⁻¹.
    P_f = f_cov[..., :-1, :, :]
    P_p = p_cov[..., 1:, :, :]
    chol, info = torch.linalg.cholesky_ex(_sym(P_p))
    if bool((info != 0).any()):
        raise ValueError("result: a predicted covariance is not positive definite (Q too small?)")
    G = torch.cholesky_solve(Fs @ P_f.transpose(-1, -2), chol).transpose(-1, -2)  # (..., T-1, n, n)
    Gt = G.transpose(-1, -2)
    m_s, c_s = f.mean[..., T - 1, :], f_cov[..., T - 1, :, :]
    means, covs = [m_s], [c_s]
    for t in range(T - 2, -1, -1):
        g = G[..., t, :, :]
        m_s = f.mean[..., t, :] + (g @ (m_s - p.mean[..., t + 1, :]).unsqueeze(-1)).squeeze(-1)
        c_s = _sym(f_cov[..., t, :, :] + g @ (c_s - p_cov[..., t + 1, :, :]) @ Gt[..., t, :, :])
        means.append(m_s)
        covs.append(c_s)
    means.reverse()
    covs.reverse()
    mean = _stack(means, 1)
    return _stack_gaussian(mean, covs)


def _compact(x: Tensor, k: int) -> Tensor:
    """Collapse leading dimensions of ``x`` that are broadcast views (stride 0) to size 1,
    keeping the last ``k`` dimensions; the result broadcasts back to ``x``'s shape."""
    for d in range(x.ndim - k):
        if x.stride(d) == 0 and x.shape[d] > 1:
            x = x.narrow(d, 0, 1)
    return x

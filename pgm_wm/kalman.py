r"""The Kalman filter and RTS smoother as repeated Gaussian marginalization and conditioning.

Model (Chapter 1, Eq. (ssm)):

.. math::
    z_{t+1} = F z_t + B u_t + \varepsilon_t,\quad \varepsilon_t\sim\mathcal N(0, Q), \qquad
    y_t = H z_t + \delta_t,\quad \delta_t\sim\mathcal N(0, R),

with the prior :math:`z_1 \sim \mathcal N(\mu_1, \Sigma_1)` given by ``init``.

* :func:`kf_update` (Eq. kf-update) = Eq. (gauss-condition), with the covariance in the Joseph
  form Eq. (kf-joseph), which stays positive semi-definite;
* :func:`kf_predict` (Eq. kf-predict) = Eq. (gauss-marginal) with one cause;
* :func:`kalman_filter_reference` is the book's loop, "update, then predict", built from these
  two steps only; :func:`kalman_filter` has the same signature and the same numbers (tested)
  with a choice of backends (``backend=``, chosen by the table of :mod:`pgm_wm._backends`):
  ``"reference"``, ``"tensor"``, ``"compiled"`` (below) or ``"parallel"``
  (:mod:`pgm_wm.kalman_parallel`, the associative scan);
* :func:`rts_smoother` (Eq. rts) runs backwards over a :class:`~pgm_wm.filtering.FilterResult`;
  :func:`rts_smoother_reference` is its readable loop.

Convention: ``init`` is the prior of the *first* state, so step ``t`` first updates with
``y_t`` and then predicts ``z_{t+1}`` (filterpy's ``batch_filter(..., update_first=True)``).
A missing observation (``mask`` False) skips the update: the posterior equals the prior and the
step contributes 0 to the log-likelihood (Eq. kf-loglik). Everything is batched over leading
dimensions and differentiable.

The fast backends (:mod:`pgm_wm._backends.kalman_fast`) use that the covariances (the Riccati
recursion), the gains and the smoother gains do not depend on the observed values. When the
parameters are unbatched and every sequence has the same mask (or none), one covariance
sequence serves the whole batch, and only the means are computed per sequence: the linear
recursion :math:`\mu^-_{t+1} = F(I - K_tH)\mu^-_t + FK_ty_t + Bu_t`. With a mask per sequence
every sequence carries its own covariances. On the CPU without a gradient both run as compiled
loops (``"compiled"``, :mod:`pgm_wm._backends.kalman_jit`, numba), filter and smoother;
otherwise (``"tensor"``) as batched tensor operations: the shared recursion once (stopping at
its bitwise steady state when nothing is masked) and the means as one small GEMM per step, or
per-sequence covariances with the small innovation matrices inverted by closed formulas
(``m ≤ 2``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._checks import (
    check_finite,
    check_last_dims,
    check_mask,
    check_same_batch,
    check_same_dtype,
    check_spd,
    check_tensor,
)
from .filtering import FilterResult
from ._linalg import predict_core, symmetrize
from .gaussian import Gaussian, condition_with_evidence
from ._backends import Backend, implementation, select
from ._backends.kalman_fast import compact, filter_fast, rts_compiled, smoothing_precision

__all__ = [
    "kf_predict",
    "kf_update",
    "kalman_filter",
    "kalman_filter_reference",
    "rts_smoother",
    "rts_smoother_reference",
    "stack_gaussians",
    "check_filter_inputs",
    "check_smoother_inputs",
    "smoother_gains",
]

# ---------------------------------------------------------------------------------------------
# The two steps
# ---------------------------------------------------------------------------------------------


def kf_predict(
    prior: Gaussian,
    F: Tensor,
    Q: Tensor,
    B: Tensor | None = None,
    u: Tensor | None = None,
    *,
    validate: bool = True,
) -> Gaussian:
    r"""Kalman predict step, Eq. (kf-predict): :math:`\mathcal N(F\mu + Bu,\; F\Sigma F^\top + Q)`.

    It is the marginalization :math:`p(z_{t+1}) = \int p(z_{t+1}\mid z_t)\,p(z_t)\,dz_t` of
    Eq. (gauss-marginal) with one Gaussian cause (``prior``, the belief about :math:`z_t`) and a
    known additive input ``B u``.

    Shapes: ``F: (..., n, n)``, ``Q: (..., n, n)``, ``B: (..., n, k)``, ``u: (..., k)``.
    With ``validate`` (default) ``Q`` must be symmetric positive semi-definite, ``F``, ``u`` and
    the belief finite, and all tensors of one dtype (float32 or float64).
    """
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior: expected a Gaussian, got {type(prior).__name__}")
    n = prior.dim
    check_last_dims("prior.cov", prior.cov, (n, n))
    check_last_dims("F", F, (n, n))
    check_last_dims("Q", Q, (n, n))
    if (B is None) != (u is None):
        raise ValueError("B: B and u must be given together")
    if B is not None and u is not None:
        check_last_dims("B", B, (n, None))
        check_last_dims("u", u, (B.shape[-1],))
    if validate:
        check_same_dtype(("prior.mean", "prior.cov", "F", "Q", "B", "u"), (prior.mean, prior.cov, F, Q, B, u))
        check_finite("prior.mean", prior.mean.detach())
        check_finite("prior.cov", prior.cov.detach())
        check_finite("F", F.detach())
        check_spd("Q", Q.detach(), semidefinite=True)
        if B is not None and u is not None:
            check_finite("B", B.detach())
            check_finite("u", u.detach())
    offset = None if B is None or u is None else (B @ u.unsqueeze(-1)).squeeze(-1)
    mean, cov = predict_core(prior.mean, prior.cov, F, Q, offset)
    return Gaussian(mean, cov)


def kf_update(
    prior: Gaussian,
    H: Tensor,
    R: Tensor,
    y: Tensor,
    mask: Tensor | None = None,
    *,
    validate: bool = True,
) -> tuple[Gaussian, Tensor]:
    r"""Kalman update step, Eq. (kf-update): condition the prior on :math:`y = Hz + \delta`.

    .. math:: S = H\Sigma^- H^\top + R,\quad K = \Sigma^- H^\top S^{-1},\quad
              \mu^+ = \mu^- + K(y - H\mu^-),\quad
              \Sigma^+ = (I - KH)\Sigma^-(I - KH)^\top + KRK^\top,

    the last in the Joseph form Eq. (kf-joseph) (equal to :math:`\Sigma^- - KSK^\top`, but
    positive semi-definite in floating point). Returns ``(posterior, log p(y | past))`` with
    the log-likelihood term ``(...)`` (Eq. gauss-evidence). Where ``mask`` (shape ``(...)``,
    True = observed) is False, the posterior is the prior and the term is 0 (the value of ``y``
    there is ignored, NaN included). With ``validate`` (default) ``R`` must be symmetric
    positive definite, ``H``, the prior and the observed ``y`` finite, all of one dtype.
    """
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior: expected a Gaussian, got {type(prior).__name__}")
    check_tensor("y", y, min_ndim=1)
    if mask is not None:
        batch = torch.broadcast_shapes(y.shape[:-1], prior.batch_shape)
        mask = check_mask("mask", mask, tuple(batch))
        if validate:
            check_finite("y", y.detach()[mask.expand(y.shape[:-1])])
        y = torch.where(mask[..., None], y, torch.zeros((), dtype=y.dtype))
    post, loglik = condition_with_evidence(prior, H, R, y, validate=validate)
    if mask is None:
        return post, loglik
    return post.where(mask, prior), torch.where(mask, loglik, torch.zeros_like(loglik))


def stack_gaussians(beliefs: list[Gaussian], dim: int = -1) -> Gaussian:
    """Stack beliefs (broadcast to a common batch shape) along a new batch axis ``dim``
    (counted among the batch dimensions; ``-1`` = just before the event axes).

    :meth:`pgm_wm.beliefs.Gaussian.stack` with ``dim`` counted among the batch axes instead of
    in the ``mean`` tensor."""
    return Gaussian.stack(beliefs, dim if dim >= 0 else dim - 1)


# ---------------------------------------------------------------------------------------------
# Input checks shared by every backend
# ---------------------------------------------------------------------------------------------


def check_filter_inputs(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None, B: Tensor | None, u: Tensor | None, validate: bool,
) -> tuple[Tensor, Tensor | None, Tensor | None, torch.Size]:
    """Check shapes (always) and values (with ``validate``). Returns ``(y, mask, offsets,
    batch)``: ``y`` zeroed where masked (so NaN there cannot reach values or gradients),
    ``mask`` as bool, ``offsets = B u`` of shape ``(..., T, n)`` or None, and the batch shape."""
    check_tensor("y", y, min_ndim=2)
    if not isinstance(init, Gaussian):
        raise ValueError(f"init: expected a Gaussian, got {type(init).__name__}")
    n = init.dim
    T, m = y.shape[-2], y.shape[-1]
    if T < 1:
        raise ValueError(f"y: expected at least one time step, got shape {tuple(y.shape)}")
    check_last_dims("init.cov", init.cov, (n, n))
    check_last_dims("F", F, (n, n))
    check_last_dims("H", H, (m, n))
    check_last_dims("Q", Q, (n, n))
    check_last_dims("R", R, (m, m))
    check_same_dtype(("y", "init.mean", "init.cov", "F", "H", "Q", "R", "B", "u"),
                     (y, init.mean, init.cov, F, H, Q, R, B, u))
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
        check_finite("init.mean", init.mean.detach())
        check_spd("init.cov", init.cov.detach())
        check_finite("F", F.detach())
        check_finite("H", H.detach())
        check_spd("Q", Q.detach(), semidefinite=True)
        check_spd("R", R.detach())
        if B is not None and u is not None:
            check_finite("B", B.detach())
            check_finite("u", u.detach())
    if mask is not None:
        y = torch.where(mask[..., None], y, torch.zeros((), dtype=y.dtype))
    # any NaN or inf makes the sum non-finite; a finite sum is the cheap common case (an
    # overflowing sum of finite values falls through to the elementwise check)
    if validate and not bool(torch.isfinite(y.detach().sum())) and not bool(torch.isfinite(y.detach()).all()):
        raise ValueError("y: contains NaN or infinite values at observed steps")
    return y, mask, offsets, batch


def _diagnose(result: FilterResult, F: Tensor, mask: Tensor | None) -> None:
    """After a run from valid inputs: raise a ``ValueError`` naming the real cause if a
    covariance overflowed (an explosive ``F`` over steps without observations) or an innovation
    covariance lost positive definiteness (a dtype too short for the model's variance ratio)."""
    cov = compact(result.next_prior.cov.detach(), 3)
    # a covariance that overflowed stays non-finite, so the last step tells (cheap)
    if not bool(torch.isfinite(cov[..., -1, :, :]).all()):
        finite_t = torch.isfinite(cov).flatten(-2).all(-1)      # (..., T)
        bad = (~finite_t).reshape(-1, finite_t.shape[-1]).any(0)
        t = int(bad.nonzero()[0])
        rho = float(torch.linalg.eigvals(F.detach().to(torch.float64)).abs().max())
        missing = "" if mask is None else (
            f" after {int((~mask.reshape(-1, mask.shape[-1])[:, : t + 1]).sum(-1).max())} steps without observations")
        raise ValueError(
            f"F: the predicted covariance overflowed at step {t}{missing}: the transition is explosive "
            f"(spectral radius {rho:.4g}) and {cov.dtype} cannot hold the growing variance; use a stable "
            "F, float64, or shorter runs without observations")
    ll = result.log_likelihoods
    if ll is not None and not bool(torch.isfinite(ll.detach().sum())):
        raise ValueError(
            f"R: an innovation covariance H Σ Hᵀ + R lost positive definiteness in {ll.dtype}: the ratio of "
            "the prior variance to the observation variance R exceeds what this dtype represents; use "
            "float64 or rescale the model")


# ---------------------------------------------------------------------------------------------
# Filters
# ---------------------------------------------------------------------------------------------


def kalman_filter_reference(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None = None, B: Tensor | None = None, u: Tensor | None = None,
    *, validate: bool = True,
) -> FilterResult[Gaussian]:
    r"""The book's Kalman filter loop: for :math:`t = 1..T`, update with :math:`y_t`
    (Eq. kf-update, :func:`kf_update`), then predict :math:`z_{t+1}` (Eq. kf-predict,
    :func:`kf_predict`). Same signature and result as :func:`kalman_filter`."""
    y, mask, offsets, batch = check_filter_inputs(y, init, F, H, Q, R, mask, B, u, validate)
    eye = torch.eye(init.dim, dtype=y.dtype, device=y.device)
    prior, priors, posteriors, next_priors, logliks = init, [], [], [], []
    for t in range(y.shape[-2]):
        mask_t = None if mask is None else mask[..., t]
        posterior, loglik = kf_update(prior, H, R, y[..., t, :], mask_t, validate=False)
        u_t = None if offsets is None else offsets[..., t, :]          # B u_t, applied with B = I
        next_prior = kf_predict(posterior, F, Q, None if u_t is None else eye, u_t, validate=False)
        priors.append(prior.expand(*batch))
        posteriors.append(posterior.expand(*batch))
        next_priors.append(next_prior.expand(*batch))
        logliks.append(loglik.expand(batch))
        prior = next_prior
    return FilterResult(Gaussian.stack(priors), Gaussian.stack(posteriors), Gaussian.stack(next_priors),
                        torch.stack(logliks, -1))


def kalman_filter(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None = None, B: Tensor | None = None, u: Tensor | None = None,
    *, validate: bool = True, backend: Backend = "auto",
) -> FilterResult[Gaussian]:
    r"""Run the Kalman filter over sequences ``y: (..., T, m)`` (Eqs. kf-update, kf-predict, kf-loglik).

    For :math:`t = 1..T`: update with :math:`y_t` (skipped where ``mask[..., t]`` is False),
    then predict :math:`z_{t+1}` using control ``u[..., t, :]`` if given. Returns a
    :class:`~pgm_wm.filtering.FilterResult`: ``prior[..., t]`` :math:`= p(z_t\mid y_{<t})`,
    ``posterior[..., t]`` :math:`= p(z_t\mid y_{\le t})`, ``next_prior[..., t]``
    :math:`= p(z_{t+1}\mid y_{\le t})` (means ``(..., T, n)``, covariances ``(..., T, n, n)``)
    and ``log_likelihoods[..., t]`` :math:`= \log\mathcal N(y_t\mid H\mu^-_t, S_t)`.

    Parameters are constant in time and broadcast over the batch: ``F, Q: (..., n, n)``,
    ``H: (..., m, n)``, ``R: (..., m, m)``, ``B: (..., n, k)``, ``u: (..., T, k)``,
    ``mask: (..., T)`` bool or 0/1 with exactly ``y.shape[:-1]`` (True = observed). Values of
    ``y`` at missing steps are ignored (they may be NaN) and do not affect gradients.

    With ``validate`` (default) the inputs are checked once: ``Q`` positive semi-definite,
    ``R`` and ``init.cov`` positive definite, ``init.mean``, ``F``, ``H``, ``B``, ``u`` finite,
    ``y`` finite where observed, one dtype (float32 or float64); after the run, an overflowing
    covariance is reported naming ``F`` and a lost positive definiteness naming ``R``.

    ``backend`` (the table of :mod:`pgm_wm._backends`): ``"reference"``
    (:func:`kalman_filter_reference`); ``"tensor"`` (batched tensor operations, differentiable,
    any device; the module docstring); ``"compiled"`` (numba loops, CPU, unbatched ``F, H, Q, R``,
    no gradient; raises ``ValueError`` where it cannot serve the call); ``"parallel"``
    (:func:`pgm_wm.kalman_parallel.parallel_kalman_filter`, :math:`O(\log T)` sequential depth);
    ``"auto"`` (or ``"fast"``): ``"compiled"`` where it can serve the call, ``"tensor"``
    otherwise. All give the same numbers up to rounding (tested in float32 and float64).
    """
    if backend == "reference":
        result = kalman_filter_reference(y, init, F, H, Q, R, mask, B, u, validate=validate)
    elif backend == "parallel":
        result = implementation("kalman_filter", "parallel")(y, init, F, H, Q, R, mask, B, u, validate=validate)
    else:
        y, mask, offsets, batch = check_filter_inputs(y, init, F, H, Q, R, mask, B, u, validate)
        which = select("kalman_filter", y, init.mean, init.cov, F, H, Q, R, offsets, backend=backend,
                       masked=mask is not None, shared_params=all(x.ndim == 2 for x in (F, H, Q, R)))
        result = filter_fast(y, init, F, H, Q, R, mask, offsets, batch, compiled=which == "compiled")
    if validate:
        _diagnose(result, F, mask if mask is None else check_mask("mask", mask, tuple(y.shape[:-1])))
    return result


# ---------------------------------------------------------------------------------------------
# RTS smoother
# ---------------------------------------------------------------------------------------------


def check_smoother_inputs(result: FilterResult, F: Tensor, Q: Tensor) -> tuple[Gaussian, Gaussian]:
    """The smoother's argument checks, shared by every smoother backend: ``(posteriors,
    next priors)`` of a filter run with dense Gaussian beliefs."""
    if not isinstance(result, FilterResult) or not isinstance(result.posterior, Gaussian):
        raise ValueError(f"result: expected a FilterResult of Gaussians, got {type(result).__name__}")
    post, nxt = result.posterior, result.next_prior
    n = post.dim
    check_last_dims("F", F, (n, n))
    check_last_dims("Q", Q, (n, n))
    check_same_dtype(("result.posterior.mean", "F", "Q"), (post.mean, F, Q))
    check_finite("F", F.detach())
    check_spd("Q", Q.detach(), semidefinite=True)
    cov = compact(post.cov.detach(), 3)          # covariances shared by the batch: checked once
    if not bool(torch.isfinite(cov).all()):
        raise ValueError("result: the filtered covariances contain NaN or inf")
    if bool((torch.diagonal(cov, dim1=-2, dim2=-1) < 0).any()):
        raise ValueError("result: a filtered variance is negative; refilter with the Joseph-form update")
    return post, nxt


def smoother_gains(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> tuple[Tensor, Tensor]:
    r"""All smoother gains :math:`G_t = \Sigma^+_t F^\top (\Sigma^-_{t+1})^{-1}` and the
    conditional covariances :math:`L_t = \operatorname{Cov}[z_t\mid z_{t+1}, y_{\le t}] =
    (I - G_tF)\Sigma^+_t(I - G_tF)^\top + G_tQG_t^\top` (Joseph form, positive semi-definite)
    for ``t < T``, at once: ``(G, L)`` each ``(..., T-1, n, n)``."""
    P_f, P_p = post.cov[..., :-1, :, :], nxt.cov[..., :-1, :, :]
    chol, info = torch.linalg.cholesky_ex(symmetrize(P_p))
    if bool((info != 0).any()):
        raise ValueError("result: a predicted covariance is not positive definite (Q too small?)")
    Fs = F.unsqueeze(-3)
    G = torch.cholesky_solve(Fs @ P_f.transpose(-1, -2), chol).transpose(-1, -2)
    A = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device) - G @ Fs
    L = symmetrize(A @ P_f @ A.transpose(-1, -2) + G @ Q.unsqueeze(-3) @ G.transpose(-1, -2))
    return G, L


def rts_smoother_reference(result: FilterResult, F: Tensor, Q: Tensor) -> Gaussian:
    r"""The book's RTS loop, Eq. (rts), backwards for :math:`t = T-1, \dots, 1`:
    :math:`G_t = \Sigma^+_t F^\top(\Sigma^-_{t+1})^{-1}`, :math:`\mu^s_t = \mu^+_t + G_t(\mu^s_{t+1} - \mu^-_{t+1})`,
    :math:`\Sigma^s_t = \Sigma^+_t + G_t(\Sigma^s_{t+1} - \Sigma^-_{t+1})G_t^\top`, the last as
    the sum of positive semi-definite terms :math:`L_t + G_t\Sigma^s_{t+1}G_t^\top` (see
    :func:`smoother_gains`). Same signature and result as :func:`rts_smoother`."""
    post, nxt = check_smoother_inputs(result, F, Q)
    eye = torch.eye(post.dim, dtype=F.dtype, device=F.device)
    T = post.mean.shape[-2]
    smoothed = [post[(slice(None),) * (len(post.batch_shape) - 1) + (T - 1,)]]
    for t in range(T - 2, -1, -1):
        idx = (slice(None),) * (len(post.batch_shape) - 1) + (t,)
        p, q = post[idx], nxt[idx]
        G = torch.linalg.solve(q.cov, F @ p.cov).transpose(-1, -2)         # Σ⁺ Fᵀ (Σ⁻)⁻¹
        A = eye - G @ F
        s = smoothed[-1]
        mean = p.mean + (G @ (s.mean - q.mean).unsqueeze(-1)).squeeze(-1)
        cov = A @ p.cov @ A.transpose(-1, -2) + G @ (Q + s.cov) @ G.transpose(-1, -2)
        smoothed.append(Gaussian(mean, symmetrize(cov)))
    return Gaussian.stack(smoothed[::-1])


def rts_smoother(result: FilterResult, F: Tensor, Q: Tensor, *, backend: Backend = "auto") -> Gaussian:
    r"""Rauch–Tung–Striebel smoother, Eq. (rts): :math:`p(z_t \mid y_{1:T})` for all ``t``.

    It is Gaussian conditioning (Eq. gauss-condition) of the joint of :math:`(z_t, z_{t+1})`
    given :math:`y_{1:t}` on :math:`z_{t+1}`, averaged over the smoothed belief of
    :math:`z_{t+1}`: :math:`\mu^s_t = \mu^+_t + G_t(\mu^s_{t+1} - \mu^-_{t+1})`,
    :math:`\Sigma^s_t = L_t + G_t\Sigma^s_{t+1}G_t^\top` with the gains and conditional
    covariances of :func:`smoother_gains` computed for all steps at once (the backward loop
    is two small products per step). ``F, Q`` must be the transition and its noise used by
    the filter; ``result`` comes from :func:`kalman_filter`. Returns a Gaussian with mean
    ``(..., T, n)`` and cov ``(..., T, n, n)``. Covariances shared by the batch (broadcast
    views, as :func:`kalman_filter` returns them when no sequence has its own mask) are
    smoothed once.

    float32 beliefs are smoothed in float64 and the result rounded to float32 once: the
    backward recursion amplifies rounding errors, and with a process noise far below the
    filtered variances float32 gave negative variances (tested against float64).

    ``backend``: as in :func:`kalman_filter`: ``"reference"`` (:func:`rts_smoother_reference`),
    ``"tensor"`` (above), ``"compiled"`` (numba loop, CPU, unbatched ``F, Q``, no gradient),
    ``"parallel"`` (:func:`pgm_wm.kalman_parallel.parallel_rts_smoother`), ``"auto"``/``"fast"``
    (compiled where it can serve the call, else tensor); tested equal in float32 and float64.
    """
    if backend == "reference":
        return rts_smoother_reference(result, F, Q)
    if backend == "parallel":
        return implementation("rts_smoother", "parallel")(result, F, Q)
    post, nxt = check_smoother_inputs(result, F, Q)
    which = select("rts_smoother", post.mean, post.cov, nxt.mean, nxt.cov, F, Q, backend=backend,
                   shared_params=F.ndim == 2 and Q.ndim == 2)
    dtype = F.dtype
    m_f, P_f, m_n, P_n, F, Q = smoothing_precision(post, nxt, F, Q)     # float32: run in float64
    post, nxt = Gaussian(m_f, P_f), Gaussian(m_n, P_n)
    if which == "compiled":
        sm = rts_compiled(post, nxt, F, Q)
        return sm if sm.mean.dtype == dtype else Gaussian(sm.mean.to(dtype), _cast_cov(sm.cov, dtype))
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    # Covariances shared by the batch (broadcast views from kalman_filter) are processed once.
    shared = Gaussian(post.mean, compact(post.cov, 3)), Gaussian(nxt.mean, compact(nxt.cov, 3))
    G, L = smoother_gains(shared[0], shared[1], F, Q)
    m_f, m_p = post.mean.expand(*batch, T, n), nxt.mean.expand(*batch, T, n)
    Gt = G.transpose(-1, -2)
    m_s, c_s = m_f[..., T - 1, :], shared[0].cov[..., T - 1, :, :]
    means, covs = [m_s], [c_s]
    for t in range(T - 2, -1, -1):
        g = G[..., t, :, :]
        m_s = m_f[..., t, :] + (g @ (m_s - m_p[..., t, :]).unsqueeze(-1)).squeeze(-1)
        c_s = symmetrize(L[..., t, :, :] + g @ c_s @ Gt[..., t, :, :])
        means.append(m_s)
        covs.append(c_s)
    mean = torch.stack(means[::-1], -2)
    cov_shape = torch.broadcast_shapes(*(c.shape for c in covs))
    cov = torch.stack([c.expand(cov_shape) for c in covs[::-1]], -3)
    return Gaussian(mean.to(dtype), _cast_cov(cov, dtype).expand(*batch, T, n, n))


def _cast_cov(cov: Tensor, dtype: torch.dtype) -> Tensor:
    """``cov`` in ``dtype``, broadcast views kept broadcast."""
    return cov if cov.dtype == dtype else compact(cov, 3).to(dtype).expand(cov.shape)

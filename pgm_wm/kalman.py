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
  two steps only; :func:`kalman_filter` selects a backend with the same signature and the same
  numbers (tested): ``"reference"``, ``"fast"`` (below) or ``"parallel"``
  (:mod:`pgm_wm.kalman_parallel`, the associative scan);
* :func:`rts_smoother` (Eq. rts) runs backwards over a :class:`~pgm_wm.filtering.FilterResult`;
  :func:`rts_smoother_reference` is its readable loop.

Convention: ``init`` is the prior of the *first* state, so step ``t`` first updates with
``y_t`` and then predicts ``z_{t+1}`` (filterpy's ``batch_filter(..., update_first=True)``).
A missing observation (``mask`` False) skips the update: the posterior equals the prior and the
step contributes 0 to the log-likelihood (Eq. kf-loglik). Everything is batched over leading
dimensions and differentiable.

The fast backend uses that the covariances (the Riccati recursion) do not depend on the
observed values. When the parameters are unbatched and every sequence has the same mask (or
none), one covariance sequence serves the whole batch, and without a mask and a gradient the
recursion stops once the prior covariance repeats bit for bit (the steady state). The means are
then a linear recursion :math:`\mu^-_{t+1} = F(I - K_tH)\mu^-_t + FK_ty_t + Bu_t`: one small GEMM
per step, the posteriors and log-likelihoods for all steps at once afterwards. With a mask per
sequence the covariances are carried per sequence, with the small innovation matrices inverted
by closed formulas on the whole batch (``m ≤ 2``) and outputs written into preallocated tensors.
"""

from __future__ import annotations

import math
from typing import Literal

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
from .gaussian import (
    _LOG_2PI,
    Gaussian,
    _predict_core,
    _predict_cov,
    _sandwich_operator,
    _sym,
    condition_with_evidence,
)

__all__ = [
    "kf_predict",
    "kf_update",
    "kalman_filter",
    "kalman_filter_reference",
    "rts_smoother",
    "rts_smoother_reference",
    "stack_gaussians",
]

Backend = Literal["auto", "reference", "fast", "parallel"]


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
    mean, cov = _predict_core(prior.mean, prior.cov, F, Q, offset)
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
    (counted among the batch dimensions; ``-1`` = just before the event axes)."""
    if len(beliefs) == 0:
        raise ValueError("beliefs: need at least one belief to stack")
    batch = torch.broadcast_shapes(*(b.batch_shape for b in beliefs))
    n = beliefs[0].dim
    d = dim if dim >= 0 else len(batch) + 1 + dim
    return Gaussian(
        torch.stack([b.mean.expand(*batch, n) for b in beliefs], d),
        torch.stack([b.cov.expand(*batch, n, n) for b in beliefs], d),
    )


# ---------------------------------------------------------------------------------------------
# Input checks shared by every backend
# ---------------------------------------------------------------------------------------------


def _check_filter_inputs(
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
        observed = y.detach() if mask is None else y.detach()[mask]
        if not bool(torch.isfinite(observed).all()):
            raise ValueError("y: contains NaN or infinite values at observed steps")
    if mask is not None:
        y = torch.where(mask[..., None], y, torch.zeros((), dtype=y.dtype))
    return y, mask, offsets, batch


def _diagnose(result: FilterResult, F: Tensor, mask: Tensor | None) -> None:
    """After a run from valid inputs: raise a ``ValueError`` naming the real cause if a
    covariance overflowed (an explosive ``F`` over steps without observations) or an innovation
    covariance lost positive definiteness (a dtype too short for the model's variance ratio)."""
    cov = _compact(result.next_prior.cov.detach(), 3)
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
    y, mask, offsets, batch = _check_filter_inputs(y, init, F, H, Q, R, mask, B, u, validate)
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
    return FilterResult(stack_gaussians(priors), stack_gaussians(posteriors), stack_gaussians(next_priors),
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

    ``backend``: ``"reference"`` (:func:`kalman_filter_reference`), ``"fast"`` (the module
    docstring), ``"parallel"`` (:func:`pgm_wm.kalman_parallel.parallel_kalman_filter`,
    O(log T) sequential depth), ``"auto"`` = ``"fast"``. All give the same numbers up to
    rounding (tested in float32 and float64).
    """
    if backend == "reference":
        result = kalman_filter_reference(y, init, F, H, Q, R, mask, B, u, validate=validate)
    elif backend == "parallel":
        from .kalman_parallel import parallel_kalman_filter

        result = parallel_kalman_filter(y, init, F, H, Q, R, mask, B, u, validate=validate)
    elif backend in ("auto", "fast"):
        y, mask, offsets, batch = _check_filter_inputs(y, init, F, H, Q, R, mask, B, u, validate)
        result = _filter_fast(y, init, F, H, Q, R, mask, offsets, batch)
    else:
        raise ValueError(f"backend: expected 'auto', 'reference', 'fast' or 'parallel', got {backend!r}")
    if validate:
        _diagnose(result, F, mask if mask is None else check_mask("mask", mask, tuple(y.shape[:-1])))
    return result


def _spd_inverse(S: Tensor) -> tuple[Tensor, Tensor]:
    """``(S⁻¹, log det S)`` of small SPD matrices ``(..., m, m)``: closed formulas on the whole
    batch for ``m ≤ 2`` (a handful of elementwise operations instead of one LAPACK call per
    matrix), Cholesky otherwise. Not positive definite → NaN in the log-determinant."""
    m = S.shape[-1]
    if m == 1:
        return S.reciprocal(), torch.log(S[..., 0, 0])
    if m == 2:
        a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        det = a * d - b * b
        logdet = torch.where(a > 0, torch.log(det), torch.full_like(det, float("nan")))
        inv = torch.stack([d, -b, -b, a], -1).reshape(S.shape) / det[..., None, None]
        return inv, logdet
    chol, info = torch.linalg.cholesky_ex(S)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    logdet = torch.where(info == 0, logdet, torch.full_like(logdet, float("nan")))
    return torch.cholesky_inverse(chol), logdet


def _joseph_step(P: Tensor, H: Tensor, R: Tensor, w: Tensor | None, eye: Tensor) -> tuple[Tensor, ...]:
    """One covariance update, Eqs. (kf-update) and (kf-joseph), on a batch of priors ``P``
    (``(..., n, n)``, parameters broadcast). Returns ``(Σ⁺, K, S⁻¹, log det S)``."""
    PHt = P @ H.transpose(-1, -2)                                  # (..., n, m)
    S_inv, logdet = _spd_inverse(H @ PHt + R)
    K = PHt @ S_inv
    if w is not None:
        K = K * w[..., None, None]
    A = eye - K @ H
    return _sym(A @ P @ A.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)), K, S_inv, logdet


def _filter_fast(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None, offsets: Tensor | None, batch: torch.Size,
) -> FilterResult[Gaussian]:
    """The fast backend (module docstring) on validated inputs; see :func:`kalman_filter`."""
    T, m, n = y.shape[-2], y.shape[-1], init.dim
    N = math.prod(batch)
    dt, dev = y.dtype, y.device
    eye = torch.eye(n, dtype=dt, device=dev)
    needs_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (y, init.mean, init.cov, F, H, Q, R) + (() if offsets is None else (offsets,)))

    def flat(x: Tensor, k: int) -> Tensor:
        """(*b, *event) with k event dims -> (N, *event)."""
        event = x.shape[x.ndim - k:]
        return x.expand(*batch, *event).reshape(N, *event)

    y_tm = flat(y, 2).transpose(0, 1)                                          # (T, N, m)
    off_tm = None if offsets is None else flat(offsets, 2).transpose(0, 1)    # (T, N, n)
    flat_mask = None if mask is None else flat(mask, 1)                        # (N, T)
    params_2d = all(x.ndim == 2 for x in (F, H, Q, R, init.cov))
    shared = params_2d and (flat_mask is None or bool((flat_mask == flat_mask[:1]).all()))
    w_all = None if flat_mask is None else flat_mask.to(dt)

    if shared:
        # One covariance sequence for the whole batch (Riccati recursion, Eqs. kf-update/kf-predict).
        w = None if w_all is None else w_all[0]
        op_F = _sandwich_operator(F)
        steady_ok = mask is None and not needs_grad
        P, Ps, Ks, Sinvs, logdets, Pps = init.cov, [], [], [], [], []
        steady = None
        for t in range(T):
            Ps.append(P)
            if steady is None:
                step = _joseph_step(P, H, R, None if w is None else w[t], eye)
                nxt = _predict_cov(step[0], F, Q, op_F)
                if steady_ok and torch.equal(nxt, P):
                    steady = step
            else:
                step, nxt = steady, P
            Pps.append(step[0])
            Ks.append(step[1])
            Sinvs.append(step[2])
            logdets.append(step[3])
            P = nxt
        Ps.append(P)
        P_all, Pp_all = torch.stack(Ps), torch.stack(Pps)                      # (T+1, n, n), (T, n, n)
        K_all, Sinv_all, logdet_all = torch.stack(Ks), torch.stack(Sinvs), torch.stack(logdets)
        # Means: μ⁻_{t+1} = A_t μ⁻_t + c_t with A_t = F(I − K_t H), c_t = F K_t y_t + B u_t.
        FK = F @ K_all                                                          # (T, n, m)
        A_t = (F - FK @ H).transpose(-1, -2)                                    # (T, n, n), transposed
        c = torch.bmm(y_tm, FK.transpose(-1, -2))                               # (T, N, n)
        if off_tm is not None:
            c = c + off_tm
        mean0 = flat(init.mean, 1)
        if needs_grad:
            means = [mean0]
            for t in range(T):
                means.append(torch.addmm(c[t], means[-1], A_t[t]))
            M = torch.stack(means)
        else:
            M = torch.empty(T + 1, N, n, dtype=dt, device=dev)
            M[0] = mean0
            for t in range(T):
                torch.addmm(c[t], M[t], A_t[t], out=M[t + 1])
        innov = y_tm - M[:T] @ H.transpose(-1, -2)                               # (T, N, m)
        M_post = M[:T] + torch.bmm(innov, K_all.transpose(-1, -2))
        S_inv_tm, logdet_tm = Sinv_all.unsqueeze(1), logdet_all.unsqueeze(1)
        cov_prior = P_all[:T].unsqueeze(1)
        cov_post = Pp_all.unsqueeze(1)
        cov_next = P_all[1:].unsqueeze(1)
    else:
        # A covariance per sequence (a mask per sequence or batched parameters), outputs
        # written into preallocated tensors (lists when a gradient is needed).
        if needs_grad:
            lists: dict[str, list[Tensor]] = {k: [] for k in ("P", "Pp", "M", "Mp", "Sinv", "ld", "e")}
            bufs: dict[str, Tensor] = {}
        else:
            # "structure of arrays": the batch is the last, contiguous axis of every slot
            sizes = dict(P=(T + 1, n, n, N), Pp=(T, n, n, N), M=(T + 1, n, N), Mp=(T, n, N),
                         Sinv=(T, m, m, N), ld=(T, N), e=(T, m, N))
            bufs = {k: torch.empty(v, dtype=dt, device=dev) for k, v in sizes.items()}

        def out(name: str, t: int) -> Tensor | None:
            """The slot of step t of an output (None: let the op allocate, for autograd)."""
            return None if needs_grad else bufs[name][t]

        def put(name: str, t: int, x: Tensor, soa: bool = True) -> None:
            """Store x (batch last if soa, else batch first) as slot t of an output."""
            if not soa:
                x = x.movedim(0, -1)
            if needs_grad:
                lists[name].append(x)
            elif x.data_ptr() != bufs[name][t].data_ptr():
                bufs[name][t].copy_(x)

        step = _SequenceStep(F, H, Q, R, n, m, N) if params_2d else None
        P, mean = flat(init.cov, 2), flat(init.mean, 1)
        if step is not None:
            P, mean = P.permute(1, 2, 0).contiguous(), mean.T.contiguous()
            y_soa = y_tm.permute(0, 2, 1).contiguous()                             # (T, m, N)
            u_soa = None if off_tm is None else off_tm.permute(0, 2, 1).contiguous()
        put("P", 0, P, soa=step is not None)
        put("M", 0, mean, soa=step is not None)
        for t in range(T):
            w = None if w_all is None else w_all[:, t]
            if step is not None:
                P, mean = step(P, mean, y_soa[t], w, None if u_soa is None else u_soa[t], t, out)
                for name in ("Pp", "Mp", "Sinv", "ld", "e"):
                    put(name, t, getattr(step, name))
                put("P", t + 1, P)
                put("M", t + 1, mean)
            else:   # batched parameters: plain batched matrix products
                prior = Gaussian(mean, P)
                Pp, K, S_inv, logdet = _joseph_step(P, flat(H, 2) if H.ndim > 2 else H,
                                                    flat(R, 2) if R.ndim > 2 else R, w, eye)
                Fb = flat(F, 2) if F.ndim > 2 else F
                e = y_tm[t] - (prior.mean.unsqueeze(-2) @ (flat(H, 2) if H.ndim > 2 else H).transpose(-1, -2)).squeeze(-2)
                mean_p = mean + (K @ e.unsqueeze(-1)).squeeze(-1)
                P = _sym(Fb @ Pp @ Fb.transpose(-1, -2)) + (flat(Q, 2) if Q.ndim > 2 else Q)
                mean = (Fb @ mean_p.unsqueeze(-1)).squeeze(-1)
                if off_tm is not None:
                    mean = mean + off_tm[t]
                for name, x in (("Pp", Pp), ("Mp", mean_p), ("Sinv", S_inv), ("ld", logdet.expand(N)),
                                ("e", e)):
                    put(name, t, x, soa=False)
                put("P", t + 1, P, soa=False)
                put("M", t + 1, mean, soa=False)
        if needs_grad:
            bufs = {k: torch.stack([x.expand_as(v[-1]) for x in v]) for k, v in lists.items()}
        aos = {k: v.movedim(-1, 1) for k, v in bufs.items()}          # batch back to axis 1 (views)
        M, M_post, innov = aos["M"], aos["Mp"], aos["e"]
        S_inv_tm, logdet_tm = aos["Sinv"], bufs["ld"]
        cov_prior, cov_post, cov_next = aos["P"][:T], aos["Pp"], aos["P"][1:]

    # Eq. (kf-loglik) for all steps at once: log N(e_t | 0, S_t).
    quad = (innov.unsqueeze(-1) * innov.unsqueeze(-2) * S_inv_tm).flatten(-2).sum(-1)   # (T, N)
    ll = -0.5 * (quad + logdet_tm + m * _LOG_2PI)
    if w_all is not None:
        ll = torch.where(w_all.T > 0, ll, torch.zeros((), dtype=dt))
    ll = ll.T.reshape(*batch, T)

    def belief(mean_tm: Tensor, cov_tm: Tensor) -> Gaussian:
        mean = mean_tm.reshape(T, *batch, n).movedim(0, -2)
        cov = cov_tm.expand(T, N, n, n).reshape(T, *batch, n, n).movedim(0, -3) if cov_tm.shape[1] == N \
            else cov_tm.reshape(T, *([1] * len(batch)), n, n).movedim(0, -3).expand(*batch, T, n, n)
        return Gaussian(mean, cov)

    return FilterResult(belief(M[:T], cov_prior), belief(M_post, cov_post), belief(M[1:], cov_next), ll)


class _SequenceStep:
    r"""One step of the per-sequence fast path for unbatched ``F, H, Q, R`` on ``N``
    covariances stored "structure of arrays" (``Σ: (n, n, N)``, ``μ: (n, N)``): every map that
    is linear in :math:`\Sigma` or :math:`K` is one GEMM with a constant matrix, products of two
    per-sequence matrices are broadcast multiply-and-sum over the contiguous batch axis, the
    innovation matrices are inverted by closed formulas (``m ≤ 2``), and results go straight
    into their output slots (``out``). Eqs. (kf-update), (kf-joseph), (kf-predict)."""

    def __init__(self, F: Tensor, H: Tensor, Q: Tensor, R: Tensor, n: int, m: int, N: int) -> None:
        dt, dev = F.dtype, F.device
        eye_n = torch.eye(n, dtype=dt, device=dev)
        # vec(Σ) -> [vec(Σ Hᵀ), vec(H Σ Hᵀ) + vec(R)], vec(K) -> vec(K H), vec(K R)
        to_PHt = torch.einsum("ab,kj->akbj", eye_n, H).reshape(n * m, n * n)        # [i k, i j] = H_kj
        to_S = torch.einsum("ki,lj->klij", H, H).reshape(m * m, n * n)
        self.lin = torch.cat([to_PHt, to_S], 0).contiguous()
        self.lin_bias = torch.cat([torch.zeros(n * m, dtype=dt, device=dev), R.reshape(m * m)])[:, None]
        self.to_KH = torch.einsum("ab,kj->ajbk", eye_n, H).reshape(n * n, n * m)     # [i j, i k] = H_kj
        self.to_KR = torch.einsum("ab,kj->ajbk", eye_n, R).reshape(n * m, n * m)     # [i j, i k] = R_kj
        self.to_FPF = torch.einsum("ki,lj->klij", F, F).reshape(n * n, n * n)
        self.eye_vec = eye_n.reshape(n * n, 1)
        self.Qv = Q.reshape(n * n, 1)
        self.H, self.F = H, F
        self.n, self.m, self.N = n, m, N

    def __call__(self, P: Tensor, mean: Tensor, y_t: Tensor, w: Tensor | None, u_t: Tensor | None, t: int, out):
        n, m, N = self.n, self.m, self.N
        lin = torch.addmm(self.lin_bias, self.lin, P.view(n * n, N))                # (n m + m², N)
        PHt = lin[: n * m].view(n, m, N)
        S = lin[n * m:].view(m, m, N)
        S_inv, logdet = _spd_inverse_soa(S, w)                                       # weight 0: K = 0
        K = _mm(PHt, S_inv)                                                           # (n, m, N)
        A = torch.addmm(self.eye_vec, self.to_KH, K.view(n * m, N), alpha=-1).view(n, n, N)   # I − K H
        KR = (self.to_KR @ K.view(n * m, N)).view(n, m, N)
        # Joseph form (kf-joseph): Σ⁺ = A Σ Aᵀ + K R Kᵀ
        Pp = torch.add(_mm_t(_mm(A, P), A), _mm_t(KR, K), out=out("Pp", t))
        e = torch.addmm(y_t, self.H, mean, alpha=-1, out=out("e", t))                # y − H μ⁻
        Mp = torch.add(mean, (K * e.unsqueeze(0)).sum(1), out=out("Mp", t))
        slot = out("P", t + 1)
        P_next = torch.addmm(self.Qv, self.to_FPF, Pp.view(n * n, N),
                             out=None if slot is None else slot.view(n * n, N)).view(n, n, N)
        mean_next = torch.addmm(u_t, self.F, Mp, out=out("M", t + 1)) if u_t is not None \
            else torch.mm(self.F, Mp, out=out("M", t + 1))
        self.Pp, self.Mp, self.Sinv, self.ld, self.e = Pp, Mp, S_inv, logdet, e
        return P_next, mean_next


def _mm(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` for batch-last matrices ``A: (i, k, N)``, ``B: (k, j, N)`` -> ``(i, j, N)``."""
    return (A.unsqueeze(2) * B.unsqueeze(0)).sum(1)


def _mm_t(A: Tensor, B: Tensor) -> Tensor:
    """``A @ Bᵀ`` for batch-last matrices ``A: (i, k, N)``, ``B: (j, k, N)`` -> ``(i, j, N)``."""
    return (A.unsqueeze(1) * B.unsqueeze(0)).sum(2)


def _spd_inverse_soa(S: Tensor, w: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(w · S⁻¹, log det S)`` for batch-last SPD matrices ``S: (m, m, N)``; closed formulas for
    ``m ≤ 2``, Cholesky otherwise (see :func:`_spd_inverse`)."""
    m = S.shape[0]
    if m == 2:
        a, b, d = S[0, 0], S[0, 1], S[1, 1]
        det = torch.addcmul(a * d, b, b, value=-1)
        scale = det.reciprocal() if w is None else w / det
        nb = -b
        inv = torch.stack([d, nb, nb, a]).view(2, 2, -1) * scale
        return inv, torch.log(det)
    inv, logdet = _spd_inverse(S.movedim(-1, 0))
    inv = inv.movedim(0, -1)
    return (inv if w is None else inv * w), logdet


# ---------------------------------------------------------------------------------------------
# RTS smoother
# ---------------------------------------------------------------------------------------------


def _check_smoother_inputs(result: FilterResult, F: Tensor, Q: Tensor) -> tuple[Gaussian, Gaussian]:
    if not isinstance(result, FilterResult) or not isinstance(result.posterior, Gaussian):
        raise ValueError(f"result: expected a FilterResult of Gaussians, got {type(result).__name__}")
    post, nxt = result.posterior, result.next_prior
    n = post.dim
    check_last_dims("F", F, (n, n))
    check_last_dims("Q", Q, (n, n))
    check_same_dtype(("result.posterior.mean", "F", "Q"), (post.mean, F, Q))
    check_finite("F", F.detach())
    check_spd("Q", Q.detach(), semidefinite=True)
    if not bool(torch.isfinite(post.cov.detach()).all()):
        raise ValueError("result: the filtered covariances contain NaN or inf")
    if bool((post.var.detach() < 0).any()):
        raise ValueError("result: a filtered variance is negative; refilter with the Joseph-form update")
    return post, nxt


def _smoother_gains(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> tuple[Tensor, Tensor]:
    r"""All smoother gains :math:`G_t = \Sigma^+_t F^\top (\Sigma^-_{t+1})^{-1}` and the
    conditional covariances :math:`L_t = \operatorname{Cov}[z_t\mid z_{t+1}, y_{\le t}] =
    (I - G_tF)\Sigma^+_t(I - G_tF)^\top + G_tQG_t^\top` (Joseph form, positive semi-definite)
    for ``t < T``, at once: ``(G, L)`` each ``(..., T-1, n, n)``."""
    P_f, P_p = post.cov[..., :-1, :, :], nxt.cov[..., :-1, :, :]
    chol, info = torch.linalg.cholesky_ex(_sym(P_p))
    if bool((info != 0).any()):
        raise ValueError("result: a predicted covariance is not positive definite (Q too small?)")
    Fs = F.unsqueeze(-3)
    G = torch.cholesky_solve(Fs @ P_f.transpose(-1, -2), chol).transpose(-1, -2)
    A = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device) - G @ Fs
    L = _sym(A @ P_f @ A.transpose(-1, -2) + G @ Q.unsqueeze(-3) @ G.transpose(-1, -2))
    return G, L


def rts_smoother_reference(result: FilterResult, F: Tensor, Q: Tensor) -> Gaussian:
    r"""The book's RTS loop, Eq. (rts), backwards for :math:`t = T-1, \dots, 1`:
    :math:`G_t = \Sigma^+_t F^\top(\Sigma^-_{t+1})^{-1}`, :math:`\mu^s_t = \mu^+_t + G_t(\mu^s_{t+1} - \mu^-_{t+1})`,
    :math:`\Sigma^s_t = \Sigma^+_t + G_t(\Sigma^s_{t+1} - \Sigma^-_{t+1})G_t^\top`, the last as
    the sum of positive semi-definite terms :math:`L_t + G_t\Sigma^s_{t+1}G_t^\top` (see
    :func:`_smoother_gains`). Same signature and result as :func:`rts_smoother`."""
    post, nxt = _check_smoother_inputs(result, F, Q)
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
        smoothed.append(Gaussian(mean, _sym(cov)))
    return stack_gaussians(smoothed[::-1])


def rts_smoother(result: FilterResult, F: Tensor, Q: Tensor) -> Gaussian:
    r"""Rauch–Tung–Striebel smoother, Eq. (rts): :math:`p(z_t \mid y_{1:T})` for all ``t``.

    It is Gaussian conditioning (Eq. gauss-condition) of the joint of :math:`(z_t, z_{t+1})`
    given :math:`y_{1:t}` on :math:`z_{t+1}`, averaged over the smoothed belief of
    :math:`z_{t+1}`: :math:`\mu^s_t = \mu^+_t + G_t(\mu^s_{t+1} - \mu^-_{t+1})`,
    :math:`\Sigma^s_t = L_t + G_t\Sigma^s_{t+1}G_t^\top` with the gains and conditional
    covariances of :func:`_smoother_gains` computed for all steps at once (the backward loop
    is two small products per step). ``F, Q`` must be the transition and its noise used by
    the filter; ``result`` comes from :func:`kalman_filter`. Returns a Gaussian with mean
    ``(..., T, n)`` and cov ``(..., T, n, n)``.
    """
    post, nxt = _check_smoother_inputs(result, F, Q)
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    # Covariances shared by the batch (broadcast views from kalman_filter) are processed once.
    shared = Gaussian(post.mean, _compact(post.cov, 3)), Gaussian(nxt.mean, _compact(nxt.cov, 3))
    needs_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (post.mean, post.cov, nxt.mean, nxt.cov, F, Q))
    if shared[0].cov.shape[:-3] == batch and len(batch) > 0 and F.ndim == 2 and Q.ndim == 2 \
            and not needs_grad and T > 1:
        return _rts_per_sequence(post, nxt, F, Q)
    G, L = _smoother_gains(shared[0], shared[1], F, Q)
    m_f, m_p = post.mean.expand(*batch, T, n), nxt.mean.expand(*batch, T, n)
    Gt = G.transpose(-1, -2)
    m_s, c_s = m_f[..., T - 1, :], shared[0].cov[..., T - 1, :, :]
    means, covs = [m_s], [c_s]
    for t in range(T - 2, -1, -1):
        g = G[..., t, :, :]
        m_s = m_f[..., t, :] + (g @ (m_s - m_p[..., t, :]).unsqueeze(-1)).squeeze(-1)
        c_s = _sym(L[..., t, :, :] + g @ c_s @ Gt[..., t, :, :])
        means.append(m_s)
        covs.append(c_s)
    mean = torch.stack(means[::-1], -2)
    cov_shape = torch.broadcast_shapes(*(c.shape for c in covs))
    cov = torch.stack([c.expand(cov_shape) for c in covs[::-1]], -3)
    return Gaussian(mean, cov.expand(*batch, T, n, n))


def _cholesky_soa(A: Tensor) -> Tensor:
    """Lower Cholesky factors of batch-last SPD matrices ``A: (n, n, B)`` by the column
    algorithm, elementwise over the contiguous batch axis (no LAPACK call per matrix)."""
    n = A.shape[0]
    L = torch.zeros_like(A)
    for j in range(n):
        d = (A[j, j] - L[j, :j].square().sum(0)).sqrt()
        L[j, j] = d
        if j + 1 < n:
            L[j + 1:, j] = (A[j + 1:, j] - (L[j + 1:, :j] * L[j, :j].unsqueeze(0)).sum(1)) / d
    return L


def _cholesky_solve_soa(L: Tensor, Bm: Tensor) -> Tensor:
    """``(L Lᵀ)⁻¹ B`` for batch-last ``L: (n, n, B)`` and ``B: (n, r, B)``, by forward and back
    substitution elementwise over the batch axis."""
    n = L.shape[0]
    Z = torch.empty_like(Bm)
    for i in range(n):
        Z[i] = (Bm[i] - (L[i, :i].unsqueeze(1) * Z[:i]).sum(0)) / L[i, i]
    X = torch.empty_like(Bm)
    for i in range(n - 1, -1, -1):
        X[i] = (Z[i] - (L[i + 1:, i].unsqueeze(1) * X[i + 1:]).sum(0)) / L[i, i]
    return X


def _rts_per_sequence(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> Gaussian:
    """:func:`rts_smoother` for a covariance per sequence and unbatched ``F, Q``, without a
    gradient: batch-last layout, gains and conditional covariances (Joseph form) for blocks of
    steps at once (about 32k matrices per block), then 9 elementwise operations per step backwards."""
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    N = math.prod(batch)
    chunk = max(1, 32768 // N)

    def soa(x: Tensor, k: int) -> Tensor:        # (*batch, T, *event) -> (T, *event, N)
        x = x.expand(*batch, T, *x.shape[x.ndim - k:]).reshape(N, T, *x.shape[x.ndim - k:])
        return x.movedim(0, -1).contiguous()

    m_f, m_p, c_f, c_p = soa(post.mean, 1), soa(nxt.mean, 1), soa(post.cov, 2), soa(nxt.cov, 2)
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    to_GF = torch.einsum("ab,kj->ajbk", eye, F).reshape(n * n, n * n)     # vec(G) -> vec(G F)
    G = torch.empty(T - 1, n, n, N, dtype=F.dtype, device=F.device)
    Lc = torch.empty_like(G)
    for s in range(0, T - 1, chunk):
        e = min(s + chunk, T - 1)
        k = e - s
        Pf = c_f[s:e].movedim(0, -2).reshape(n, n, k * N)                  # Σ⁺_t
        Pp = c_p[s:e].movedim(0, -2).reshape(n, n, k * N)                  # Σ⁻_{t+1}
        FP = (F @ Pf.reshape(n, n * k * N)).view(n, n, k * N)                 # F Σ⁺
        X = _cholesky_solve_soa(_cholesky_soa(Pp), FP)                     # (Σ⁻)⁻¹ F Σ⁺ = Gᵀ
        Gs = X.transpose(0, 1)
        A = (eye.reshape(n * n, 1) - to_GF @ Gs.reshape(n * n, k * N)).view(n, n, k * N)   # I − G F
        GQ = _mm(Gs, Q.unsqueeze(-1))                                         # G Q
        Ls = _mm_t(_mm(A, Pf), A) + _mm_t(GQ, Gs)
        G[s:e] = Gs.reshape(n, n, k, N).movedim(2, 0)
        Lc[s:e] = Ls.reshape(n, n, k, N).movedim(2, 0)
    M = torch.empty(T, n, N, dtype=F.dtype, device=F.device)
    C = torch.empty(T, n, n, N, dtype=F.dtype, device=F.device)
    M[T - 1], C[T - 1] = m_f[T - 1], c_f[T - 1]
    for t in range(T - 2, -1, -1):
        g = G[t]
        d = M[t + 1] - m_p[t]
        torch.add(m_f[t], (g * d.unsqueeze(0)).sum(1), out=M[t])
        torch.add(Lc[t], _mm_t(_mm(g, C[t + 1]), g), out=C[t])
    mean = M.movedim(-1, 0).reshape(*batch, T, n)
    cov = C.movedim(-1, 0).reshape(*batch, T, n, n)
    return Gaussian(mean, _sym(cov))


def _compact(x: Tensor, k: int) -> Tensor:
    """Collapse leading dimensions of ``x`` that are broadcast views (stride 0) to size 1,
    keeping the last ``k`` dimensions; the result broadcasts back to ``x``'s shape."""
    for d in range(x.ndim - k):
        if x.stride(d) == 0 and x.shape[d] > 1:
            x = x.narrow(d, 0, 1)
    return x

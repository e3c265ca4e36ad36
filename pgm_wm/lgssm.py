r"""The linear-Gaussian state space model of Chapter 1 as one parameter container, and its
maximum-likelihood fit.

:class:`LinearGaussianSSM` holds ``F, H, Q, R, init`` and an optional control matrix ``B``
(Eq. ssm), checks them once, and runs :func:`pgm_wm.kalman.kalman_filter` /
:func:`pgm_wm.kalman.rts_smoother` on data. :func:`fit_mle` maximizes the exact
log-likelihood (Eq. kf-loglik) over positive parameters with L-BFGS, each parameter optimized
as its logarithm (so it stays positive), with the **exact diffuse initialization** of Durbin and
Koopman (2012) as an option: the limit of ``init.cov`` → ∞, in which the first observation
fixes the state (``H`` square and invertible, e.g. the local-level model) and its
improper likelihood term is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_same_dtype, check_spd, check_tensor
from .filtering import FilterResult
from .gaussian import Gaussian
from .kalman import Backend, kalman_filter, kf_predict, rts_smoother

__all__ = ["LinearGaussianSSM", "MLEResult", "fit_mle"]


@dataclass(frozen=True)
class LinearGaussianSSM:
    """Parameters of Eq. (ssm): ``F: (n, n)``, ``H: (m, n)``, ``Q: (n, n)`` (PSD), ``R: (m, m)``
    (PD), ``init`` the prior of the first state, ``B: (n, k)`` optional. Leading batch
    dimensions are allowed and broadcast. Construction checks shapes, one dtype (float32 or
    float64) and finite values; ``validate=False`` skips the value checks (inside an optimizer)."""

    F: Tensor
    H: Tensor
    Q: Tensor
    R: Tensor
    init: Gaussian
    B: Tensor | None = None
    validate: bool = field(default=True, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.init, Gaussian):
            raise ValueError(f"init: expected a Gaussian, got {type(self.init).__name__}")
        n = self.init.dim
        check_last_dims("F", self.F, (n, n))
        check_tensor("H", self.H, min_ndim=2)
        check_last_dims("H", self.H, (None, n))
        m = self.H.shape[-2]
        check_last_dims("Q", self.Q, (n, n))
        check_last_dims("R", self.R, (m, m))
        if self.B is not None:
            check_last_dims("B", self.B, (n, None))
        check_same_dtype(("F", "H", "Q", "R", "init.mean", "init.cov", "B"),
                         (self.F, self.H, self.Q, self.R, self.init.mean, self.init.cov, self.B))
        if self.validate:
            check_finite("F", self.F.detach())
            check_finite("H", self.H.detach())
            check_spd("Q", self.Q.detach(), semidefinite=True)
            check_spd("R", self.R.detach())
            check_finite("init.mean", self.init.mean.detach())
            check_spd("init.cov", self.init.cov.detach())

    @property
    def state_dim(self) -> int:
        return self.init.dim

    @property
    def obs_dim(self) -> int:
        return self.H.shape[-2]

    def filter(self, y: Tensor, mask: Tensor | None = None, u: Tensor | None = None, *,
               diffuse: bool = False, backend: Backend = "auto") -> FilterResult[Gaussian]:
        """Eqs. (kf-update, kf-predict, kf-loglik) over ``y: (..., T, m)``; see
        :func:`pgm_wm.kalman.kalman_filter`. ``diffuse``: exact diffuse start, the result
        covers steps ``2..T`` (see :meth:`diffuse_prior`)."""
        if (u is None) != (self.B is None):
            raise ValueError("u: give a control input exactly when the model has B")
        init = self.init
        if diffuse:
            init = self.diffuse_prior(y, mask, u)
            y = y[..., 1:, :]
            mask = None if mask is None else mask[..., 1:]
            u = None if u is None else u[..., 1:, :]
        return kalman_filter(y, init, self.F, self.H, self.Q, self.R, mask, self.B, u,
                             validate=self.validate, backend=backend)

    def smooth(self, y: Tensor, mask: Tensor | None = None, u: Tensor | None = None, *,
               diffuse: bool = False) -> Gaussian:
        """RTS smoothed beliefs, Eq. (rts), of :meth:`filter`'s steps."""
        return rts_smoother(self.filter(y, mask, u, diffuse=diffuse), self.F, self.Q)

    def log_likelihood(self, y: Tensor, mask: Tensor | None = None, u: Tensor | None = None, *,
                       diffuse: bool = False, drop_first: int = 0) -> Tensor:
        """:math:`\\log p(y)` (Eq. kf-loglik), shape ``(...)``; ``drop_first`` leaves out the
        first terms (the vague-prior convention); ``diffuse`` the exact diffuse likelihood."""
        return self.filter(y, mask, u, diffuse=diffuse).log_likelihoods[..., drop_first:].sum(-1)

    def diffuse_prior(self, y: Tensor, mask: Tensor | None = None, u: Tensor | None = None) -> Gaussian:
        r"""The prior of step 2 in the limit ``init.cov → ∞`` (exact diffuse initialization):
        with ``H`` square and invertible the first observation gives the posterior
        :math:`\mathcal N(H^{-1}y_1, H^{-1}RH^{-\top})` whatever the prior was, then one
        predict step (Eq. kf-predict)."""
        n, m = self.state_dim, self.obs_dim
        if n != m:
            raise ValueError(f"H: the exact diffuse start needs a square invertible H, got shape {tuple(self.H.shape)}")
        check_tensor("y", y, min_ndim=2)
        if y.shape[-2] < 2:
            raise ValueError("y: the exact diffuse start needs at least two steps")
        if mask is not None and not bool(mask[..., 0].all()):
            raise ValueError("mask: the exact diffuse start needs the first step observed in every sequence")
        H_inv = torch.linalg.inv(self.H)
        post = Gaussian((H_inv @ y[..., 0, :].unsqueeze(-1)).squeeze(-1), H_inv @ self.R @ H_inv.transpose(-1, -2))
        if u is None:
            return kf_predict(post, self.F, self.Q, validate=False)
        return kf_predict(post, self.F, self.Q, self.B, u[..., 0, :], validate=False)


@dataclass(frozen=True)
class MLEResult:
    """Result of :func:`fit_mle`: the fitted positive parameters, the model built from them,
    the maximized log-likelihood, the largest absolute gradient with respect to the log-parameters
    at the optimum (a stationarity check) and the number of function evaluations."""

    params: dict[str, float]
    model: LinearGaussianSSM
    log_likelihood: float
    max_abs_grad: float
    n_evals: int


def fit_mle(
    build: Callable[[Mapping[str, Tensor]], LinearGaussianSSM],
    y: Tensor,
    init_params: Mapping[str, float],
    mask: Tensor | None = None,
    u: Tensor | None = None,
    *,
    diffuse: bool = False,
    drop_first: int = 0,
    max_iter: int = 200,
    tolerance_grad: float = 1e-10,
    tolerance_change: float = 1e-14,
) -> MLEResult:
    r"""Maximum-likelihood estimate of positive parameters by L-BFGS (strong Wolfe line search)
    on the exact log-likelihood, Eq. (kf-loglik).

    ``build(params)`` maps a dict of positive scalar tensors (same keys as ``init_params``) to a
    :class:`LinearGaussianSSM`; each parameter is optimized as its logarithm. The objective is the
    negative log-likelihood of all sequences divided by the number of observed steps (a scale
    that keeps L-BFGS's tolerances meaningful). ``diffuse``: exact diffuse initialization
    (:meth:`LinearGaussianSSM.diffuse_prior`); ``drop_first``: leave out the first terms (the
    vague-prior convention). ``y: (..., T, m)`` with ``mask``/``u`` as for the filter.
    """
    if not init_params:
        raise ValueError("init_params: need at least one parameter")
    for k, v in init_params.items():
        if not (float(v) > 0 and torch.isfinite(torch.tensor(float(v)))):
            raise ValueError(f"init_params: {k} must be positive and finite, got {v!r}")
    check_tensor("y", y, min_ndim=2)
    names = list(init_params)
    log_p = torch.tensor([float(init_params[k]) for k in names], dtype=y.dtype).log().requires_grad_()
    observed = y.shape[:-1].numel() if mask is None else int(mask.sum())
    scale = 1.0 / max(1, observed)

    def loglik(lp: Tensor) -> Tensor:
        params = {k: lp[i].exp() for i, k in enumerate(names)}
        return build(params).log_likelihood(y, mask, u, diffuse=diffuse, drop_first=drop_first).sum()

    opt = torch.optim.LBFGS([log_p], max_iter=max_iter, line_search_fn="strong_wolfe",
                            tolerance_grad=tolerance_grad, tolerance_change=tolerance_change)
    evals = [0]

    def closure() -> Tensor:
        opt.zero_grad()
        loss = -loglik(log_p) * scale
        loss.backward()
        evals[0] += 1
        return loss

    opt.step(closure)
    lp = log_p.detach().requires_grad_()
    ll = loglik(lp)
    (grad,) = torch.autograd.grad(ll, lp)
    params = {k: float(lp[i].detach().exp()) for i, k in enumerate(names)}
    model = build({k: torch.tensor(v, dtype=y.dtype) for k, v in params.items()})
    return MLEResult(params, model, float(ll), float(grad.abs().max()), evals[0])

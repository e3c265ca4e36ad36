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

The user API of a fitted model: :meth:`LinearGaussianSSM.filter`, :meth:`~LinearGaussianSSM.smooth`,
:meth:`~LinearGaussianSSM.forecast` (observation forecasts with prediction intervals, a
:class:`Forecast`) and :meth:`~LinearGaussianSSM.plot` (data, filtered and smoothed signal and the
forecast in one figure); :meth:`LinearGaussianSSM.local_level` builds the local-level model. The
Nile analysis of Chapter 1 in a dozen lines (the README's script, run verbatim by a test)::

    fit = fit_mle(lambda p: LinearGaussianSSM.local_level(p["var_obs"], p["var_level"]),
                  y, {"var_obs": 1e4, "var_level": 1e3}, diffuse=True)
    forecast = fit.model.forecast(y, steps=10, diffuse=True, level=0.9)
    ax = fit.model.plot(y, x=years, diffuse=True, forecast_steps=10, level=0.9)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any, Callable, Mapping

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_mask, check_same_dtype, check_spd, check_tensor
from .filtering import FilterResult
from .gaussian import Gaussian, marginalize_linear
from .kalman import Backend, kalman_filter, kf_predict, rts_smoother

__all__ = ["LinearGaussianSSM", "Forecast", "MLEResult", "fit_mle"]


def _z_value(level: float) -> float:
    """The two-sided standard-normal quantile of a central interval of probability ``level``."""
    if not (isinstance(level, (int, float)) and 0.0 < float(level) < 1.0):
        raise ValueError(f"level: the interval's probability must lie in (0, 1), got {level!r}")
    return NormalDist().inv_cdf(0.5 + float(level) / 2.0)


@dataclass(frozen=True)
class Forecast:
    r"""Forecasts of the observations :math:`y_{T+1..T+K}` given :math:`y_{1:T}`, Eq. (kf-predict)
    applied :math:`K` times and Eq. (gauss-marginal) for :math:`y = Hz + \varepsilon`:

    .. math:: p(y_{T+k}\mid y_{1:T}) = \mathcal N(H\mu_{T+k},\; H\Sigma_{T+k}H^\top + R).

    Attributes:
        mean: ``(..., K, m)`` forecast means; ``cov``: ``(..., K, m, m)`` their covariances
            (parameter uncertainty not included).
        state: the state beliefs :math:`p(z_{T+k}\mid y_{1:T})`, ``(..., K, n)``.
        level: probability of the central prediction intervals :attr:`lower`..:attr:`upper`
            (per coordinate, :math:`\mu \pm z_{(1+\text{level})/2}\,\sigma`).
    """

    mean: Tensor
    cov: Tensor
    state: Gaussian
    level: float = 0.95

    @property
    def var(self) -> Tensor:
        """Per-coordinate forecast variances ``(..., K, m)``."""
        return self.cov.diagonal(dim1=-2, dim2=-1)

    @property
    def lower(self) -> Tensor:
        """Lower ends of the ``level`` prediction intervals, ``(..., K, m)``."""
        return self.mean - _z_value(self.level) * self.var.sqrt()

    @property
    def upper(self) -> Tensor:
        """Upper ends of the ``level`` prediction intervals, ``(..., K, m)``."""
        return self.mean + _z_value(self.level) * self.var.sqrt()


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

    @classmethod
    def local_level(cls, var_obs: Tensor | float, var_level: Tensor | float, init_mean: float = 0.0,
                    init_var: float = 1e7, *, dtype: torch.dtype = torch.float64,
                    validate: bool = True) -> "LinearGaussianSSM":
        r"""The local-level (random walk plus noise) model of Chapter 1:
        :math:`\ell_{t+1} = \ell_t + \eta_t,\ y_t = \ell_t + \varepsilon_t` with
        :math:`\eta_t\sim\mathcal N(0, \sigma^2_\eta)` (``var_level``),
        :math:`\varepsilon_t\sim\mathcal N(0, \sigma^2_\varepsilon)` (``var_obs``) and the prior
        :math:`\ell_1\sim\mathcal N(` ``init_mean``, ``init_var`` :math:`)` (ignored by ``diffuse=True``).
        Tensor variances keep their gradient and dtype (for :func:`fit_mle`)."""
        for name, v in (("var_obs", var_obs), ("var_level", var_level)):
            if isinstance(v, Tensor):
                if v.numel() != 1:
                    raise ValueError(f"{name}: expected a scalar, got shape {tuple(v.shape)}")
                dtype = v.dtype
            elif not isinstance(v, (int, float)):
                raise ValueError(f"{name}: expected a number or a scalar tensor, got {type(v).__name__}")
        one = torch.eye(1, dtype=dtype)

        def scaled(v: Tensor | float) -> Tensor:
            return (v.reshape(1, 1).to(dtype) if isinstance(v, Tensor) else torch.tensor(float(v), dtype=dtype)) * one

        init = Gaussian(torch.full((1,), float(init_mean), dtype=dtype), float(init_var) * one)
        return cls(one, one, scaled(var_level), scaled(var_obs), init, validate=validate)

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

    def forecast(self, y: Tensor, steps: int, mask: Tensor | None = None, u: Tensor | None = None,
                 u_future: Tensor | None = None, *, diffuse: bool = False, level: float = 0.95) -> Forecast:
        r"""Forecast the next ``steps`` observations after ``y: (..., T, m)`` with prediction
        intervals (:class:`Forecast`): filter the data (:meth:`filter`), then alternate
        Eq. (kf-predict) and the observation marginal :math:`\mathcal N(H\mu, H\Sigma H^\top + R)`.
        No observation beyond ``T`` is needed. With a control matrix ``B``: ``u: (..., T, k)`` as
        for the filter (``u[..., T-1]`` drives step ``T+1``) and ``u_future: (..., steps-1, k)``, the
        inputs between the forecast steps."""
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
            raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
        _z_value(level)
        if self.B is not None and steps > 1:
            if u_future is None:
                raise ValueError(f"u_future: a model with B needs the inputs between the forecast steps, "
                                 f"shape (..., {steps - 1}, k)")
            check_tensor("u_future", u_future, min_ndim=2)
            if u_future.shape[-2] != steps - 1:
                raise ValueError(f"u_future: expected {steps - 1} steps, got shape {tuple(u_future.shape)}")
        elif self.B is None and u_future is not None:
            raise ValueError("u_future: the model has no control matrix B")
        nxt = self.filter(y, mask, u, diffuse=diffuse).next_prior        # (..., T, n): take the last
        state = Gaussian(nxt.mean[..., -1, :], nxt.cov[..., -1, :, :])
        means, covs, s_means, s_covs = [], [], [], []
        for k in range(steps):
            obs = marginalize_linear([(self.H, state)], self.R, validate=False)
            means.append(obs.mean)
            covs.append(obs.cov)
            s_means.append(state.mean)
            s_covs.append(state.cov)
            if k < steps - 1:
                if self.B is None:
                    state = kf_predict(state, self.F, self.Q, validate=False)
                else:
                    state = kf_predict(state, self.F, self.Q, self.B, u_future[..., k, :], validate=False)
        return Forecast(torch.stack(means, -2), torch.stack(covs, -3),
                        Gaussian(torch.stack(s_means, -2), torch.stack(s_covs, -3)), float(level))

    def plot(self, y: Tensor, mask: Tensor | None = None, u: Tensor | None = None, *, x: Any = None,
             diffuse: bool = False, forecast_steps: int = 0, u_future: Tensor | None = None,
             level: float = 0.95, dim: int = 0, ax: Any = None) -> Any:
        r"""One figure of a single sequence ``y: (T, m)``: the observations (coordinate ``dim``), the
        filtered and the RTS-smoothed signal :math:`H z_t` with ``level`` bands, and, with
        ``forecast_steps``, the forecast with its ``level`` prediction interval. ``x: (T,)`` time
        stamps (default ``0..T-1``; the forecast continues with the last spacing). Returns the
        matplotlib axis (a new figure unless ``ax`` is given)."""
        import matplotlib.pyplot as plt
        import numpy as np

        check_tensor("y", y, min_ndim=2)
        if y.ndim != 2:
            raise ValueError(f"y: plot draws one sequence (T, m), got shape {tuple(y.shape)}")
        T, m = y.shape
        if not (isinstance(dim, int) and 0 <= dim < m):
            raise ValueError(f"dim: expected an int in [0, {m - 1}], got {dim!r}")
        if not isinstance(forecast_steps, int) or forecast_steps < 0:
            raise ValueError(f"forecast_steps: expected an int >= 0, got {forecast_steps!r}")
        z = _z_value(level)
        t = np.arange(T, dtype=float) if x is None else np.asarray(x, dtype=float).reshape(-1)
        if t.shape != (T,):
            raise ValueError(f"x: expected {T} time stamps, got shape {t.shape}")
        seen = np.ones(T, bool) if mask is None else check_mask("mask", mask, (T,)).cpu().numpy()
        first = 1 if diffuse else 0                  # the diffuse start has beliefs from step 2 on
        res = self.filter(y, mask, u, diffuse=diffuse)
        smooth = rts_smoother(res, self.F, self.Q)
        if ax is None:
            _, ax = plt.subplots(figsize=(9, 3.5))
        yn = y[:, dim].detach().cpu().numpy()
        ax.plot(t[seen], yn[seen], ".", color="0.35", ms=4, label="observation")
        for name, belief, color in (("filtered", res.posterior, "C0"), ("smoothed", smooth, "C1")):
            signal = marginalize_linear([(self.H, belief)], validate=False)
            mean = signal.mean[:, dim].detach().cpu().numpy()
            sd = signal.cov[:, dim, dim].detach().clamp_min(0).sqrt().cpu().numpy()
            ax.plot(t[first:], mean, color=color, lw=1.5, label=f"{name} signal")
            ax.fill_between(t[first:], mean - z * sd, mean + z * sd, color=color, alpha=0.2, lw=0)
        if forecast_steps:
            fc = self.forecast(y, forecast_steps, mask, u, u_future, diffuse=diffuse, level=level)
            step = t[-1] - t[-2] if T > 1 else 1.0
            tf = t[-1] + step * np.arange(1, forecast_steps + 1)
            fm = fc.mean[:, dim].detach().cpu().numpy()
            ax.plot(tf, fm, color="C3", lw=1.5, label="forecast")
            ax.fill_between(tf, fc.lower[:, dim].detach().cpu().numpy(), fc.upper[:, dim].detach().cpu().numpy(),
                            color="C3", alpha=0.2, lw=0, label=f"{100 * level:g} % prediction interval")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        return ax

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
    vague-prior convention). ``y: (..., T, m)`` with ``mask``/``u`` as for the filter; ``y`` must be
    finite at observed steps (missing values: ``mask`` False). Raises ``ValueError`` (no silent NaN)
    when the optimization ends at non-finite parameters or log-likelihood.
    """
    if not init_params:
        raise ValueError("init_params: need at least one parameter")
    for k, v in init_params.items():
        if not (float(v) > 0 and torch.isfinite(torch.tensor(float(v)))):
            raise ValueError(f"init_params: {k} must be positive and finite, got {v!r}")
    check_tensor("y", y, min_ndim=2)
    if mask is not None:
        mask = check_mask("mask", mask, tuple(y.shape[:-1]))
    observed_y = y if mask is None else y[mask]
    if not bool(torch.isfinite(observed_y.detach()).all()):
        raise ValueError("y: contains NaN or infinite values at observed steps; mark missing values with "
                         "mask (e.g. mask=torch.isfinite(y).all(-1)), their values are then ignored")
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
    ll_value = float(ll.detach())
    bad = [k for k, v in params.items() if not (math.isfinite(v) and v > 0)]
    if bad or not math.isfinite(ll_value):
        raise ValueError(f"init_params: the optimization ended at non-finite values (parameters {params}, "
                         f"log-likelihood {ll_value}); start from other values or check build(params)")
    model = build({k: torch.tensor(v, dtype=y.dtype) for k, v in params.items()})
    return MLEResult(params, model, ll_value, float(grad.detach().abs().max()), evals[0])

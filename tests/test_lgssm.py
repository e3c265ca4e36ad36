"""LinearGaussianSSM and fit_mle (pgm_wm.lgssm). Oracles: filterpy (pgm_wm.testing); the
dense joint Gaussian of a whole local-level sequence (scipy's multivariate normal) for the
log-likelihood and its maximizer (scipy.optimize on the dense likelihood); the closed-form
diffuse prior of the local-level model."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from scipy.stats import multivariate_normal

from pgm_wm.gaussian import Gaussian
from pgm_wm.lgssm import LinearGaussianSSM, fit_mle
from pgm_wm.testing import filterpy_filter, filterpy_rts

D = torch.float64


def local_level(vo, vl, kappa=10.0, mean0=0.0):
    one = torch.eye(1, dtype=D)
    return LinearGaussianSSM(F=one, H=one, Q=vl * one, R=vo * one,
                             init=Gaussian(torch.full((1,), mean0, dtype=D), kappa * one), validate=False)


def simulate_local_level(T: int, vo: float, vl: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    level = 100 + np.cumsum(rng.standard_normal(T) * vl**0.5)
    return level + rng.standard_normal(T) * vo**0.5


def dense_loglik(y: np.ndarray, vo: float, vl: float, kappa: float) -> float:
    T = len(y)
    i = np.arange(T)
    cov = kappa + vl * np.minimum.outer(i, i) + vo * np.eye(T)
    return float(multivariate_normal(np.zeros(T), cov).logpdf(y))


def test_filter_and_smoother_match_filterpy() -> None:
    rng = np.random.default_rng(1)
    F = np.array([[1.0, 0.1], [0.0, 0.95]])
    H = np.array([[1.0, 0.0]])
    Q, R = 0.05 * np.eye(2), np.array([[0.4]])
    model = LinearGaussianSSM(*(torch.tensor(a) for a in (F, H, Q, R)),
                              init=Gaussian(torch.zeros(2, dtype=D), torch.eye(2, dtype=D)))
    zs, valid = rng.standard_normal((30, 1)), rng.random(30) > 0.2
    res = model.filter(torch.tensor(zs), torch.tensor(valid))
    ref = filterpy_filter(zs, valid, F, H, Q, R, np.zeros(2), np.eye(2))
    np.testing.assert_allclose(res.posterior.mean.numpy(), ref.means, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.posterior.cov.numpy(), ref.covs, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.next_prior.mean.numpy(), ref.next_means, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.log_likelihoods.numpy(), ref.log_likelihoods, rtol=1e-10, atol=1e-12)
    xs, Ps = filterpy_rts(ref.means, ref.covs, F, Q)
    sm = model.smooth(torch.tensor(zs), torch.tensor(valid))
    np.testing.assert_allclose(sm.mean.numpy(), xs, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sm.cov.numpy(), Ps, rtol=1e-10, atol=1e-12)


def test_log_likelihood_equals_dense_joint_and_diffuse_limit() -> None:
    y = simulate_local_level(40, 2.0, 0.5)
    yt = torch.tensor(y, dtype=D)[:, None]
    assert abs(float(local_level(2.0, 0.5, kappa=10.0).log_likelihood(yt)) - dense_loglik(y, 2.0, 0.5, 10.0)) < 1e-9
    # exact diffuse = log p(y_2..T | y_1) in the limit kappa -> inf
    kappa = 1e8
    limit = dense_loglik(y - y[0], 2.0, 0.5, kappa) - float(multivariate_normal(0, kappa + 2.0).logpdf(0.0))
    diffuse = float(local_level(2.0, 0.5).log_likelihood(yt, diffuse=True))
    assert abs(diffuse - limit) < 1e-5
    prior2 = local_level(2.0, 0.5).diffuse_prior(yt)          # closed form N(y_1, vo + vl)
    assert float(prior2.mean) == pytest.approx(y[0], rel=1e-14) and float(prior2.cov) == pytest.approx(2.5, rel=1e-14)


def test_fit_mle_equals_maximizer_of_the_dense_likelihood() -> None:
    y = simulate_local_level(60, 3.0, 0.8, seed=2)
    fit = fit_mle(lambda p: local_level(p["var_obs"], p["var_level"], kappa=10.0),
                  torch.tensor(y, dtype=D)[:, None], {"var_obs": 1.0, "var_level": 1.0})
    ref = minimize(lambda lv: -dense_loglik(y - 0.0, *np.exp(lv), 10.0), np.zeros(2), method="Nelder-Mead",
                   options=dict(xatol=1e-9, fatol=1e-12, maxiter=4000))
    np.testing.assert_allclose([fit.params["var_obs"], fit.params["var_level"]], np.exp(ref.x), rtol=1e-4)
    assert fit.max_abs_grad < 1e-5
    assert fit.log_likelihood == pytest.approx(-ref.fun, abs=1e-7)


def test_fit_mle_diffuse_and_mask() -> None:
    """The diffuse fit with a gap equals the fit on the dense diffuse limit of the observed steps."""
    y = simulate_local_level(50, 2.0, 1.0, seed=3)
    mask = np.ones(50, bool)
    mask[20:28] = False
    yt = torch.tensor(y, dtype=D)[:, None]
    fit = fit_mle(lambda p: local_level(p["vo"], p["vl"]), yt, {"vo": 1.0, "vl": 1.0},
                  mask=torch.tensor(mask), diffuse=True)
    kappa = 1e8
    obs = np.flatnonzero(mask)

    def neg(lv):
        vo, vl = np.exp(lv)
        cov = kappa + vl * np.minimum.outer(obs, obs) + vo * np.eye(len(obs))
        full = multivariate_normal(np.zeros(len(obs)), cov).logpdf(y[obs] - y[0])
        return -(full - multivariate_normal(0, kappa + vo).logpdf(0.0))

    ref = minimize(neg, np.zeros(2), method="Nelder-Mead", options=dict(xatol=1e-9, fatol=1e-12, maxiter=4000))
    np.testing.assert_allclose([fit.params["vo"], fit.params["vl"]], np.exp(ref.x), rtol=2e-3)


def test_bad_inputs_name_the_argument() -> None:
    one = torch.eye(1, dtype=D)
    init = Gaussian(torch.zeros(1, dtype=D), one)
    with pytest.raises(ValueError, match="^R"):
        LinearGaussianSSM(one, one, one, -one, init)
    with pytest.raises(ValueError, match="^H"):
        LinearGaussianSSM(one, torch.ones(2, 3, dtype=D), one, one, init)
    with pytest.raises(ValueError, match="^Q"):
        LinearGaussianSSM(one, one, one.float(), one, init)
    with pytest.raises(ValueError, match="^u"):
        LinearGaussianSSM(one, one, one, one, init).filter(torch.zeros(4, 1, dtype=D), u=torch.zeros(4, 1, dtype=D))
    with pytest.raises(ValueError, match="^init_params"):
        fit_mle(lambda p: local_level(p["a"], 1.0), torch.zeros(5, 1, dtype=D), {"a": -1.0})
    with pytest.raises(ValueError, match="^H"):
        LinearGaussianSSM(torch.eye(2, dtype=D), torch.ones(1, 2, dtype=D), torch.eye(2, dtype=D), one,
                          Gaussian(torch.zeros(2, dtype=D), torch.eye(2, dtype=D))).diffuse_prior(torch.zeros(3, 1, dtype=D))

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


# ----------------------------------------------------------------------------- issue 24: the user API
def dense_forecast(y: np.ndarray, F, H, Q, R, m0, P0, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Oracle: the joint Gaussian of (y_1..y_{T+K}) built densely (states by repeated F, noises
    independent), conditioned on y_1..y_T by the Schur complement. Returns the K predictive means
    (K, m) and covariances (K, m, m)."""
    T, m = y.shape
    n = F.shape[0]
    N = T + steps
    # z_t = F^{t} z_1 + sum_{s<t} F^{t-1-s} w_s: covariance of the stacked states
    Fp = [np.linalg.matrix_power(F, k) for k in range(N)]
    Cz = np.zeros((N * n, N * n))
    for t in range(N):
        for u in range(N):
            c = Fp[t] @ P0 @ Fp[u].T
            for s in range(min(t, u)):
                c = c + Fp[t - 1 - s] @ Q @ Fp[u - 1 - s].T
            Cz[t * n:(t + 1) * n, u * n:(u + 1) * n] = c
    Hb = np.kron(np.eye(N), H)
    Cy = Hb @ Cz @ Hb.T + np.kron(np.eye(N), R)
    mu = np.concatenate([H @ Fp[t] @ m0 for t in range(N)])
    o, f = slice(0, T * m), slice(T * m, N * m)
    gain = Cy[f, o] @ np.linalg.inv(Cy[o, o])
    mean = mu[f] + gain @ (y.reshape(-1) - mu[o])
    cov = Cy[f, f] - gain @ Cy[o, f]
    return mean.reshape(steps, m), np.stack([cov[k * m:(k + 1) * m, k * m:(k + 1) * m] for k in range(steps)])


def test_forecast_equals_the_dense_conditional_of_the_joint_gaussian() -> None:
    rng = np.random.default_rng(5)
    F = np.array([[1.0, 0.2], [0.0, 0.9]])
    H = np.array([[1.0, 0.0], [0.5, 1.0]])
    Q, R = np.diag([0.05, 0.1]), np.array([[0.3, 0.05], [0.05, 0.2]])
    m0, P0 = np.array([0.5, -0.2]), np.diag([2.0, 1.0])
    y = rng.standard_normal((25, 2))
    model = LinearGaussianSSM(*(torch.tensor(a) for a in (F, H, Q, R)), init=Gaussian(torch.tensor(m0), torch.tensor(P0)))
    fc = model.forecast(torch.tensor(y), steps=6, level=0.8)
    mean, cov = dense_forecast(y, F, H, Q, R, m0, P0, 6)
    np.testing.assert_allclose(fc.mean.numpy(), mean, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fc.cov.numpy(), cov, rtol=1e-9, atol=1e-10)
    from scipy.stats import norm

    z = norm.ppf(0.9)
    np.testing.assert_allclose(fc.upper.numpy(), mean + z * np.sqrt(np.diagonal(cov, axis1=1, axis2=2)), rtol=1e-9)
    np.testing.assert_allclose(fc.lower.numpy(), mean - z * np.sqrt(np.diagonal(cov, axis1=1, axis2=2)), rtol=1e-9)


def test_forecast_with_controls_equals_filtering_unobserved_future_steps() -> None:
    """Property: a forecast is the filter's prior at steps whose observations are all missing."""
    rng = np.random.default_rng(6)
    F = torch.tensor([[0.9, 0.1], [0.0, 0.8]], dtype=D)
    B = torch.tensor([[0.5], [1.0]], dtype=D)
    H = torch.tensor([[1.0, 0.0]], dtype=D)
    model = LinearGaussianSSM(F, H, 0.1 * torch.eye(2, dtype=D), 0.2 * torch.eye(1, dtype=D),
                              Gaussian(torch.zeros(2, dtype=D), torch.eye(2, dtype=D)), B=B)
    T, K = 20, 5
    y = torch.tensor(rng.standard_normal((3, T + K, 1)))
    u = torch.tensor(rng.standard_normal((3, T + K, 1)))
    mask = torch.ones(3, T + K, dtype=torch.bool)
    mask[:, T:] = False
    res = model.filter(y, mask, u)
    fc = model.forecast(y[:, :T], K, u=u[:, :T], u_future=u[:, T:T + K - 1])
    torch.testing.assert_close(fc.state.mean, res.prior.mean[:, T:], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fc.state.cov, res.prior.cov[:, T:], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fc.mean, res.prior.mean[:, T:, :1], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="^u_future"):
        model.forecast(y[:, :T], K, u=u[:, :T])
    with pytest.raises(ValueError, match="^steps"):
        model.forecast(y[:, :T], 0, u=u[:, :T])
    with pytest.raises(ValueError, match="^level"):
        model.forecast(y[:, :T], 1, u=u[:, :T], level=1.5)


def test_local_level_forecast_has_the_closed_form_variance() -> None:
    """Local level: Var(y_{T+k} | y_1..T) = P_{T+1} + (k-1) var_level + var_obs, mean = the level's."""
    y = torch.tensor(simulate_local_level(40, 2.0, 0.5), dtype=D)[:, None]
    model = LinearGaussianSSM.local_level(2.0, 0.5, init_var=10.0)
    assert torch.equal(model.Q, 0.5 * torch.eye(1, dtype=D)) and torch.equal(model.R, 2.0 * torch.eye(1, dtype=D))
    nxt = model.filter(y).next_prior
    fc = model.forecast(y, steps=4)
    k = torch.arange(4, dtype=D)
    torch.testing.assert_close(fc.var[:, 0], nxt.cov[-1, 0, 0] + k * 0.5 + 2.0)
    torch.testing.assert_close(fc.mean[:, 0], nxt.mean[-1, 0].expand(4))


def test_fit_mle_warns_nothing() -> None:
    import warnings

    y = torch.tensor(simulate_local_level(30, 2.0, 0.5), dtype=D)[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_mle(lambda p: LinearGaussianSSM.local_level(p["vo"], p["vl"], validate=False), y, {"vo": 1.0, "vl": 1.0})


def test_fit_mle_never_returns_nan_parameters_from_nan_data() -> None:
    """The book's own pattern (validate=False inside the optimizer) with a NaN in y: a clear error,
    and with the NaN marked missing the same fit as leaving the step out by the mask."""
    y = torch.tensor(simulate_local_level(40, 2.0, 0.5), dtype=D)[:, None]
    y_nan = y.clone()
    y_nan[7] = float("nan")
    build = lambda p: local_level(p["vo"], p["vl"])  # noqa: E731  (validate=False, as in Chapter 1)
    with pytest.raises(ValueError, match="^y: contains NaN"):
        fit_mle(build, y_nan, {"vo": 1.0, "vl": 1.0})
    mask = torch.isfinite(y_nan).all(-1)
    a = fit_mle(build, y_nan, {"vo": 1.0, "vl": 1.0}, mask=mask)
    b = fit_mle(build, torch.where(mask[:, None], y, torch.zeros_like(y)), {"vo": 1.0, "vl": 1.0}, mask=mask)
    assert all(np.isfinite(v) for v in a.params.values())
    assert a.params == pytest.approx(b.params, rel=1e-10)


def test_fit_mle_reports_a_non_finite_optimum() -> None:
    y = torch.tensor(simulate_local_level(20, 2.0, 0.5), dtype=D)[:, None]

    def broken(p):  # a build whose likelihood is NaN everywhere
        return local_level(p["vo"] * float("nan"), p["vl"])

    with pytest.raises(ValueError, match="non-finite"):
        fit_mle(broken, y, {"vo": 1.0, "vl": 1.0}, max_iter=3)


def test_plot_draws_data_filter_smoother_and_forecast() -> None:
    import matplotlib

    matplotlib.use("Agg")
    y = torch.tensor(simulate_local_level(30, 2.0, 0.5), dtype=D)[:, None]
    model = LinearGaussianSSM.local_level(2.0, 0.5)
    ax = model.plot(y, x=np.arange(1900, 1930), diffuse=True, forecast_steps=5, level=0.9)
    labels = [line.get_label() for line in ax.get_lines()]
    assert labels == ["observation", "filtered signal", "smoothed signal", "forecast"]
    fc_line = ax.get_lines()[-1]
    np.testing.assert_array_equal(fc_line.get_xdata(), np.arange(1930, 1935))
    np.testing.assert_allclose(fc_line.get_ydata(), model.forecast(y, 5, diffuse=True).mean[:, 0].numpy())
    np.testing.assert_allclose(ax.get_lines()[2].get_ydata(), model.smooth(y, diffuse=True).mean[:, 0].numpy())
    with pytest.raises(ValueError, match="^y"):
        model.plot(y[None])
    import matplotlib.pyplot as plt

    plt.close("all")


def _readme_block(marker: str) -> str:
    """The fenced python block of README.md that follows the line containing ``marker``."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = text.index(marker)
    code_start = text.index("```python\n", start) + len("```python\n")
    return text[code_start:text.index("```", code_start)]


def test_readme_nile_script_runs_verbatim(tmp_path) -> None:
    """The README's Nile analysis (define, fit by MLE, smooth, forecast with intervals, plot), run
    exactly as printed, in a fresh interpreter, from another folder."""
    import os
    import subprocess
    import sys

    code = _readme_block("<!-- nile-script -->")
    assert len([line for line in code.splitlines() if line.strip()]) <= 14, code
    script = tmp_path / "nile.py"
    script.write_text(code)
    proc = subprocess.run([sys.executable, "-W", "error::UserWarning", str(script)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    params = eval(proc.stdout.splitlines()[0])  # the printed dict of fitted variances
    assert params["var_obs"] == pytest.approx(15099.0, rel=1e-3)       # Durbin & Koopman (2012)
    assert params["var_level"] == pytest.approx(1469.1, rel=1e-3)
    assert (tmp_path / "nile.png").stat().st_size > 10_000

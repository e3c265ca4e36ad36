"""Tests for pgm_wm.kalman (Chapter 1): filter, log-likelihood, RTS smoother, masks, control.

Oracles: filterpy's KalmanFilter (predict, update, batch_filter with update_first=True and
None for missing observations, rts_smoother, log_likelihood); the dense joint Gaussian of a
whole short sequence built with numpy and conditioned with scipy-free linear algebra
(smoother marginals and the total log-likelihood = log-density of the observed y's);
closed forms (random walk variance grows by Q per missing step; the steady state of a long
run solves the discrete algebraic Riccati equation, scipy.linalg.solve_discrete_are);
torch.autograd.gradcheck; batch = loop.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import block_diag, solve_discrete_are
from scipy.stats import multivariate_normal

from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter, kf_predict, kf_update, rts_smoother

DT = torch.float64
TOL = 1e-8


SETTINGS = settings(max_examples=25, deadline=None)


def t(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=DT)


def close(a, b, tol: float = TOL) -> None:
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else np.asarray(a, dtype=float)
    b = b.detach().numpy() if isinstance(b, torch.Tensor) else np.asarray(b, dtype=float)
    scale = max(1.0, float(np.abs(b).max(initial=0.0)))
    np.testing.assert_allclose(a, b, rtol=tol, atol=tol * scale)


def spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n + 0.1 * np.eye(n))


def random_system(rng: np.random.Generator, n: int, m: int, k: int = 0) -> dict:
    """A random linear-Gaussian SSM with spectral radius of F at most 1.05."""
    F = rng.standard_normal((n, n))
    F *= rng.uniform(0.3, 1.05) / max(1e-9, np.abs(np.linalg.eigvals(F)).max())
    sysm = dict(
        F=F, H=rng.standard_normal((m, n)), Q=spd(rng, n, rng.uniform(0.05, 1.0)),
        R=spd(rng, m, rng.uniform(0.1, 2.0)), x0=rng.standard_normal(n), P0=spd(rng, n, 3.0),
    )
    if k:
        sysm["B"] = rng.standard_normal((n, k))
    return sysm


def filterpy_run(s: dict, zs: np.ndarray, valid: np.ndarray, us: np.ndarray | None = None):
    """filterpy reference: update then predict, None for missing z; per-step log-likelihoods."""
    n, m = s["F"].shape[0], s["H"].shape[0]
    k = 0 if us is None else us.shape[-1]

    def make() -> KalmanFilter:
        kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=k)
        kf.F, kf.H, kf.Q, kf.R = s["F"], s["H"], s["Q"], s["R"]
        kf.x, kf.P = s["x0"].copy(), s["P0"].copy()
        if k:
            kf.B = s["B"]
        return kf

    z_list = [z if v else None for z, v in zip(zs, valid)]
    kf = make()
    out = kf.batch_filter(z_list, update_first=True, us=None if us is None else list(us))
    # log-likelihood per step (batch_filter does not return it): same loop by hand
    kf2, lls = make(), []
    for i, z in enumerate(z_list):
        kf2.update(z)
        lls.append(kf2.log_likelihood if z is not None else 0.0)
        kf2.predict(u=None if us is None else us[i])
    return out, np.array(lls), make()


def ours(s: dict, zs, valid, us=None, mask_nan: bool = False):
    y = t(zs).clone()
    if mask_nan:
        y[~torch.as_tensor(valid)] = float("nan")
    kw = {}
    if us is not None:
        kw = dict(B=t(s["B"]), u=t(us))
    return kalman_filter(
        y, Gaussian(t(s["x0"]), t(s["P0"])), t(s["F"]), t(s["H"]), t(s["Q"]), t(s["R"]),
        mask=torch.as_tensor(valid), **kw,
    )


# ---------------------------------------------------------------- against filterpy


@SETTINGS
@given(
    seed=st.integers(0, 2**31 - 1), n=st.integers(1, 4), m=st.integers(1, 3),
    T=st.integers(1, 25), p_missing=st.sampled_from([0.0, 0.3, 1.0]),
)
def test_filter_smoother_loglik_match_filterpy(seed: int, n: int, m: int, T: int, p_missing: float) -> None:
    rng = np.random.default_rng(seed)
    s = random_system(rng, n, m)
    zs = rng.standard_normal((T, m)) * 2
    valid = rng.random(T) >= p_missing
    (mu, cov, mu_p, cov_p), lls, kf = filterpy_run(s, zs, valid)
    res = ours(s, zs, valid, mask_nan=True)
    close(res.posterior.mean, mu)
    close(res.posterior.cov, cov)
    # filterpy's "predictions" after step i are our priors for step i + 1
    close(res.prior.mean[1:], mu_p[:-1])
    close(res.prior.cov[1:], cov_p[:-1])
    close(res.next_prior.mean[-1], mu_p[-1])
    close(res.next_prior.cov[-1], cov_p[-1])
    close(res.next_prior.mean[:-1], res.prior.mean[1:], tol=0)
    close(res.prior.mean[0], s["x0"], tol=0)
    close(res.log_likelihoods, lls)
    close(res.log_likelihood, lls.sum())
    xs, Ps, _, _ = kf.rts_smoother(mu, cov)
    sm = rts_smoother(res, t(s["F"]), t(s["Q"]))
    close(sm.mean, xs)
    close(sm.cov, Ps)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 4), m=st.integers(1, 3), k=st.integers(1, 2), T=st.integers(1, 20))
def test_control_input_matches_filterpy(seed: int, n: int, m: int, k: int, T: int) -> None:
    rng = np.random.default_rng(seed)
    s = random_system(rng, n, m, k)
    zs, us = rng.standard_normal((T, m)), rng.standard_normal((T, k))
    valid = rng.random(T) >= 0.2
    (mu, cov, mu_p, cov_p), lls, _ = filterpy_run(s, zs, valid, us)
    res = ours(s, zs, valid, us)
    close(res.posterior.mean, mu)
    close(res.posterior.cov, cov)
    close(res.next_prior.mean[-1], mu_p[-1])
    close(res.log_likelihoods, lls)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 4), m=st.integers(1, 3), k=st.integers(0, 2))
def test_single_steps_match_filterpy(seed: int, n: int, m: int, k: int) -> None:
    rng = np.random.default_rng(seed)
    s = random_system(rng, n, m, k)
    kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=k)
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = s["F"], s["H"], s["Q"], s["R"], s["x0"].copy(), s["P0"].copy()
    belief = Gaussian(t(s["x0"]), t(s["P0"]))
    for _ in range(3):
        z = rng.standard_normal(m)
        kf.update(z)
        belief, ll = kf_update(belief, t(s["H"]), t(s["R"]), t(z))
        close(belief.mean, kf.x)
        close(belief.cov, kf.P)
        close(ll, kf.log_likelihood)
        if k:
            u = rng.standard_normal(k)
            kf.B = s["B"]
            kf.predict(u=u)
            belief = kf_predict(belief, t(s["F"]), t(s["Q"]), B=t(s["B"]), u=t(u))
        else:
            kf.predict()
            belief = kf_predict(belief, t(s["F"]), t(s["Q"]))
        close(belief.mean, kf.x)
        close(belief.cov, kf.P)


# ---------------------------------------------------------------- against the dense joint of a whole sequence


def dense_sequence_joint(s: dict, T: int, us: np.ndarray | None):
    """Mean and covariance of [z_1..z_T, y_1..y_T] from the stacked linear map of the
    independent inputs [z_1, ε_1..ε_{T-1}, δ_1..δ_T] (numpy only)."""
    F, H, Q, R = s["F"], s["H"], s["Q"], s["R"]
    n, m = F.shape[0], H.shape[0]
    Z = np.zeros((T * n, T * n))            # z = Z [z_1; ε_1; …; ε_{T-1}] + c
    c = np.zeros(T * n)
    c[:n] = s["x0"]
    Z[:n, :n] = np.eye(n)
    for i in range(1, T):
        Z[i * n:(i + 1) * n] = F @ Z[(i - 1) * n:i * n]
        Z[i * n:(i + 1) * n, i * n:(i + 1) * n] += np.eye(n)
        c[i * n:(i + 1) * n] = F @ c[(i - 1) * n:i * n] + (0 if us is None else s["B"] @ us[i - 1])
    Hb = np.kron(np.eye(T), H)
    M = np.block([[Z, np.zeros((T * n, T * m))], [Hb @ Z, np.eye(T * m)]])
    W = block_diag(s["P0"], *([Q] * (T - 1)), *([R] * T))
    return np.concatenate([c, Hb @ c]), M @ W @ M.T


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 3), m=st.integers(1, 2), T=st.integers(1, 8), k=st.integers(0, 1))
def test_smoother_and_loglik_equal_dense_conditioning(seed: int, n: int, m: int, T: int, k: int) -> None:
    """Smoothed marginals = p(z_t | observed y) from the dense joint; total log-likelihood =
    log N(observed y | dense marginal) — with missing steps and control input."""
    rng = np.random.default_rng(seed)
    s = random_system(rng, n, m, k)
    zs = rng.standard_normal((T, m))
    us = rng.standard_normal((T, k)) if k else None
    valid = rng.random(T) >= 0.3
    mean, cov = dense_sequence_joint(s, T, us)
    obs = np.concatenate([T * n + i * m + np.arange(m) for i in range(T) if valid[i]]).astype(int) if valid.any() else np.zeros(0, int)
    zi = np.arange(T * n)
    if len(obs):
        Syy = cov[np.ix_(obs, obs)]
        G = np.linalg.solve(Syy, cov[np.ix_(obs, zi)]).T
        resid = zs[valid].reshape(-1) - mean[obs]
        post_mean = mean[zi] + G @ resid
        post_cov = cov[np.ix_(zi, zi)] - G @ cov[np.ix_(obs, zi)]
        ref_ll = multivariate_normal(mean[obs], Syy).logpdf(zs[valid].reshape(-1))
    else:
        post_mean, post_cov, ref_ll = mean[zi], cov[np.ix_(zi, zi)], 0.0
    res = ours(s, zs, valid, us)
    sm = rts_smoother(res, t(s["F"]), t(s["Q"]))
    for i in range(T):
        close(sm.mean[i], post_mean[i * n:(i + 1) * n])
        close(sm.cov[i], post_cov[i * n:(i + 1) * n, i * n:(i + 1) * n])
    close(res.log_likelihood, ref_ll)


# ---------------------------------------------------------------- long and all-missing sequences (closed forms)


def test_all_missing_random_walk_variance_grows_by_q_per_step() -> None:
    T, q, p0 = 3_000, 0.37, 2.5
    y = torch.full((2, T, 1), float("nan"), dtype=DT)
    res = kalman_filter(
        y, Gaussian(torch.tensor([1.5], dtype=DT), torch.tensor([[p0]], dtype=DT)),
        torch.eye(1, dtype=DT), torch.eye(1, dtype=DT), torch.tensor([[q]], dtype=DT),
        torch.tensor([[1.0]], dtype=DT), mask=torch.zeros(2, T, dtype=torch.bool),
    )
    steps = torch.arange(T, dtype=DT)
    close(res.posterior.cov[..., 0, 0], (p0 + q * steps).expand(2, T), tol=1e-12)
    close(res.prior.cov[..., 0, 0], (p0 + q * steps).expand(2, T), tol=1e-12)
    close(res.next_prior.cov[..., -1, 0, 0], torch.full((2,), p0 + q * T, dtype=DT), tol=1e-12)
    assert bool((res.posterior.mean == 1.5).all())
    assert bool((res.log_likelihoods == 0).all())
    sm = rts_smoother(res, torch.eye(1, dtype=DT), torch.tensor([[q]], dtype=DT))
    assert bool(torch.isfinite(sm.mean).all()) and bool(torch.isfinite(sm.cov).all())
    # with no data the smoother cannot sharpen anything: the smoothed belief at t is the
    # backward conditioning of a pure random walk, variance p0 + q t exactly
    close(sm.cov[..., 0, 0], (p0 + q * steps).expand(2, T), tol=1e-9)


def constant_velocity(dt: float = 0.1, q: float = 0.5):
    """2-D constant-velocity model (white-noise acceleration), positions observed."""
    F = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    Q = q * np.block([[dt**3 / 3 * np.eye(2), dt**2 / 2 * np.eye(2)], [dt**2 / 2 * np.eye(2), dt * np.eye(2)]])
    return F, np.hstack([np.eye(2), np.zeros((2, 2))]), Q, np.eye(2)


def test_long_sequence_reaches_riccati_steady_state() -> None:
    """10 000 steps of a 4-d constant-velocity model: no NaN/inf anywhere (filter, likelihood,
    smoother), and the predicted covariance converges to the solution of the discrete
    algebraic Riccati equation; the filtered means agree with filterpy at the end."""
    rng = np.random.default_rng(0)
    F, H, Q, R = constant_velocity()
    T = 10_000
    zs = np.cumsum(rng.standard_normal((2, T, 2)), axis=1) * 5     # wandering far from the origin
    res = kalman_filter(t(zs), Gaussian(torch.zeros(4, dtype=DT), 100 * torch.eye(4, dtype=DT)), t(F), t(H), t(Q), t(R))
    sm = rts_smoother(res, t(F), t(Q))
    for x in (res.posterior.mean, res.posterior.cov, res.log_likelihoods, sm.mean, sm.cov):
        assert bool(torch.isfinite(x).all())
    P_inf = solve_discrete_are(F.T, H.T, Q, R)   # steady-state prior covariance
    for b in range(2):
        close(res.next_prior.cov[b, -1], P_inf, tol=1e-9)
    # filterpy over the last 300 steps, started from our prior at that point
    t0 = T - 300
    s = dict(F=F, H=H, Q=Q, R=R, x0=res.prior.mean[1, t0].numpy(), P0=res.prior.cov[1, t0].numpy())
    (mu, cov, _, _), lls, _ = filterpy_run(s, zs[1, t0:], np.ones(300, bool))
    close(res.posterior.mean[1, t0:], mu)
    close(res.posterior.cov[1, t0:], cov)
    close(res.log_likelihoods[1, t0:], lls)


def test_steady_state_reuse_matches_full_recursion() -> None:
    """The filter reuses the covariances once the Riccati recursion is at a bitwise fixed point
    (no mask, no gradient); with a gradient required it recomputes every step. Same numbers."""
    rng = np.random.default_rng(5)
    F, H, Q, R = constant_velocity()
    y = t(rng.standard_normal((4, 250, 2)))
    args = (Gaussian(torch.zeros(4, dtype=DT), 10 * torch.eye(4, dtype=DT)), t(F), t(H), t(Q), t(R))
    fast = kalman_filter(y, *args)
    Qg = t(Q).requires_grad_()
    slow = kalman_filter(y, args[0], args[1], args[2], Qg, args[4])
    close(fast.posterior.cov, slow.posterior.cov.detach(), tol=1e-12)
    close(fast.posterior.mean, slow.posterior.mean.detach(), tol=1e-12)
    close(fast.log_likelihoods, slow.log_likelihoods.detach(), tol=1e-12)


# ---------------------------------------------------------------- batching, masks, gradients


def test_batch_with_batched_parameters_equals_loop() -> None:
    rng = np.random.default_rng(1)
    B, T, n, m = 4, 12, 3, 2
    systems = [random_system(rng, n, m) for _ in range(B)]
    zs = rng.standard_normal((B, T, m))
    valid = rng.random((B, T)) > 0.25
    stack = lambda key: t(np.stack([s[key] for s in systems]))  # noqa: E731
    res = kalman_filter(t(zs), Gaussian(stack("x0"), stack("P0")), stack("F"), stack("H"), stack("Q"), stack("R"),
                        mask=torch.as_tensor(valid))
    sm = rts_smoother(res, stack("F"), stack("Q"))
    for b in range(B):
        rb = ours(systems[b], zs[b], valid[b])
        close(res.posterior.mean[b], rb.posterior.mean, tol=1e-12)
        close(res.posterior.cov[b], rb.posterior.cov, tol=1e-12)
        close(res.log_likelihoods[b], rb.log_likelihoods, tol=1e-12)
        close(sm.mean[b], rts_smoother(rb, t(systems[b]["F"]), t(systems[b]["Q"])).mean, tol=1e-12)


def test_shared_covariance_is_a_broadcast_view_with_full_shape() -> None:
    rng = np.random.default_rng(2)
    s = random_system(rng, 2, 1)
    y = t(rng.standard_normal((5, 7, 1)))
    res = kalman_filter(y, Gaussian(t(s["x0"]), t(s["P0"])), t(s["F"]), t(s["H"]), t(s["Q"]), t(s["R"]))
    assert res.posterior.mean.shape == (5, 7, 2) and res.posterior.cov.shape == (5, 7, 2, 2)
    assert res.log_likelihoods.shape == (5, 7)
    one = ours(s, y[3].numpy(), np.ones(7, bool))
    close(res.posterior.cov[3], one.posterior.cov, tol=1e-13)
    close(res.posterior.mean[3], one.posterior.mean, tol=1e-13)


def test_per_sequence_masks_and_batched_controls_equal_loop() -> None:
    """Shared parameters, a different mask per sequence (covariances become per-sequence), a
    control input batched while y is not, and the same mask for all sequences (shared path)."""
    rng = np.random.default_rng(6)
    s = random_system(rng, 3, 2, k=1)
    zs = rng.standard_normal((5, 11, 2))
    valid = rng.random((5, 11)) > 0.3
    us = rng.standard_normal((5, 11, 1))
    args = (Gaussian(t(s["x0"]), t(s["P0"])), t(s["F"]), t(s["H"]), t(s["Q"]), t(s["R"]))
    res = kalman_filter(t(zs), *args, mask=torch.as_tensor(valid), B=t(s["B"]), u=t(us))
    same = kalman_filter(t(zs), *args, mask=torch.as_tensor(np.broadcast_to(valid[:1], valid.shape).copy()))
    ctl = kalman_filter(t(zs[0]), *args, B=t(s["B"]), u=t(us))          # y unbatched, u batched
    assert ctl.posterior.mean.shape == (5, 11, 3)
    for b in range(5):
        rb = ours(s, zs[b], valid[b], us[b])
        close(res.posterior.mean[b], rb.posterior.mean, tol=1e-12)
        close(res.posterior.cov[b], rb.posterior.cov, tol=1e-12)
        close(res.log_likelihoods[b], rb.log_likelihoods, tol=1e-12)
        r0 = ours(s, zs[b], valid[0])
        close(same.posterior.mean[b], r0.posterior.mean, tol=1e-12)
        close(same.log_likelihoods[b], r0.log_likelihoods, tol=1e-12)
        close(ctl.posterior.mean[b], ours(s, zs[0], np.ones(11, bool), us[b]).posterior.mean, tol=1e-12)


def test_masked_observations_do_not_affect_values_or_gradients() -> None:
    rng = np.random.default_rng(3)
    s = random_system(rng, 2, 2)
    zs, valid = rng.standard_normal((9, 2)), rng.random(9) > 0.4
    valid[0] = False
    log_q = torch.zeros((), dtype=DT, requires_grad=True)

    def loglik(y):
        return kalman_filter(y, Gaussian(t(s["x0"]), t(s["P0"])), t(s["F"]), t(s["H"]),
                             t(s["Q"]) * log_q.exp(), t(s["R"]), mask=torch.as_tensor(valid)).log_likelihood

    y1 = t(zs).clone()
    y2 = y1.clone()
    y2[~torch.as_tensor(valid)] = float("nan")
    l1, l2 = loglik(y1), loglik(y2)
    (g1,) = torch.autograd.grad(l1, log_q)
    (g2,) = torch.autograd.grad(l2, log_q)
    assert float(l1.detach()) == float(l2.detach()) and float(g1) == float(g2) and bool(torch.isfinite(g2))


def test_gradcheck_loglik_wrt_noise_parameters() -> None:
    """d log p(y_{1:T}) / d(log-variances), d/d(init mean), with a missing step, by finite differences."""
    rng = np.random.default_rng(4)
    T = 6
    F, H = t([[1.0, 0.5], [0.0, 0.9]]), t(rng.standard_normal((1, 2)))
    y = t(rng.standard_normal((2, T, 1)))
    mask = torch.ones(2, T, dtype=torch.bool)
    mask[0, 2] = False
    log_q = t([-1.0, -0.5]).requires_grad_()
    log_r = t([0.2]).requires_grad_()
    mu0 = t([0.1, -0.2]).requires_grad_()

    weights = t(rng.standard_normal((2, T, 2)))   # a random linear functional of the smoothed means

    def f(log_q, log_r, mu0):
        res = kalman_filter(y, Gaussian(mu0, torch.eye(2, dtype=DT)), F, H, torch.diag(log_q.exp()),
                            torch.diag(log_r.exp()), mask=mask, validate=False)
        return res.log_likelihood, (rts_smoother(res, F, torch.diag(log_q.exp())).mean * weights).sum()

    assert torch.autograd.gradcheck(f, (log_q, log_r, mu0))


def test_gradient_ascent_learns_noise_variances() -> None:
    """Maximizing the log-likelihood over the log-variances of a simulated local-level model
    recovers the true variances (data: 100 sequences × 40 steps)."""
    g = torch.Generator().manual_seed(0)
    q, r, B, T = 0.5, 2.0, 100, 40
    level = torch.cumsum(torch.randn(B, T, generator=g, dtype=DT) * q**0.5, 1)
    y = (level + torch.randn(B, T, generator=g, dtype=DT) * r**0.5).unsqueeze(-1)
    params = torch.zeros(2, dtype=DT, requires_grad=True)
    one = torch.eye(1, dtype=DT)
    opt = torch.optim.LBFGS([params], max_iter=30, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        res = kalman_filter(y, Gaussian(torch.zeros(1, dtype=DT), 10 * one), one, one,
                            params[0].exp() * one, params[1].exp() * one, validate=False)
        loss = -res.log_likelihood.sum() / (B * T)
        loss.backward()
        return loss

    opt.step(closure)
    q_hat, r_hat = params.detach().exp().tolist()
    assert abs(q_hat - q) < 0.15 * q and abs(r_hat - r) < 0.15 * r


# ---------------------------------------------------------------- bad input -> ValueError naming the argument


def test_bad_inputs_name_the_argument() -> None:
    n, m, T = 2, 1, 5
    y = torch.zeros(3, T, m, dtype=DT)
    init = Gaussian(torch.zeros(n, dtype=DT), torch.eye(n, dtype=DT))
    F, H, Q, R = torch.eye(n, dtype=DT), torch.ones(m, n, dtype=DT), torch.eye(n, dtype=DT), torch.eye(m, dtype=DT)

    def run(**kw):
        args = dict(y=y, init=init, F=F, H=H, Q=Q, R=R)
        args.update(kw)
        return kalman_filter(**args)

    cases = [
        (dict(mask=torch.ones(3, T + 1, dtype=torch.bool)), "mask"),
        (dict(mask=torch.full((3, T), 2.0)), "mask"),
        (dict(Q=torch.diag(torch.tensor([1.0, -0.1], dtype=DT))), "Q"),
        (dict(R=torch.tensor([[-1.0]], dtype=DT)), "R"),
        (dict(R=torch.tensor([[0.0]], dtype=DT)), "R"),
        (dict(init=Gaussian(torch.zeros(n, dtype=DT), torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=DT))), "init.cov"),
        (dict(F=torch.eye(3, dtype=DT)), "F"),
        (dict(H=torch.ones(2, n, dtype=DT)), "H"),
        (dict(Q=torch.eye(3, dtype=DT)), "Q"),
        (dict(y=torch.zeros(3, T, m)), "init.mean"),  # float32 data with float64 parameters
        (dict(y=torch.full((3, T, m), float("nan"), dtype=DT)), "y"),
        (dict(y=torch.zeros(T, dtype=DT)), "y"),
        (dict(u=torch.zeros(3, T, 1, dtype=DT)), "B"),
        (dict(B=torch.ones(n, 1, dtype=DT), u=torch.zeros(3, T + 1, 1, dtype=DT)), "u"),
        (dict(init=torch.zeros(n)), "init"),
        (dict(y=torch.zeros(4, T, m, dtype=DT), init=Gaussian(torch.zeros(3, n, dtype=DT), torch.eye(n, dtype=DT))), "y"),
    ]
    for kw, name in cases:
        with pytest.raises(ValueError, match=f"^{name}"):
            run(**kw)
    with pytest.raises(ValueError, match="^mask"):
        kf_update(init, H, R, torch.zeros(m, dtype=DT), mask=torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="^Q"):
        kf_predict(init, F, -Q)
    with pytest.raises(ValueError, match="^B"):
        kf_predict(init, F, Q, B=torch.ones(n, 1, dtype=DT))
    with pytest.raises(ValueError, match="^F"):
        rts_smoother(run(), torch.eye(3, dtype=DT), Q)
    with pytest.raises(ValueError, match="^result"):
        rts_smoother("not a result", F, Q)  # type: ignore[arg-type]

"""Tests for pgm_wm.gaussian (Chapter 1): the joint, marginal and conditional identities.

Oracles: scipy's multivariate normal log-density; brute-force stacked linear maps of
independent Gaussians (dense closed forms built here with numpy); Monte Carlo sampling;
the precision (information) form of Bayes' rule; Bayes' rule evaluated pointwise
(log p(y) = log p(x) + log p(y|x) - log p(x|y)); order invariance of conditioning.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import block_diag
from scipy.stats import multivariate_normal

from pgm_wm.gaussian import (
    Gaussian,
    condition,
    condition_on_block,
    condition_with_evidence,
    joint_linear_gaussian,
    log_density,
    marginalize_linear,
)

DT = torch.float64


SETTINGS = settings(max_examples=30, deadline=None)


def spd(rng: np.random.Generator, n: int, scale: float = 1.0, jitter: float = 0.1) -> np.ndarray:
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n + jitter * np.eye(n))


def t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=DT)


def close(a: torch.Tensor, b, tol: float = 1e-10) -> None:
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    b = b.detach().numpy() if isinstance(b, torch.Tensor) else np.asarray(b)
    scale = max(1.0, float(np.abs(b).max(initial=0.0)))
    np.testing.assert_allclose(a, b, rtol=tol, atol=tol * scale)


# ---------------------------------------------------------------- log-density (gauss-logpdf)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6), batch=st.integers(1, 4))
def test_log_density_matches_scipy(seed: int, n: int, batch: int) -> None:
    rng = np.random.default_rng(seed)
    covs = np.stack([spd(rng, n) for _ in range(batch)])
    means = rng.standard_normal((batch, n))
    xs = rng.standard_normal((batch, n)) * 2
    ours = log_density(t(xs), t(means), t(covs))
    ref = [multivariate_normal(means[i], covs[i]).logpdf(xs[i]) for i in range(batch)]
    close(ours, ref)
    close(Gaussian(t(means), t(covs)).log_prob(t(xs)), ref)


def test_log_density_broadcasts_shared_covariance() -> None:
    rng = np.random.default_rng(0)
    cov = spd(rng, 3)
    x = rng.standard_normal((5, 7, 3))
    ours = log_density(t(x), torch.zeros(3, dtype=DT), t(cov))
    assert ours.shape == (5, 7)
    close(ours, multivariate_normal(np.zeros(3), cov).logpdf(x.reshape(-1, 3)).reshape(5, 7))


# ---------------------------------------------------------------- joint (gauss-joint)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 5), m=st.integers(1, 4))
def test_joint_equals_stacked_linear_map(seed: int, n: int, m: int) -> None:
    """[x; y] = M [x; δ] + [0; b] with x ⟂ δ: mean M[μ; 0] + [0; b], covariance M blkdiag(Σ, R) Mᵀ."""
    rng = np.random.default_rng(seed)
    mu, S, H, R, b = rng.standard_normal(n), spd(rng, n), rng.standard_normal((m, n)), spd(rng, m), rng.standard_normal(m)
    M = np.block([[np.eye(n), np.zeros((n, m))], [H, np.eye(m)]])
    ref_mean = M @ np.concatenate([mu, np.zeros(m)]) + np.concatenate([np.zeros(n), b])
    ref_cov = M @ block_diag(S, R) @ M.T
    joint = joint_linear_gaussian(Gaussian(t(mu), t(S)), t(H), t(R), offset=t(b))
    close(joint.mean, ref_mean)
    close(joint.cov, ref_cov)


def test_joint_matches_monte_carlo() -> None:
    """Sample x ~ N(μ, Σ), y = Hx + b + δ and compare the empirical moments with Eq. (gauss-joint)."""
    rng = np.random.default_rng(1)
    n, m, N = 3, 2, 400_000
    mu, S, H, R, b = rng.standard_normal(n), spd(rng, n), rng.standard_normal((m, n)), spd(rng, m), rng.standard_normal(m)
    x = rng.multivariate_normal(mu, S, size=N)
    y = x @ H.T + b + rng.multivariate_normal(np.zeros(m), R, size=N)
    xy = np.concatenate([x, y], axis=1)
    joint = joint_linear_gaussian(Gaussian(t(mu), t(S)), t(H), t(R), offset=t(b))
    cov = joint.cov.numpy()
    # standard errors: mean sqrt(C_ii / N), covariance sqrt((C_ii C_jj + C_ij^2) / N)
    se_mean = np.sqrt(np.diag(cov) / N)
    se_cov = np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / N)
    assert np.all(np.abs(xy.mean(0) - joint.mean.numpy()) < 5 * se_mean)
    assert np.all(np.abs(np.cov(xy.T) - cov) < 5 * se_cov)


# ---------------------------------------------------------------- marginal (gauss-marginal)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 4), m=st.integers(1, 4), batch=st.integers(1, 3))
def test_marginalize_several_causes_equals_stacked_joint(seed: int, k: int, m: int, batch: int) -> None:
    """y = Σ A_i u_i + b + ε equals [A_1 … A_k I] [u_1; …; u_k; ε] + b with a block-diagonal covariance."""
    rng = np.random.default_rng(seed)
    dims = rng.integers(1, 5, size=k)
    A = [rng.standard_normal((batch, m, d)) for d in dims]
    mus = [rng.standard_normal((batch, d)) for d in dims]
    Ss = [np.stack([spd(rng, d) for _ in range(batch)]) for d in dims]
    Q, b = np.stack([spd(rng, m) for _ in range(batch)]), rng.standard_normal((batch, m))
    out = marginalize_linear([(t(A[i]), Gaussian(t(mus[i]), t(Ss[i]))) for i in range(k)], t(Q), t(b))
    for j in range(batch):
        big_A = np.concatenate([a[j] for a in A] + [np.eye(m)], axis=1)
        big_mu = np.concatenate([mu[j] for mu in mus] + [np.zeros(m)])
        big_S = block_diag(*[S[j] for S in Ss], Q[j])
        close(out.mean[j], big_A @ big_mu + b[j])
        close(out.cov[j], big_A @ big_S @ big_A.T)


def test_marginalize_matches_monte_carlo() -> None:
    rng = np.random.default_rng(2)
    m, N = 2, 400_000
    A1, A2 = rng.standard_normal((m, 3)), rng.standard_normal((m, 2))
    u1, u2 = Gaussian(t(rng.standard_normal(3)), t(spd(rng, 3))), Gaussian(t(rng.standard_normal(2)), t(spd(rng, 2)))
    Q = spd(rng, m)
    s1 = rng.multivariate_normal(u1.mean.numpy(), u1.cov.numpy(), size=N)
    s2 = rng.multivariate_normal(u2.mean.numpy(), u2.cov.numpy(), size=N)
    y = s1 @ A1.T + s2 @ A2.T + rng.multivariate_normal(np.zeros(m), Q, size=N)
    out = marginalize_linear([(t(A1), u1), (t(A2), u2)], t(Q))
    cov = out.cov.numpy()
    assert np.all(np.abs(y.mean(0) - out.mean.numpy()) < 5 * np.sqrt(np.diag(cov) / N))
    se_cov = np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / N)
    assert np.all(np.abs(np.cov(y.T) - cov) < 5 * se_cov)


def test_marginalize_identity_cause_and_no_noise() -> None:
    rng = np.random.default_rng(3)
    u = Gaussian(t(rng.standard_normal(3)), t(spd(rng, 3)))
    out = marginalize_linear([(None, u)])
    close(out.mean, u.mean)
    close(out.cov, u.cov)


# ---------------------------------------------------------------- conditioning (gauss-condition)


def precision_form(mu, S, H, R, y, b):
    """Bayes' rule in information form: Λ⁺ = Σ⁻¹ + HᵀR⁻¹H, η⁺ = Σ⁻¹μ + HᵀR⁻¹(y − b)."""
    Ri = np.linalg.inv(R)
    lam = np.linalg.inv(S) + H.T @ Ri @ H
    cov = np.linalg.inv(lam)
    return cov @ (np.linalg.solve(S, mu) + H.T @ Ri @ (y - b)), cov


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 5), m=st.integers(1, 4), batch=st.integers(1, 3))
def test_three_routes_to_the_posterior_agree(seed: int, n: int, m: int, batch: int) -> None:
    """condition_with_evidence (Kalman form) = condition_on_block (Schur complement of the joint)
    = precision form, batched."""
    rng = np.random.default_rng(seed)
    mu = rng.standard_normal((batch, n))
    S = np.stack([spd(rng, n) for _ in range(batch)])
    H = rng.standard_normal((batch, m, n))
    R = np.stack([spd(rng, m, scale=0.5) for _ in range(batch)])
    y, b = rng.standard_normal((batch, m)) * 2, rng.standard_normal((batch, m))
    prior = Gaussian(t(mu), t(S))
    post, loglik = condition_with_evidence(prior, t(H), t(R), t(y), offset=t(b))
    via_joint = condition_on_block(joint_linear_gaussian(prior, t(H), t(R), offset=t(b)), n, t(y))
    close(post.mean, via_joint.mean)
    close(post.cov, via_joint.cov)
    for j in range(batch):
        pm, pc = precision_form(mu[j], S[j], H[j], R[j], y[j], b[j])
        close(post.mean[j], pm, tol=1e-8)
        close(post.cov[j], pc, tol=1e-8)
        ref_ll = multivariate_normal(H[j] @ mu[j] + b[j], H[j] @ S[j] @ H[j].T + R[j]).logpdf(y[j])
        close(loglik[j], ref_ll)
    # posterior covariance is exactly symmetric
    assert torch.equal(post.cov, post.cov.transpose(-1, -2))
    close(condition(prior, t(H), t(R), t(y), offset=t(b)).mean, post.mean, tol=0)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 4), m=st.integers(1, 3))
def test_evidence_is_bayes_rule_pointwise(seed: int, n: int, m: int) -> None:
    """log p(y) = log p(x) + log p(y | x) − log p(x | y) for any x."""
    rng = np.random.default_rng(seed)
    mu, S, H, R, y = rng.standard_normal(n), spd(rng, n), rng.standard_normal((m, n)), spd(rng, m), rng.standard_normal(m)
    prior = Gaussian(t(mu), t(S))
    post, logev = condition_with_evidence(prior, t(H), t(R), t(y))
    for x in rng.standard_normal((3, n)):
        rhs = (
            prior.log_prob(t(x))
            + log_density(t(y), t(H @ x), t(R))
            - post.log_prob(t(x))
        )
        close(logev, rhs, tol=1e-9)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 5), m1=st.integers(1, 3), m2=st.integers(1, 3))
def test_conditioning_order_invariance(seed: int, n: int, m1: int, m2: int) -> None:
    """Two conditionally independent observations: y1 then y2 = y2 then y1 = both jointly;
    the evidences multiply (chain rule)."""
    rng = np.random.default_rng(seed)
    prior = Gaussian(t(rng.standard_normal(n)), t(spd(rng, n)))
    H1, H2 = t(rng.standard_normal((m1, n))), t(rng.standard_normal((m2, n)))
    R1, R2 = t(spd(rng, m1)), t(spd(rng, m2))
    y1, y2 = t(rng.standard_normal(m1)), t(rng.standard_normal(m2))
    a, la1 = condition_with_evidence(prior, H1, R1, y1)
    a, la2 = condition_with_evidence(a, H2, R2, y2)
    b, lb2 = condition_with_evidence(prior, H2, R2, y2)
    b, lb1 = condition_with_evidence(b, H1, R1, y1)
    H12 = torch.cat([H1, H2], 0)
    R12 = torch.block_diag(R1, R2)
    c, lc = condition_with_evidence(prior, H12, R12, torch.cat([y1, y2]))
    d = condition_on_block(joint_linear_gaussian(prior, H12, R12), n, torch.cat([y1, y2]))
    for post in (b, c, d):
        close(a.mean, post.mean, tol=1e-9)
        close(a.cov, post.cov, tol=1e-9)
    close(la1 + la2, lc, tol=1e-10)
    close(lb1 + lb2, lc, tol=1e-10)


def test_batched_equals_loop_and_broadcasting() -> None:
    rng = np.random.default_rng(4)
    n, m, B = 3, 2, 5
    prior = Gaussian(t(rng.standard_normal(n)), t(spd(rng, n)))   # shared prior
    H, R = t(rng.standard_normal((m, n))), t(spd(rng, m))          # shared model
    y = t(rng.standard_normal((B, m)))                              # batched data
    post, ll = condition_with_evidence(prior, H, R, y)
    assert post.mean.shape == (B, n) and post.cov.shape[-2:] == (n, n) and ll.shape == (B,)
    for i in range(B):
        pi, li = condition_with_evidence(prior, H, R, y[i])
        close(post.mean[i], pi.mean, tol=1e-13)
        close(post.cov.expand(B, n, n)[i], pi.cov, tol=1e-13)
        close(ll[i], li, tol=1e-13)


def test_float32_is_supported() -> None:
    rng = np.random.default_rng(5)
    prior = Gaussian(torch.tensor(rng.standard_normal(3), dtype=torch.float32), torch.eye(3) * 2)
    H, R = torch.tensor(rng.standard_normal((2, 3)), dtype=torch.float32), torch.eye(2)
    post, ll = condition_with_evidence(prior, H, R, torch.ones(2))
    assert post.mean.dtype == torch.float32 and ll.dtype == torch.float32
    ref, ref_ll = condition_with_evidence(prior.to(DT), H.to(DT), R.to(DT), torch.ones(2, dtype=DT))
    np.testing.assert_allclose(post.cov.numpy(), ref.cov.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ll.numpy(), ref_ll.numpy(), rtol=1e-5)


def test_gradcheck_condition_with_evidence() -> None:
    rng = np.random.default_rng(6)
    mu, S = t(rng.standard_normal(3)).requires_grad_(), t(spd(rng, 3))
    H, y = t(rng.standard_normal((2, 3))), t(rng.standard_normal(2))
    log_r = t(rng.standard_normal(2) * 0.3).requires_grad_()

    def f(mu, log_r):
        post, ll = condition_with_evidence(Gaussian(mu, S), H, torch.diag(log_r.exp()), y, validate=False)
        return ll, post.mean, post.cov

    assert torch.autograd.gradcheck(f, (mu, log_r))


# ---------------------------------------------------------------- Gaussian type


def test_sample_moments_and_indexing() -> None:
    rng = np.random.default_rng(7)
    g = Gaussian(t(rng.standard_normal((2, 3))), t(np.stack([spd(rng, 3), spd(rng, 3)])))
    x = g.sample(200_000, generator=torch.Generator().manual_seed(0))
    assert x.shape == (200_000, 2, 3)
    se = (g.var / 200_000).sqrt()
    assert bool(((x.mean(0) - g.mean).abs() < 5 * se).all())
    emp = torch.einsum("sbi,sbj->bij", x - x.mean(0), x - x.mean(0)) / (x.shape[0] - 1)
    assert float((emp - g.cov).abs().max()) < 0.05 * float(g.cov.abs().max())
    first = g[1]
    close(first.mean, g.mean[1], tol=0)
    close(first.cov, g.cov[1], tol=0)
    shared = Gaussian(torch.zeros(4, 3, dtype=DT), torch.eye(3, dtype=DT))  # cov broadcast over the batch
    assert shared.batch_shape == (4,) and shared[2].cov.shape == (3, 3)
    close(g.std, g.var.sqrt(), tol=0)


def test_where_selects_beliefs() -> None:
    a = Gaussian(torch.zeros(3, 2, dtype=DT), torch.eye(2, dtype=DT).expand(3, 2, 2))
    b = Gaussian(torch.ones(3, 2, dtype=DT), 2 * torch.eye(2, dtype=DT).expand(3, 2, 2))
    c = a.where(torch.tensor([True, False, True]), b)
    assert c.mean[:, 0].tolist() == [0.0, 1.0, 0.0]
    assert c.cov[:, 0, 0].tolist() == [1.0, 2.0, 1.0]


# ---------------------------------------------------------------- bad input -> ValueError naming the argument


def test_bad_inputs_name_the_argument() -> None:
    g = Gaussian(torch.zeros(3, dtype=DT), torch.eye(3, dtype=DT))
    with pytest.raises(ValueError, match="^cov"):
        Gaussian(torch.zeros(3, dtype=DT), torch.eye(2, dtype=DT))
    with pytest.raises(ValueError, match="^mean"):
        Gaussian(torch.zeros((), dtype=DT), torch.eye(1, dtype=DT))
    with pytest.raises(ValueError, match="^cov"):
        Gaussian(torch.zeros(4, 3, dtype=DT), torch.eye(3, dtype=DT).expand(5, 3, 3))
    with pytest.raises(ValueError, match="^belief.cov"):
        Gaussian(torch.zeros(2, dtype=DT), torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=DT)).validate()
    with pytest.raises(ValueError, match="^cov"):
        log_density(torch.zeros(2, dtype=DT), torch.zeros(2, dtype=DT), -torch.eye(2, dtype=DT))
    with pytest.raises(ValueError, match="^H"):
        condition(g, torch.ones(2, 4, dtype=DT), torch.eye(2, dtype=DT), torch.zeros(2, dtype=DT))
    with pytest.raises(ValueError, match="^R"):
        condition(g, torch.ones(2, 3, dtype=DT), torch.eye(3, dtype=DT), torch.zeros(2, dtype=DT))
    with pytest.raises(ValueError, match="^R"):  # negative variance
        condition(g, torch.ones(2, 3, dtype=DT), torch.diag(torch.tensor([1.0, -1.0], dtype=DT)), torch.zeros(2, dtype=DT))
    with pytest.raises(ValueError, match="^y"):
        condition(g, torch.ones(2, 3, dtype=DT), torch.eye(2, dtype=DT), torch.zeros(3, dtype=DT))
    with pytest.raises(ValueError, match="^noise_cov"):
        marginalize_linear([(None, g)], noise_cov=-torch.eye(3, dtype=DT))
    with pytest.raises(ValueError, match="^causes"):
        marginalize_linear([])
    with pytest.raises(ValueError, match=r"^causes\[1\]"):
        marginalize_linear([(None, g), (torch.ones(2, 3, dtype=DT), g)])
    with pytest.raises(ValueError, match="^n_first"):
        condition_on_block(g, 0, torch.zeros(3, dtype=DT))
    with pytest.raises(ValueError, match="^n"):
        g.sample(0)

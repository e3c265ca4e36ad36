"""Tests of pgm_wm.factorized against dense Gaussian algebra (pgm_wm.gaussian / pgm_wm.kalman)."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm_wm.beliefs import DiagGaussian
from pgm_wm.factorized import (
    FactorizedBelief,
    block_inverse,
    factorized_predict,
    factorized_predict_from_matrix,
    factorized_update,
    known_input,
    linear_cause,
)
from pgm_wm.gaussian import Gaussian, marginalize_linear
from pgm_wm.kalman import kf_predict, kf_update

D = torch.float64


def random_belief(gen: torch.Generator, batch: tuple[int, ...], m: int, dtype=D) -> FactorizedBelief:
    """A random valid factorized belief: |σs| < sqrt(σu σl)."""
    su = 0.1 + 3.0 * torch.rand(*batch, m, generator=gen, dtype=dtype)
    sl = 0.1 + 3.0 * torch.rand(*batch, m, generator=gen, dtype=dtype)
    rho = 1.9 * torch.rand(*batch, m, generator=gen, dtype=dtype) - 0.95
    mean = torch.randn(*batch, 2 * m, generator=gen, dtype=dtype)
    return FactorizedBelief(mean, su, sl, rho * (su * sl).sqrt())


def obs_matrix(m: int) -> torch.Tensor:
    return torch.cat([torch.eye(m, dtype=D), torch.zeros(m, m, dtype=D)], dim=-1)


def band(m: int, bw: int) -> torch.Tensor:
    i = torch.arange(m)
    return ((i[:, None] - i[None, :]).abs() <= bw).to(D)


# ------------------------------------------------------------------------------ belief container
def test_dense_roundtrip_and_structure():
    gen = torch.Generator().manual_seed(0)
    b = random_belief(gen, (3,), 4)
    g = b.to_dense()
    assert g.cov.shape == (3, 8, 8)
    g.validate()  # positive definite
    # off-diagonal entries inside each block are zero
    offdiag = ~torch.eye(4, dtype=torch.bool)
    for blk in (g.cov[:, :4, :4], g.cov[:, :4, 4:], g.cov[:, 4:, :4], g.cov[:, 4:, 4:]):
        assert torch.all(blk[:, offdiag] == 0)
    b2 = FactorizedBelief.from_dense(g)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        assert torch.equal(getattr(b, f), getattr(b2, f))
    assert torch.equal(b.var, torch.diagonal(g.cov, dim1=-2, dim2=-1))


def test_container_helpers():
    gen = torch.Generator().manual_seed(1)
    b0, b1 = random_belief(gen, (2,), 3), random_belief(gen, (2,), 3)
    st_ = FactorizedBelief.stack([b0, b1])
    assert st_.mean.shape == (2, 2, 6) and st_.var_upper.shape == (2, 2, 3)
    assert torch.equal(st_.at(1).cov_side, b1.cov_side)
    sel = b0.where(torch.tensor([True, False]), b1)
    assert torch.equal(sel.mean[0], b0.mean[0]) and torch.equal(sel.mean[1], b1.mean[1])
    s = b0 + b1
    assert torch.allclose(s.to_dense().cov, b0.to_dense().cov + b1.to_dense().cov)
    d = b0.drop_side()
    assert torch.all(d.cov_side == 0) and torch.equal(d.var_upper, b0.var_upper)
    iso = FactorizedBelief.isotropic((5,), 2, var=3.0, dtype=D)
    assert torch.all(iso.var == 3.0) and torch.all(iso.cov_side == 0) and iso.mean.dtype == D


# ------------------------------------------------------------------------------ update
@settings(max_examples=25, deadline=None)
@given(m=st.integers(1, 6), batch=st.integers(1, 4), seed=st.integers(0, 10_000))
def test_update_equals_dense_kalman_update(m, batch, seed):
    gen = torch.Generator().manual_seed(seed)
    prior = random_belief(gen, (batch,), m)
    w = torch.randn(batch, m, generator=gen, dtype=D)
    w_var = 0.05 + 2.0 * torch.rand(batch, m, generator=gen, dtype=D)
    post = factorized_update(prior, DiagGaussian(w, w_var))
    dense, _ = kf_update(prior.to_dense(), obs_matrix(m), torch.diag_embed(w_var), w)
    torch.testing.assert_close(post.mean, dense.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(post.to_dense().cov, dense.cov, rtol=1e-10, atol=1e-10)
    # the dense posterior keeps the factorized structure, so nothing was approximated
    torch.testing.assert_close(FactorizedBelief.from_dense(dense).to_dense().cov, dense.cov, rtol=0, atol=1e-12)
    # conditioning never increases a variance
    assert torch.all(post.var <= prior.var + 1e-12)


def test_thesis_printed_update_formulas_are_wrong():
    """The errata claim: the printed σu⁺ = σu⊙σu⊘S and σs⁺ = σu⊙σs⊘S disagree with dense algebra."""
    gen = torch.Generator().manual_seed(3)
    m = 4
    prior = random_belief(gen, (1,), m)
    w = torch.randn(1, m, generator=gen, dtype=D)
    w_var = 0.5 + torch.rand(1, m, generator=gen, dtype=D)
    dense, _ = kf_update(prior.to_dense(), obs_matrix(m), torch.diag_embed(w_var), w)
    ref = FactorizedBelief.from_dense(dense)
    S = prior.var_upper + w_var
    printed_u = prior.var_upper * prior.var_upper / S
    printed_s = prior.var_upper * prior.cov_side / S
    printed_lower_mean = prior.mean_lower + prior.var_lower * (w - prior.mean_upper) / S
    assert (printed_u - ref.var_upper).abs().max() > 1e-2
    assert (printed_s - ref.cov_side).abs().max() > 1e-2
    assert (printed_lower_mean - ref.mean_lower).abs().max() > 1e-2


def test_update_mask_leaves_prior_exactly():
    gen = torch.Generator().manual_seed(4)
    prior = random_belief(gen, (4,), 3)
    w = torch.randn(4, 3, generator=gen, dtype=D)
    w_var = 0.1 + torch.rand(4, 3, generator=gen, dtype=D)
    mask = torch.tensor([True, False, True, False])
    post = factorized_update(prior, DiagGaussian(w, w_var), mask)
    full = factorized_update(prior, DiagGaussian(w, w_var))
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        a, p, q = getattr(post, f), getattr(prior, f), getattr(full, f)
        assert torch.equal(a[~mask], p[~mask])  # bit-identical to the prior
        torch.testing.assert_close(a[mask], q[mask], rtol=1e-14, atol=1e-14)
    # a 0/1 float mask is accepted
    post2 = factorized_update(prior, DiagGaussian(w, w_var), mask.to(D))
    assert torch.equal(post2.mean, post.mean)


def test_update_float32_small_observation_variance_stays_positive():
    b = FactorizedBelief.isotropic((2,), 5, var=10.0, dtype=torch.float32)
    w = torch.randn(2, 5)
    post = factorized_update(b, DiagGaussian(w, torch.full((2, 5), 1e-6)))
    assert torch.all(post.var_upper > 0) and torch.all(post.var_lower > 0)
    torch.testing.assert_close(post.var_upper, torch.full((2, 5), 1e-6), rtol=1e-4, atol=0)


def test_sequential_updates_commute():
    """Two observations of the same state in either order give the same posterior."""
    gen = torch.Generator().manual_seed(5)
    prior = random_belief(gen, (2,), 3)
    w1, w2 = torch.randn(2, 2, 3, generator=gen, dtype=D)
    v1, v2 = 0.1 + torch.rand(2, 2, 3, generator=gen, dtype=D)
    a = factorized_update(factorized_update(prior, DiagGaussian(w1, v1)), DiagGaussian(w2, v2))
    b = factorized_update(factorized_update(prior, DiagGaussian(w2, v2)), DiagGaussian(w1, v1))
    torch.testing.assert_close(a.to_dense().cov, b.to_dense().cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------ block inversion
@settings(max_examples=20, deadline=None)
@given(m=st.integers(1, 6), seed=st.integers(0, 10_000))
def test_block_inverse_roundtrip_and_dense(m, seed):
    gen = torch.Generator().manual_seed(seed)
    b = random_belief(gen, (2,), m)
    lu, ll, ls = block_inverse(b.var_upper, b.var_lower, b.cov_side)
    prec = FactorizedBelief(b.mean, lu, ll, ls).to_dense().cov
    torch.testing.assert_close(prec, torch.linalg.inv(b.to_dense().cov), rtol=1e-10, atol=1e-10)
    su, sl, ss = block_inverse(lu, ll, ls)
    torch.testing.assert_close(su, b.var_upper, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(sl, b.var_lower, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ss, b.cov_side, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------ predict
def dense_A(A11, A12, A21, A22):
    return torch.cat([torch.cat([A11, A12], -1), torch.cat([A21, A22], -1)], -2)


@settings(max_examples=20, deadline=None)
@given(m=st.integers(1, 6), seed=st.integers(0, 10_000))
def test_predict_diagonal_blocks_equals_dense_predict(m, seed):
    gen = torch.Generator().manual_seed(seed)
    b = random_belief(gen, (3,), m)
    blocks = [torch.diag_embed(torch.randn(3, m, generator=gen, dtype=D)) for _ in range(4)]
    q = torch.rand(2 * m, generator=gen, dtype=D)
    out = factorized_predict(b, *blocks, q)
    dense = kf_predict(b.to_dense(), dense_A(*blocks), torch.diag(q))
    torch.testing.assert_close(out.mean, dense.mean, rtol=1e-12, atol=1e-12)
    # exact: the dense result is itself factorized
    torch.testing.assert_close(out.to_dense().cov, dense.cov, rtol=1e-12, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(m=st.integers(2, 7), bw=st.integers(0, 3), seed=st.integers(0, 10_000))
def test_predict_band_blocks_keeps_block_diagonals(m, bw, seed):
    gen = torch.Generator().manual_seed(seed)
    b = random_belief(gen, (2,), m)
    blocks = [torch.randn(2, m, m, generator=gen, dtype=D) * band(m, bw) for _ in range(4)]
    q = torch.rand(2 * m, generator=gen, dtype=D)
    out = factorized_predict(b, *blocks, q)
    dense = kf_predict(b.to_dense(), dense_A(*blocks), torch.diag(q))
    ref = FactorizedBelief.from_dense(dense)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(out, f), getattr(ref, f), rtol=1e-12, atol=1e-12)
    # same result from the one-matrix entry point, with broadcasting of unbatched blocks
    out2 = factorized_predict_from_matrix(b, dense_A(*blocks), q)
    torch.testing.assert_close(out2.to_dense().cov, out.to_dense().cov, rtol=1e-13, atol=1e-13)
    shared = [blk[0] for blk in blocks]
    out3 = factorized_predict(b, *shared, q)
    ref3 = FactorizedBelief.from_dense(kf_predict(b.to_dense(), dense_A(*shared), torch.diag(q)))
    torch.testing.assert_close(out3.cov_side, ref3.cov_side, rtol=1e-12, atol=1e-12)


def test_predict_with_full_blocks_is_an_approximation():
    """With full blocks the dense covariance has off-diagonal block entries the RKN drops."""
    gen = torch.Generator().manual_seed(6)
    b = random_belief(gen, (1,), 4)
    blocks = [torch.randn(4, 4, generator=gen, dtype=D) for _ in range(4)]
    dense = kf_predict(b.to_dense(), dense_A(*blocks), torch.zeros(8, 8, dtype=D))
    approx = factorized_predict(b, *blocks, torch.zeros(8, dtype=D)).to_dense()
    assert (dense.cov - approx.cov).abs().max() > 1e-3
    torch.testing.assert_close(torch.diagonal(approx.cov, dim1=-2, dim2=-1),
                               torch.diagonal(dense.cov, dim1=-2, dim2=-1), rtol=1e-12, atol=1e-12)


def test_linear_cause_block_diagonals():
    gen = torch.Generator().manual_seed(7)
    m, k = 3, 5
    C = torch.randn(2, 2 * m, k, generator=gen, dtype=D)
    mu = torch.randn(2, k, generator=gen, dtype=D)
    var = 0.1 + torch.rand(2, k, generator=gen, dtype=D)
    c = linear_cause(C, DiagGaussian(mu, var))
    ref = C @ torch.diag_embed(var) @ C.transpose(-1, -2)
    torch.testing.assert_close(c.mean, (C @ mu.unsqueeze(-1)).squeeze(-1))
    exp = FactorizedBelief.from_dense(Gaussian(c.mean, ref))
    for f in ("var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(c, f), getattr(exp, f), rtol=1e-12, atol=1e-12)


def test_predict_with_causes_equals_dense_marginalization():
    """State + a known input + a task with diagonal-block C = dense marginalize_linear exactly."""
    gen = torch.Generator().manual_seed(8)
    m = 3
    b = random_belief(gen, (2,), m)
    blocks = [torch.diag_embed(torch.randn(m, generator=gen, dtype=D)) for _ in range(4)]
    q = torch.rand(2 * m, generator=gen, dtype=D)
    C = torch.cat([torch.diag(torch.randn(m, generator=gen, dtype=D)),
                   torch.diag(torch.randn(m, generator=gen, dtype=D))], dim=0)  # (2m, m)
    task_mu, task_var = torch.randn(2, m, generator=gen, dtype=D), 0.2 + torch.rand(2, m, generator=gen, dtype=D)
    u = torch.randn(2, 2 * m, generator=gen, dtype=D)
    out = factorized_predict(b, *blocks, q, causes=[known_input(u), linear_cause(C, DiagGaussian(task_mu, task_var))])
    dense = marginalize_linear([(dense_A(*blocks), b.to_dense()),
                                (C, Gaussian(task_mu, torch.diag_embed(task_var)))],
                               noise_cov=torch.diag(q), offset=u)
    torch.testing.assert_close(out.mean, dense.mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.to_dense().cov, dense.cov, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------ bad inputs
def test_bad_inputs_raise_value_error():
    b = FactorizedBelief.isotropic((2,), 3, dtype=D)
    w, v = torch.zeros(2, 3, dtype=D), torch.ones(2, 3, dtype=D)
    with pytest.raises(ValueError, match="mean"):
        FactorizedBelief(torch.zeros(2, 5), torch.ones(2, 2), torch.ones(2, 2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="var_lower"):
        FactorizedBelief(torch.zeros(2, 6), torch.ones(2, 3), torch.ones(2, 2), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="cov_side"):
        FactorizedBelief(torch.zeros(6), torch.ones(3), torch.ones(3), torch.full((3,), 2.0)).validate()
    with pytest.raises(ValueError, match="var_upper"):
        FactorizedBelief(torch.zeros(6), -torch.ones(3), torch.ones(3), torch.zeros(3)).validate()
    o = DiagGaussian(w, v)
    with pytest.raises(ValueError, match="^observation.mean"):
        factorized_update(b, DiagGaussian(torch.zeros(2, 4, dtype=D), torch.ones(2, 4, dtype=D)))
    with pytest.raises(ValueError, match="^observation.var"):
        factorized_update(b, DiagGaussian(w, -v))
    with pytest.raises(ValueError, match="^observation.var"):
        factorized_update(b, DiagGaussian(w, torch.full_like(v, float("nan"))))
    with pytest.raises(ValueError, match="^observation.mean"):
        factorized_update(b, DiagGaussian(w * float("nan"), v))
    with pytest.raises(ValueError, match="^observation"):
        factorized_update(b, w)
    with pytest.raises(ValueError, match="^observation: batch"):
        factorized_update(b, DiagGaussian(torch.zeros(5, 3, dtype=D), torch.ones(5, 3, dtype=D)))
    with pytest.raises(ValueError, match="^mask"):
        factorized_update(b, o, torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="^mask"):
        factorized_update(b, o, torch.full((2,), 0.5))
    with pytest.raises(ValueError, match="^prior"):
        factorized_update(b.to_dense(), o)
    # issue 13.8: validate=True checks the prior belief too (a negative prior variance would give a
    # negative posterior variance)
    bad = FactorizedBelief(b.mean, -b.var_upper, b.var_lower, b.cov_side)
    with pytest.raises(ValueError, match="^prior.var_upper"):
        factorized_update(bad, o)
    with pytest.raises(ValueError, match="^prior.mean"):
        factorized_update(FactorizedBelief(b.mean * float("nan"), b.var_upper, b.var_lower, b.cov_side), o)
    # the older positional form (w, w_var, mask) is still accepted and gives the same result
    legacy = factorized_update(b, w, v, torch.tensor([True, False]))
    new = factorized_update(b, o, torch.tensor([True, False]))
    assert all(torch.equal(x, y) for x, y in zip(legacy._tensors(), new._tensors()))
    eye = torch.eye(3, dtype=D)
    with pytest.raises(ValueError, match="A12"):
        factorized_predict(b, eye, torch.eye(4, dtype=D), eye, eye, torch.ones(6, dtype=D))
    with pytest.raises(ValueError, match="trans_var"):
        factorized_predict(b, eye, eye, eye, eye, torch.ones(5, dtype=D))
    with pytest.raises(ValueError, match="trans_var"):
        factorized_predict(b, eye, eye, eye, eye, -torch.ones(6, dtype=D))
    with pytest.raises(ValueError, match="causes"):
        factorized_predict(b, eye, eye, eye, eye, torch.ones(6, dtype=D), causes=[w])
    with pytest.raises(ValueError, match="A"):
        factorized_predict_from_matrix(b, torch.eye(5, dtype=D), torch.ones(6, dtype=D))
    with pytest.raises(ValueError, match="side"):
        block_inverse(torch.ones(3), torch.ones(3), torch.full((3,), 1.0))
    with pytest.raises(ValueError, match="C"):
        linear_cause(torch.ones(5, 2), DiagGaussian(torch.zeros(2), torch.ones(2)))
    with pytest.raises(ValueError, match="b"):
        known_input(torch.ones(3))

"""Tests for pgm_wm.aggregation and pgm_wm.context.

Oracles: dense Gaussian conditioning (pgm_wm.gaussian.condition) on the stacked observation
model, N sequential Kalman updates (pgm_wm.kalman.kf_update, pgm_wm.factorized.factorized_update),
and properties (permutation invariance, padding invariance, monotone variance).
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm_wm.aggregation import (
    BayesianContextEncoder,
    MaxPoolContextEncoder,
    MeanPoolContextEncoder,
    SetEncoder,
    bayesian_aggregation,
    masked_max_pool,
    masked_mean_pool,
    precision_weights,
    set_condition,
)
from pgm_wm.context import (
    ContextSetSampler,
    corrupt_elements,
    evaluate_set_model,
    fit_set_model,
    set_nll,
    transition_features,
)
from pgm_wm.factorized import FactorizedBelief, factorized_update
from pgm_wm.gaussian import Gaussian, condition
from pgm_wm.kalman import kf_update

D64 = torch.float64
SETTINGS = settings(max_examples=25, deadline=None)


def random_set(gen, batch, N, d):
    r = torch.randn(*batch, N, d, generator=gen, dtype=D64) * 2.0
    v = torch.rand(*batch, N, d, generator=gen, dtype=D64) * 3.0 + 0.05
    return r, v


def random_belief(gen, batch, m):
    """A random factorized belief with positive-definite 2x2 blocks."""
    su = torch.rand(*batch, m, generator=gen, dtype=D64) * 4 + 0.2
    sl = torch.rand(*batch, m, generator=gen, dtype=D64) * 4 + 0.2
    rho = torch.rand(*batch, m, generator=gen, dtype=D64) * 1.8 - 0.9
    ss = rho * (su * sl).sqrt()
    mean = torch.randn(*batch, 2 * m, generator=gen, dtype=D64)
    return FactorizedBelief(mean, su, sl, ss)


def stacked_dense_condition(prior: Gaussian, H: torch.Tensor, r: torch.Tensor, v: torch.Tensor) -> Gaussian:
    """Oracle: condition once on all N observations stacked, H_bar = [H; ...; H], R = blockdiag."""
    N, d = r.shape[-2], r.shape[-1]
    H_bar = torch.cat([H] * N, dim=-2)
    R = torch.diag_embed(v.reshape(*v.shape[:-2], N * d))
    return condition(prior, H_bar, R, r.reshape(*r.shape[:-2], N * d))


# ----------------------------------------------------------------------------- Bayesian aggregation
@SETTINGS
@given(N=st.integers(1, 7), d=st.integers(1, 3), b=st.integers(1, 3), seed=st.integers(0, 10_000))
def test_ba_equals_dense_and_sequential_kalman(N, d, b, seed):
    gen = torch.Generator().manual_seed(seed)
    r, v = random_set(gen, (b,), N, d)
    mu0 = torch.randn(b, d, generator=gen, dtype=D64)
    var0 = torch.rand(b, d, generator=gen, dtype=D64) + 0.5
    mean, var = bayesian_aggregation(r, v, prior_mean=mu0, prior_var=var0)
    prior = Gaussian(mu0, torch.diag_embed(var0))
    eye = torch.eye(d, dtype=D64)
    dense = stacked_dense_condition(prior, eye, r, v)
    torch.testing.assert_close(mean, dense.mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(torch.diag_embed(var), dense.cov, rtol=1e-9, atol=1e-10)
    # N sequential Kalman updates with H = I and no dynamics
    belief = prior
    for n in range(N):
        belief, _ = kf_update(belief, r[:, n], eye, torch.diag_embed(v[:, n]))
    torch.testing.assert_close(mean, belief.mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(torch.diag_embed(var), belief.cov, rtol=1e-9, atol=1e-10)


def test_ba_default_prior_is_standard_normal_and_closed_form():
    r = torch.tensor([[[1.0], [3.0]]], dtype=D64)  # batch 1, N = 2, d = 1
    v = torch.tensor([[[1.0], [0.5]]], dtype=D64)
    mean, var = bayesian_aggregation(r, v)
    # precision 1 + 1 + 2 = 4; mean = (0*1 + 1*1 + 3*2) / 4
    torch.testing.assert_close(var, torch.tensor([[0.25]], dtype=D64))
    torch.testing.assert_close(mean, torch.tensor([[7.0 / 4.0]], dtype=D64))


@SETTINGS
@given(N=st.integers(2, 8), d=st.integers(1, 3), seed=st.integers(0, 10_000))
def test_ba_permutation_invariance(N, d, seed):
    gen = torch.Generator().manual_seed(seed)
    r, v = random_set(gen, (2,), N, d)
    perm = torch.randperm(N, generator=gen)
    m1, v1 = bayesian_aggregation(r, v)
    m2, v2 = bayesian_aggregation(r[:, perm], v[:, perm])
    torch.testing.assert_close(m1, m2, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(v1, v2, rtol=1e-12, atol=1e-12)


@SETTINGS
@given(N=st.integers(1, 6), pad=st.integers(1, 5), seed=st.integers(0, 10_000))
def test_ba_padding_invariance_with_garbage(N, pad, seed):
    gen = torch.Generator().manual_seed(seed)
    r, v = random_set(gen, (3,), N, 2)
    r.requires_grad_(True)
    garbage_r = torch.full((3, pad, 2), float("nan"), dtype=D64)
    garbage_v = torch.zeros(3, pad, 2, dtype=D64)  # zero / invalid variances in the padding
    rp = torch.cat([r, garbage_r], dim=1)
    vp = torch.cat([v, garbage_v], dim=1)
    mask = torch.cat([torch.ones(3, N, dtype=torch.bool), torch.zeros(3, pad, dtype=torch.bool)], dim=1)
    # interleave the padding at random positions
    perm = torch.randperm(N + pad, generator=gen)
    m1, v1 = bayesian_aggregation(r, v)
    m2, v2 = bayesian_aggregation(rp[:, perm], vp[:, perm], mask[:, perm])
    torch.testing.assert_close(m1, m2, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(v1, v2, rtol=1e-12, atol=1e-12)
    (g,) = torch.autograd.grad(m2.sum(), r)
    assert torch.isfinite(g).all()


def test_ba_empty_set_returns_prior_and_batch_one_works():
    r = torch.randn(1, 4, 3, dtype=D64)
    v = torch.rand(1, 4, 3, dtype=D64) + 0.1
    mean, var = bayesian_aggregation(r, v, torch.zeros(1, 4, dtype=torch.bool), prior_mean=0.5, prior_var=2.0)
    torch.testing.assert_close(mean, torch.full((1, 3), 0.5, dtype=D64))
    torch.testing.assert_close(var, torch.full((1, 3), 2.0, dtype=D64))
    # batch size 1 and N = 1 keep their dimensions (no squeeze)
    mean, var = bayesian_aggregation(r[:, :1], v[:, :1])
    assert mean.shape == (1, 3) and var.shape == (1, 3)
    # no batch dimension at all
    mean, var = bayesian_aggregation(r[0], v[0])
    assert mean.shape == (3,)


@SETTINGS
@given(N=st.integers(1, 10), seed=st.integers(0, 10_000))
def test_ba_variance_never_increases_and_shrinks_like_one_over_n(N, seed):
    gen = torch.Generator().manual_seed(seed)
    r, v = random_set(gen, (2,), N, 3)
    prev = torch.ones(2, 3, dtype=D64)  # prior variance
    for n in range(1, N + 1):
        _, var = bayesian_aggregation(r[:, :n], v[:, :n])
        assert bool((var <= prev * (1 + 1e-12)).all())
        prev = var
    # equal variances s: posterior variance is exactly 1 / (1 + N / s)
    s = 0.7
    _, var = bayesian_aggregation(r, torch.full_like(v, s))
    torch.testing.assert_close(var, torch.full_like(var, 1.0 / (1.0 + N / s)))


def test_precision_weights_reproduce_the_posterior_mean():
    gen = torch.Generator().manual_seed(3)
    r, v = random_set(gen, (4,), 6, 2)
    mask = torch.rand(4, 6, generator=gen) < 0.7
    mask[:, 0] = True
    mu0, var0 = 0.3, 1.5
    mean, var = bayesian_aggregation(r, v, mask, mu0, var0)
    w = precision_weights(v, mask, prior_var=var0)
    w0 = var / var0  # the prior's share
    torch.testing.assert_close(w.sum(-2) + w0, torch.ones_like(w0))
    torch.testing.assert_close(mean, w0 * mu0 + (w * r).sum(-2))
    assert bool((w[~mask] == 0).all())
    share = precision_weights(v, mask)
    torch.testing.assert_close(share.sum(-2), torch.ones(4, 2, dtype=D64))


def test_ba_float32_and_broadcast_prior():
    r = torch.randn(5, 7, 3)
    v = torch.rand(5, 7, 3) + 0.1
    mean, var = bayesian_aggregation(r, v, prior_mean=torch.zeros(3), prior_var=torch.ones(5, 3))
    assert mean.dtype == torch.float32 and mean.shape == (5, 3) and var.shape == (5, 3)


# ----------------------------------------------------------------------------- set conditioning
@SETTINGS
@given(N=st.integers(1, 6), m=st.integers(1, 3), b=st.integers(1, 3), seed=st.integers(0, 10_000))
def test_set_condition_equals_dense_conditioning(N, m, b, seed):
    gen = torch.Generator().manual_seed(seed)
    prior = random_belief(gen, (b,), m)
    r, v = random_set(gen, (b,), N, m)
    post = set_condition(prior, r, v)
    H = torch.cat([torch.eye(m, dtype=D64), torch.zeros(m, m, dtype=D64)], dim=-1)
    dense = stacked_dense_condition(prior.to_dense(), H, r, v)
    torch.testing.assert_close(post.mean, dense.mean, rtol=1e-8, atol=1e-9)
    torch.testing.assert_close(post.to_dense().cov, dense.cov, rtol=1e-8, atol=1e-9)


@SETTINGS
@given(N=st.integers(1, 6), m=st.integers(1, 3), seed=st.integers(0, 10_000))
def test_set_condition_equals_sequential_factorized_updates_in_any_order(N, m, seed):
    gen = torch.Generator().manual_seed(seed)
    prior = random_belief(gen, (2,), m)
    r, v = random_set(gen, (2,), N, m)
    post = set_condition(prior, r, v)
    belief = prior
    for n in torch.randperm(N, generator=gen).tolist():
        belief = factorized_update(belief, r[:, n], v[:, n])
    for name in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(post, name), getattr(belief, name), rtol=1e-8, atol=1e-9)


def test_set_condition_single_element_is_factorized_update_exactly():
    gen = torch.Generator().manual_seed(1)
    prior = random_belief(gen, (1,), 4)  # batch size 1
    r, v = random_set(gen, (1,), 1, 4)
    post = set_condition(prior, r, v)
    ref = factorized_update(prior, r[:, 0], v[:, 0])
    for name in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(post, name), getattr(ref, name), rtol=1e-12, atol=1e-12)


def test_set_condition_reduces_to_ba_when_memory_is_uncorrelated():
    gen = torch.Generator().manual_seed(2)
    m = 3
    prior = random_belief(gen, (2,), m)
    prior = FactorizedBelief(prior.mean, prior.var_upper, prior.var_lower, torch.zeros_like(prior.cov_side))
    r, v = random_set(gen, (2,), 5, m)
    post = set_condition(prior, r, v)
    mean, var = bayesian_aggregation(r, v, prior_mean=prior.mean_upper, prior_var=prior.var_upper)
    torch.testing.assert_close(post.mean_upper, mean)
    torch.testing.assert_close(post.var_upper, var)
    torch.testing.assert_close(post.mean_lower, prior.mean_lower)  # memory untouched
    torch.testing.assert_close(post.var_lower, prior.var_lower)


@SETTINGS
@given(N=st.integers(1, 6), pad=st.integers(1, 4), seed=st.integers(0, 10_000))
def test_set_condition_permutation_and_padding_invariance(N, pad, seed):
    gen = torch.Generator().manual_seed(seed)
    m = 2
    prior = random_belief(gen, (3,), m)
    r, v = random_set(gen, (3,), N, m)
    rp = torch.cat([r, torch.full((3, pad, m), float("nan"), dtype=D64)], 1)
    vp = torch.cat([v, -torch.ones(3, pad, m, dtype=D64)], 1)
    mask = torch.arange(N + pad).expand(3, -1) < N
    perm = torch.randperm(N + pad, generator=gen)
    a = set_condition(prior, r, v)
    b = set_condition(prior, rp[:, perm], vp[:, perm], mask[:, perm])
    for name in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-10, atol=1e-12)


@SETTINGS
@given(N=st.integers(1, 8), seed=st.integers(0, 10_000))
def test_set_condition_marginal_variances_never_increase(N, seed):
    gen = torch.Generator().manual_seed(seed)
    prior = random_belief(gen, (2,), 3)
    r, v = random_set(gen, (2,), N, 3)
    prev_u, prev_l = prior.var_upper, prior.var_lower
    for n in range(1, N + 1):
        post = set_condition(prior, r[:, :n], v[:, :n])
        assert bool((post.var_upper <= prev_u * (1 + 1e-10)).all())
        assert bool((post.var_lower <= prev_l * (1 + 1e-10)).all())
        prev_u, prev_l = post.var_upper, post.var_lower


def test_set_condition_broadcasts_prior_over_sets():
    gen = torch.Generator().manual_seed(5)
    prior = random_belief(gen, (), 2)  # one prior for a batch of 4 sets
    r, v = random_set(gen, (4,), 3, 2)
    post = set_condition(prior, r, v)
    assert post.mean.shape == (4, 4) and post.var_lower.shape == (4, 2)
    one = set_condition(prior, r[1], v[1])
    torch.testing.assert_close(post.mean[1], one.mean)
    torch.testing.assert_close(post.var_lower[1], one.var_lower)


# ----------------------------------------------------------------------------- bad input
def test_bad_input_raises_value_error_naming_the_argument():
    r = torch.randn(2, 3, 2)
    v = torch.rand(2, 3, 2) + 0.1
    with pytest.raises(ValueError, match="r_var"):
        bayesian_aggregation(r, v.clone().index_fill_(1, torch.tensor([1]), 0.0))
    with pytest.raises(ValueError, match="r_var"):
        bayesian_aggregation(r, -v)
    with pytest.raises(ValueError, match="r_var"):
        bayesian_aggregation(r, v[:, :2])
    with pytest.raises(ValueError, match="mask"):
        bayesian_aggregation(r, v, torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask"):
        bayesian_aggregation(r, v, torch.full((2, 3), 0.5))
    with pytest.raises(ValueError, match="prior_var"):
        bayesian_aggregation(r, v, prior_var=0.0)
    with pytest.raises(ValueError, match="prior_mean"):
        bayesian_aggregation(r, v, prior_mean=torch.zeros(3))
    with pytest.raises(ValueError, match="prior_mean"):
        bayesian_aggregation(r, v, prior_mean=torch.zeros(5, 2))
    with pytest.raises(ValueError, match="r"):
        bayesian_aggregation(torch.randn(3), torch.rand(3))
    prior = FactorizedBelief.isotropic((2,), 2)
    with pytest.raises(ValueError, match="r"):
        set_condition(prior, torch.randn(2, 3, 3), torch.rand(2, 3, 3) + 0.1)
    with pytest.raises(ValueError, match="r_var"):
        set_condition(prior, r, torch.zeros_like(v))
    with pytest.raises(ValueError, match="prior"):
        set_condition(Gaussian(torch.zeros(4), torch.eye(4)), r, v)
    bad = FactorizedBelief(prior.mean, prior.var_upper, prior.var_lower, prior.var_upper * 2)
    with pytest.raises(ValueError, match="cov_side"):
        set_condition(bad, r, v)
    with pytest.raises(ValueError, match="x"):
        SetEncoder(5, 2)(torch.randn(3, 4))
    with pytest.raises(ValueError, match="min_var"):
        SetEncoder(5, 2, min_var=0.0)
    with pytest.raises(ValueError, match="pool"):
        from pgm_wm.aggregation import DeepSetContextEncoder

        DeepSetContextEncoder(5, 2, pool="sum")


# ----------------------------------------------------------------------------- modules
@pytest.mark.parametrize("cls", [BayesianContextEncoder, MeanPoolContextEncoder, MaxPoolContextEncoder])
def test_set_models_are_permutation_and_padding_invariant(cls):
    torch.manual_seed(0)
    model = cls(5, 2, hidden=(16, 16)).double()
    x = torch.randn(3, 6, 5, dtype=D64)
    mask = torch.tensor([[1, 1, 1, 1, 1, 1], [1, 1, 0, 1, 0, 1], [1, 0, 0, 0, 0, 0]], dtype=torch.bool)
    m1, v1 = model(x, mask)
    perm = torch.randperm(6)
    m2, v2 = model(x[:, perm], mask[:, perm])
    torch.testing.assert_close(m1, m2)
    torch.testing.assert_close(v1, v2)
    # padded elements may hold anything
    x3 = torch.where(mask.unsqueeze(-1), x, torch.randn_like(x) * 100)
    m3, v3 = model(x3, mask)
    torch.testing.assert_close(m1, m3)
    torch.testing.assert_close(v1, v3)
    # the compact set (no padding) gives the same answer, batch size 1 included
    keep = mask[1]
    m4, v4 = model(x[1:2, keep])
    torch.testing.assert_close(m1[1:2], m4)
    assert bool((v1 > 0).all())


def test_set_encoder_variance_floor_and_bayesian_encoder_consistency():
    torch.manual_seed(1)
    model = BayesianContextEncoder(4, 3, hidden=(8,), min_var=0.01)
    with torch.no_grad():
        model.encoder.enc_var.bias.fill_(-50.0)  # softplus -> ~0: variance sits on the floor
    x = torch.randn(2, 5, 4)
    r, r_var = model.encode(x)
    assert r.shape == (2, 5, 3) and bool((r_var >= 0.01).all())
    mean, var = model(x)
    ref = bayesian_aggregation(r, r_var)
    torch.testing.assert_close(mean, ref[0])
    torch.testing.assert_close(var, ref[1])
    assert bool((var >= 1.0 / (1.0 + 5 / 0.01) * 0.999).all())


def test_masked_pools():
    h = torch.tensor([[[1.0], [5.0], [3.0]]])
    mask = torch.tensor([[True, False, True]])
    assert masked_mean_pool(h, mask).item() == pytest.approx(2.0)
    assert masked_max_pool(h, mask).item() == pytest.approx(3.0)
    empty = torch.zeros(1, 3, dtype=torch.bool)
    assert masked_max_pool(h, empty).item() == 0.0 and masked_mean_pool(h, empty).item() == 0.0


# ----------------------------------------------------------------------------- context sets
def _toy_sampler(S=6, T=40, F=3, seed=0):
    gen = torch.Generator().manual_seed(seed)
    theta = torch.randn(S, 1, generator=gen)
    # element = theta + noise in feature 0, noise level in feature 1; feature 2 = step index
    noise_sd = torch.rand(S, T, generator=gen) * 1.5 + 0.05
    f0 = theta + noise_sd * torch.randn(S, T, generator=gen)
    feats = torch.stack([f0, noise_sd, torch.arange(T).float().expand(S, T)], -1)
    return ContextSetSampler(feats, theta), theta


def test_sampler_draws_distinct_steps_from_one_sequence():
    sampler, theta = _toy_sampler()
    gen = torch.Generator().manual_seed(1)
    batch = sampler.sample(8, 10, 3, gen)
    assert batch.x.shape == (8, 10, 3) and batch.mask.shape == (8, 10)
    assert bool((batch.sizes >= 3).all()) and bool((batch.sizes <= 10).all())
    torch.testing.assert_close(batch.y, theta[batch.seq])
    for b in range(8):
        steps = batch.x[b, :, 2].long()
        assert len(set(steps.tolist())) == 10  # distinct time steps
        torch.testing.assert_close(batch.x[b, :, :2], sampler.features[batch.seq[b], steps, :2])
    assert not batch.corrupted.any()
    with pytest.raises(ValueError, match="n_max"):
        sampler.sample(2, 41)
    with pytest.raises(ValueError, match="n_min"):
        sampler.sample(2, 5, 6)


def test_corrupt_elements_fraction_and_levels():
    gen = torch.Generator().manual_seed(0)
    x = torch.zeros(200, 50, 2)
    xc, corrupted, level = corrupt_elements(x, 0.3, 2.0, gen)
    assert abs(corrupted.float().mean().item() - 0.3) < 0.02
    assert bool((level[corrupted] == 2.0).all()) and bool((level[~corrupted] == 0).all())
    assert bool((xc[~corrupted] == 0).all())
    assert abs(xc[corrupted].std().item() - 2.0) < 0.1
    with pytest.raises(ValueError, match="frac"):
        corrupt_elements(x, 1.5, 1.0)


def test_transition_features_layout():
    obs = torch.arange(12.0).reshape(1, 4, 3)
    act = torch.ones(1, 4, 2)
    f = transition_features(obs, act)
    assert f.shape == (1, 3, 8)
    torch.testing.assert_close(f[0, 1], torch.tensor([3.0, 4, 5, 1, 1, 3, 3, 3]))
    with pytest.raises(ValueError, match="actions"):
        transition_features(obs, torch.ones(1, 3, 2))


def test_set_nll_matches_torch_distribution():
    gen = torch.Generator().manual_seed(0)
    y, mu = torch.randn(5, 3, generator=gen), torch.randn(5, 3, generator=gen)
    var = torch.rand(5, 3, generator=gen) + 0.1
    ref = -torch.distributions.Normal(mu, var.sqrt()).log_prob(y).sum(-1)
    torch.testing.assert_close(set_nll(y, mu, var), ref)


def test_bayesian_encoder_learns_to_downweight_noisy_elements():
    """End-to-end: with the noise level visible in the input, the learned variance must grow with it."""
    torch.manual_seed(0)
    sampler, _ = _toy_sampler(S=64, T=60)
    sampler = ContextSetSampler(sampler.features[..., :2], sampler.targets)
    gen = torch.Generator().manual_seed(2)
    valid = sampler.sample(128, 16, 1, gen)
    model = BayesianContextEncoder(2, 1, hidden=(32, 32))
    res = fit_set_model(model, sampler, valid, steps=300, batch_size=32, n_max=16, lr=1e-2,
                        corrupt_prob=0.0, eval_every=100, seed=0)
    assert res.valid_loss[-1] < res.valid_loss[0] or res.best_epoch > 0
    x = torch.stack([torch.zeros(20), torch.linspace(0.05, 1.5, 20)], -1)
    _, r_var = model.encode(x)
    # variance increasing with the noise level (Spearman-like check on the ends)
    assert r_var[-1].item() > 3 * r_var[0].item()
    metrics = evaluate_set_model(model, valid)
    assert metrics["rmse"] < 0.5 and math.isfinite(metrics["nll"])


def test_sampler_from_payload_arm_split():
    from pgm_wm.datasets import load

    data = load("payload_arm", "valid", action="pd_target")
    sampler = ContextSetSampler.from_sequence_data(data, "payload", target_mean=1.0, target_std=0.5)
    assert sampler.features.shape == (data.n_sequences, data.seq_len - 1, 2 * data.obs_dim + data.action_dim)
    raw = transition_features(data.obs, data.actions)
    d = data.obs_dim
    torch.testing.assert_close(sampler.features[..., :d], data.normalize_obs(raw[..., :d]))
    torch.testing.assert_close(sampler.features[..., -d:], data.normalize_diff(raw[..., -d:]))
    torch.testing.assert_close(sampler.targets[:, 0], (data.hidden["payload"][:, 0] - 1.0) / 0.5)
    gen = torch.Generator().manual_seed(0)
    batch = sampler.sample(3, 5, generator=gen, sizes=torch.tensor([1, 5, 3]))
    assert batch.sizes.tolist() == [1, 5, 3]
    with pytest.raises(ValueError, match="sizes"):
        sampler.sample(2, 5, sizes=torch.tensor([0, 3]))
    with pytest.raises(ValueError, match="hidden_key"):
        ContextSetSampler.from_sequence_data(load("payload_arm", "switching"), "payload")
    with pytest.raises(ValueError, match="hidden_key"):
        ContextSetSampler.from_sequence_data(data, "mass")

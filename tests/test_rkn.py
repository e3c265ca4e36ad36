"""Tests of the RKN (pgm_wm.rkn), its image trunk (pgm_wm.encoders) and the RNN baselines
(pgm_wm.rnn_filters), against the dense Kalman filter and by properties."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from pgm_wm.encoders import ConvTrunk
from pgm_wm.factorized import FactorizedBelief, factorized_predict, factorized_update
from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter, kf_predict
from pgm_wm.metrics import gaussian_nll
from pgm_wm.rkn import (
    RKN,
    BeliefDecoder,
    LocallyLinearTransition,
    ObservationEncoder,
    band_mask,
    elup1,
)
from pgm_wm.rnn_filters import (
    FilterData,
    GaussianHead,
    RecurrentFilter,
    count_parameters,
    evaluate_filter,
    fit_filter,
    recurrent_hidden_for_budget,
)

D = torch.float64


def small_rkn(m=3, K=4, bw=1, obs_dim=5, dtype=D, diagonal_only=False, seed=0) -> RKN:
    torch.manual_seed(seed)
    enc = ObservationEncoder(obs_dim, m, hidden=(8,))
    model = RKN(enc, LocallyLinearTransition(m, K, bw), BeliefDecoder(m, 2, (8,), (8,)),
                diagonal_only=diagonal_only)
    return model.to(dtype)


def perturb_(module: nn.Module, scale: float = 0.1, seed: int = 1) -> None:
    """Move all parameters away from their structured initialization."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen, dtype=p.dtype))


# ------------------------------------------------------------------------------ building blocks
def test_elup1_and_band_mask():
    x = torch.linspace(-30, 5, 50, dtype=D)
    assert torch.all(elup1(x) > 0)
    torch.testing.assert_close(elup1(torch.tensor([2.0])), torch.tensor([3.0]))
    bm = band_mask(5, 1)
    assert bm.sum() == 5 + 2 * 4 and bm[0, 2].item() is False and bm[3, 2].item() is True
    assert torch.equal(band_mask(4, 0), torch.eye(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="bandwidth"):
        band_mask(4, -1)


def test_transition_initialization_and_structure():
    m, K = 4, 5
    tr = LocallyLinearTransition(m, K, bandwidth=1).to(D)
    mean = torch.randn(7, 2 * m, dtype=D)
    alpha = tr.coefficients(mean)
    assert alpha.shape == (7, K)
    torch.testing.assert_close(alpha.sum(-1), torch.ones(7, dtype=D))
    eye = torch.eye(m, dtype=D)
    expected = torch.cat([torch.cat([eye, 0.2 * eye], -1), torch.cat([-0.2 * eye, eye], -1)], -2)
    torch.testing.assert_close(tr.dense_matrix(mean), expected.expand(7, -1, -1))
    torch.testing.assert_close(tr.trans_var, torch.full((2 * m,), 0.1, dtype=D))
    # after training-like perturbation, entries outside the band stay exactly zero (identity aside)
    perturb_(tr, 0.3)
    A = tr.dense_matrix(mean)
    outside = ~band_mask(m, 1)
    for blk, off in zip(tr.blocks(mean), (eye, 0 * eye, 0 * eye, eye)):
        assert torch.all((blk - off)[:, outside] == 0)
    torch.testing.assert_close(A[:, :m, m:], tr.blocks(mean)[1])
    # the mixture really is sum_k alpha_k A^(k) + I
    basis = tr.dense_basis()
    mix = torch.einsum("bk,kij->bij", tr.coefficients(mean), basis) + torch.eye(2 * m, dtype=D)
    torch.testing.assert_close(A, mix)


def test_transition_forward_equals_block_diagonals_of_dense_predict():
    m = 4
    tr = LocallyLinearTransition(m, 3, bandwidth=2).to(D)
    perturb_(tr, 0.3)
    gen = torch.Generator().manual_seed(2)
    su, sl = 0.5 + torch.rand(2, 5, m, generator=gen, dtype=D)
    b = FactorizedBelief(torch.randn(5, 2 * m, generator=gen, dtype=D), su, sl, 0.5 * (su * sl).sqrt())
    out = tr(b)
    with torch.no_grad():
        dense = kf_predict(b.to_dense(), tr.dense_matrix(b.mean), torch.diag(tr.trans_var))
    ref = FactorizedBelief.from_dense(dense)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(out, f), getattr(ref, f), rtol=1e-12, atol=1e-12)
    # block API gives the same
    out2 = factorized_predict(b, *tr.blocks(b.mean), tr.trans_var)
    torch.testing.assert_close(out2.to_dense().cov, out.to_dense().cov)
    # the predictor closure equals forward
    torch.testing.assert_close(tr.predictor()(b).mean, out.mean)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="latent_obs_dim"):
        LocallyLinearTransition(0)
    with pytest.raises(ValueError, match="num_basis"):
        LocallyLinearTransition(3, num_basis=0)
    with pytest.raises(ValueError, match="bandwidth"):
        LocallyLinearTransition(3, bandwidth=-2)
    with pytest.raises(ValueError, match="trans_var_init"):
        LocallyLinearTransition(3, trans_var_init=0.0)
    tr = LocallyLinearTransition(3)
    with pytest.raises(ValueError, match="init_var"):
        RKN(nn.Identity(), tr, nn.Identity(), init_var=-1.0)
    with pytest.raises(ValueError, match="feature_dim"):
        ObservationEncoder(4, 3, trunk=nn.Identity())
    with pytest.raises(ValueError, match="image_shape"):
        ConvTrunk((24,))
    with pytest.raises(ValueError, match="kernel_size"):
        ConvTrunk((8, 8), kernel_size=2)
    with pytest.raises(ValueError, match="cell_type"):
        RecurrentFilter(ObservationEncoder(4, 3), "rnn", 8, out_dim=2)
    with pytest.raises(ValueError, match="out_dim"):
        RecurrentFilter(ObservationEncoder(4, 3), "gru", 8)


# ------------------------------------------------------------------------------ the RKN filter
def test_rkn_with_one_diagonal_basis_reproduces_the_dense_kalman_filter():
    """num_basis=1, bandwidth=0, fixed parameters: the RKN filter *is* a Kalman filter."""
    m, B, T = 3, 2, 25
    tr = LocallyLinearTransition(m, num_basis=1, bandwidth=0).to(D)
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in (tr.basis_11, tr.basis_12, tr.basis_21, tr.basis_22):
            p.copy_(torch.diag_embed(0.3 * torch.randn(1, m, generator=gen, dtype=D)))
        tr.trans_var_raw.add_(0.5 * torch.randn(2 * m, generator=gen, dtype=D))
    model = RKN(nn.Identity(), tr, nn.Identity(), init_var=4.0)
    y = torch.randn(B, T, m, generator=gen, dtype=D)
    r = 0.2 + torch.rand(B, 1, m, generator=gen, dtype=D)  # constant in time (dense KF takes one R)
    mask = torch.rand(B, T, generator=gen) > 0.3
    out = model.filter(y, r.expand(B, T, m), mask)
    A = tr.dense_matrix(torch.zeros(2 * m, dtype=D))
    H = torch.cat([torch.eye(m, dtype=D), torch.zeros(m, m, dtype=D)], -1)
    init = Gaussian(torch.zeros(2 * m, dtype=D), 4.0 * torch.eye(2 * m, dtype=D))
    ref = kalman_filter(y, init, A.detach(), H, torch.diag(tr.trans_var.detach()), torch.diag_embed(r[:, 0]), mask=mask)
    post = out.posterior.to_dense()
    prior = out.prior.to_dense()
    torch.testing.assert_close(post.mean, ref.filtered.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(post.cov, ref.filtered.cov, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(prior.mean, ref.predicted.mean.expand_as(prior.mean), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(prior.cov, ref.predicted.cov.expand_as(prior.cov), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.predicted.at(-1).mean, ref.next_prior.mean, rtol=1e-10, atol=1e-10)


def test_filter_masked_steps_posterior_equals_prior_and_predicted_shifts():
    model = small_rkn()
    perturb_(model.transition, 0.2)
    gen = torch.Generator().manual_seed(4)
    w = torch.randn(3, 12, 3, generator=gen, dtype=D)
    w_var = 0.1 + torch.rand(3, 12, 3, generator=gen, dtype=D)
    mask = torch.rand(3, 12, generator=gen) > 0.4
    mask[0, 5:9] = False
    out = model.filter(w, w_var, mask)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        post, prior, pred = (getattr(x, f) for x in (out.posterior, out.prior, out.predicted))
        assert torch.equal(post[~mask], prior[~mask])
        assert not torch.equal(post[mask], prior[mask])
        assert torch.equal(pred[:, :-1], prior[:, 1:])
    # uncertainty grows over the gap
    vu = out.posterior.var_upper[0, 5:9].sum(-1)
    assert torch.all(vu[1:] > vu[:-1])


def test_filter_batch_equals_one_sequence_at_a_time():
    model = small_rkn()
    perturb_(model, 0.2)
    gen = torch.Generator().manual_seed(5)
    w = torch.randn(4, 8, 3, generator=gen, dtype=D)
    w_var = 0.1 + torch.rand(4, 8, 3, generator=gen, dtype=D)
    mask = torch.rand(4, 8, generator=gen) > 0.3
    out = model.filter(w, w_var, mask)
    for i in range(4):
        one = model.filter(w[i:i + 1], w_var[i:i + 1], mask[i:i + 1])
        torch.testing.assert_close(one.posterior.mean[0], out.posterior.mean[i], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(one.posterior.cov_side[0], out.posterior.cov_side[i], rtol=1e-12, atol=1e-12)


def test_causes_fn_adds_independent_terms():
    model = small_rkn()
    gen = torch.Generator().manual_seed(6)
    w = torch.randn(2, 5, 3, generator=gen, dtype=D)
    w_var = 0.1 + torch.rand(2, 5, 3, generator=gen, dtype=D)
    shift = torch.randn(2, 6, generator=gen, dtype=D)
    seen = []

    def causes_fn(t, post):
        seen.append(t)
        z = torch.zeros(2, 3, dtype=D)
        return [FactorizedBelief(shift, z, z, z)]

    base = model.filter(w, w_var)
    out = model.filter(w, w_var, causes_fn=causes_fn)
    assert seen == list(range(5))
    # first prediction differs exactly by the known shift
    torch.testing.assert_close(out.predicted.at(0).mean, base.predicted.at(0).mean + shift)


def test_diagonal_only_never_updates_the_memory_half():
    model = small_rkn(diagonal_only=True)
    perturb_(model.transition, 0.2)
    gen = torch.Generator().manual_seed(7)
    w = torch.randn(2, 10, 3, generator=gen, dtype=D)
    w_var = 0.1 + torch.rand(2, 10, 3, generator=gen, dtype=D)
    out = model.filter(w, w_var)
    assert torch.all(out.prior.cov_side == 0) and torch.all(out.posterior.cov_side == 0)
    assert torch.equal(out.posterior.mean_lower, out.prior.mean_lower)
    assert torch.equal(out.posterior.var_lower, out.prior.var_lower)
    # with the side covariance the same observations do move the memory half
    full = small_rkn()
    full.load_state_dict(model.state_dict())
    out_full = full.filter(w, w_var)
    assert not torch.allclose(out_full.posterior.mean_lower[:, 1:], out_full.prior.mean_lower[:, 1:])


def test_cell_gradcheck():
    """autograd.gradcheck of one update + predict step w.r.t. inputs and a transition parameter."""
    m = 2
    tr = LocallyLinearTransition(m, num_basis=3, bandwidth=1).to(D)
    perturb_(tr, 0.3)
    gen = torch.Generator().manual_seed(8)
    args = (torch.randn(2, m, generator=gen, dtype=D),              # w
            0.2 + torch.rand(2, m, generator=gen, dtype=D),          # w_var
            torch.randn(2, 2 * m, generator=gen, dtype=D),          # prior mean
            0.5 + torch.rand(2, m, generator=gen, dtype=D),          # var_upper
            0.5 + torch.rand(2, m, generator=gen, dtype=D),          # var_lower
            0.1 * torch.rand(2, m, generator=gen, dtype=D),          # cov_side
            tr.basis_12.detach().clone())                            # a basis parameter
    args = tuple(a.requires_grad_() for a in args)

    def cell(w, w_var, mean, su, sl, ss, b12):
        post = factorized_update(FactorizedBelief(mean, su, sl, ss), w, w_var, validate=False)
        params = dict(tr.named_parameters())
        params["basis_12"] = b12
        prior = torch.func.functional_call(tr, params, (post,))
        return prior.mean, prior.var_upper, prior.var_lower, prior.cov_side, post.mean

    assert torch.autograd.gradcheck(cell, args)


def test_filter_bad_inputs():
    model = small_rkn()
    w, v = torch.zeros(2, 4, 3, dtype=D), torch.ones(2, 4, 3, dtype=D)
    with pytest.raises(ValueError, match="w"):
        model.filter(torch.zeros(2, 4, 5, dtype=D), v)
    with pytest.raises(ValueError, match="w_var"):
        model.filter(w, torch.ones(2, 5, 3, dtype=D))
    with pytest.raises(ValueError, match="w_var"):
        model.filter(w, torch.ones(3, 4, 3, dtype=D))
    with pytest.raises(ValueError, match="mask"):
        model.filter(w, v, torch.ones(2, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="init"):
        model.filter(w, v, init="prior")
    with pytest.raises(ValueError, match="obs"):
        model(torch.zeros(2, 4, 7, dtype=D))


# ------------------------------------------------------------------------------ end to end
def test_conv_trunk_and_forward_with_missing_frames():
    torch.manual_seed(0)
    trunk = ConvTrunk((8, 8), channels=(2, 4), feature_dim=6)
    assert trunk(torch.rand(3, 5, 64)).shape == (3, 5, 6)
    enc = ObservationEncoder(64, 3, trunk=trunk, feature_dim=6, normalize_w=True)
    w, w_var = enc(torch.rand(2, 4, 64))
    torch.testing.assert_close(w.norm(dim=-1), torch.ones(2, 4))
    assert torch.all(w_var > 0)
    model = RKN(enc, LocallyLinearTransition(3, 4, 1), BeliefDecoder(3, 2, (8,), (8,)))
    obs = torch.rand(2, 6, 64)
    mask = torch.ones(2, 6, dtype=torch.bool)
    mask[:, 2:4] = False
    obs[~mask] = float("nan")  # whatever a missing frame holds must not matter
    mean, var = model(obs, mask)
    assert mean.shape == (2, 6, 2) and torch.all(var > 0) and torch.isfinite(mean).all()
    gaussian_nll(mean, var, torch.zeros_like(mean)).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_recurrent_filter_baseline():
    torch.manual_seed(0)
    enc = ObservationEncoder(5, 3, hidden=(8,))
    for cell in ("lstm", "gru"):
        f = RecurrentFilter(enc, cell, 6, GaussianHead(6, 2, (8,), (8,)))
        obs = torch.randn(2, 7, 5)
        mask = torch.ones(2, 7, dtype=torch.bool)
        mask[1, 3] = False
        mean, var = f(obs, mask)
        assert mean.shape == (2, 7, 2) and torch.all(var > 0)
        obs2 = obs.clone()
        obs2[1, 3] = 100.0  # a masked frame is never seen
        torch.testing.assert_close(f(obs2, mask)[0], mean)
        obs2[1, 4] = 100.0  # an observed one is
        assert not torch.allclose(f(obs2, mask)[0], mean)
        # parameter budget helper matches PyTorch's count
        h = recurrent_hidden_for_budget(cell, 7, count_parameters(f.rnn))
        assert h == 6


def test_fit_filter_learns_and_keeps_best_validation_epoch():
    """A tiny RKN learns to filter a noisy sine observed through a 4-d random projection."""
    gen = torch.Generator().manual_seed(10)
    n, T = 24, 20
    phase = 2 * math.pi * torch.rand(n, 1, generator=gen)
    t = torch.arange(T) * 0.3
    target = torch.stack([torch.sin(t + phase), torch.cos(t + phase)], -1)
    proj = torch.randn(2, 4, generator=gen)
    obs = target @ proj + 0.1 * torch.randn(n, T, 4, generator=gen)
    data = FilterData(obs, torch.rand(n, T, generator=gen) > 0.2, target)
    torch.manual_seed(0)
    model = RKN(ObservationEncoder(4, 2, hidden=(16,)), LocallyLinearTransition(2, 2, 0),
                BeliefDecoder(2, 2, (16,), (16,)))
    before = evaluate_filter(model, data.subset(slice(16, 24)))
    hist = fit_filter(model, data.subset(slice(0, 16)), data.subset(slice(16, 24)), epochs=15,
                      batch_size=8, lr=1e-2, seed=0, crop=15)
    after = evaluate_filter(model, data.subset(slice(16, 24)))
    assert after["nll"] < before["nll"] - 0.3
    assert after["nll"] == pytest.approx(min(hist.valid_metric), abs=1e-6)
    assert hist.valid_metric[hist.best_epoch] == min(hist.valid_metric)
    with pytest.raises(ValueError, match="crop"):
        fit_filter(model, data, data, epochs=1, crop=T + 1)
    with pytest.raises(ValueError, match="drop_prob"):
        fit_filter(model, data, data, epochs=1, drop_prob=1.0)
    # frame dropout hides frames from the model during training only
    seen_masks = []
    probe = RecurrentFilter(ObservationEncoder(4, 2, hidden=(4,)), "gru", 4, out_dim=2)
    orig_forward = probe.forward
    probe.forward = lambda obs, mask=None: (seen_masks.append(mask.clone()), orig_forward(obs, mask))[1]
    fit_filter(probe, data, data, epochs=1, batch_size=24, drop_prob=0.5, gap_prob=1.0, context_steps=3)
    train_mask = seen_masks[0]
    assert train_mask.float().mean() < 0.5 * data.mask.float().mean()
    assert train_mask[:, -1].sum() == 0  # gap_prob=1: every window loses its tail
    with pytest.raises(ValueError, match="targets"):
        FilterData(obs, data.mask, target[:, :5])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    model = small_rkn(dtype=torch.float32)
    obs = torch.randn(2, 6, 5)
    mask = torch.rand(2, 6) > 0.3
    mean, var = model(obs, mask)
    model_gpu = small_rkn(dtype=torch.float32).cuda()
    model_gpu.load_state_dict(model.state_dict())
    mean_g, var_g = model_gpu(obs.cuda(), mask.cuda())
    torch.testing.assert_close(mean_g.cpu(), mean, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(var_g.cpu(), var, rtol=1e-4, atol=1e-5)


def test_fixed_transition_and_log_variance_decoder():
    gen = torch.Generator().manual_seed(11)
    A = torch.randn(6, 6, generator=gen, dtype=D)
    q = 0.01 + torch.rand(6, generator=gen, dtype=D)
    tr = LocallyLinearTransition.fixed(A, q)
    torch.testing.assert_close(tr.dense_matrix(torch.zeros(6, dtype=D)), A, rtol=0, atol=0)
    torch.testing.assert_close(tr.trans_var, q, rtol=1e-12, atol=1e-12)
    banded = LocallyLinearTransition.fixed(A, q, bandwidth=0)
    Ab = banded.dense_matrix(torch.zeros(6, dtype=D))
    assert torch.equal(Ab[:3, :3], torch.diag(torch.diagonal(A[:3, :3])))
    with pytest.raises(ValueError, match="A"):
        LocallyLinearTransition.fixed(torch.eye(5, dtype=D), q)
    with pytest.raises(ValueError, match="trans_var"):
        LocallyLinearTransition.fixed(A, -q)
    # the log-variance decoder stays finite and positive for beliefs of huge scale
    torch.manual_seed(0)
    dec = BeliefDecoder(3, 2, (8,), (8,), log_var_input=True)
    big = FactorizedBelief(torch.zeros(6), torch.full((3,), 1e12), torch.full((3,), 1e-12), torch.zeros(3))
    mean, var = dec(big)
    assert torch.isfinite(var).all() and torch.all(var > 0)
    # and it reads the correlation, not the raw side covariance
    b1 = FactorizedBelief(torch.zeros(6), torch.full((3,), 4.0), torch.full((3,), 1.0), torch.full((3,), 1.0))
    b2 = FactorizedBelief(torch.zeros(6), torch.full((3,), 4.0), torch.full((3,), 1.0), torch.full((3,), -1.0))
    assert not torch.allclose(dec(b1)[1], dec(b2)[1])



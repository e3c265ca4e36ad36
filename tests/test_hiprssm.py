"""Tests for the hidden-parameter RSSM (Chapter 5).

Oracles: dense Gaussian algebra (pgm_wm.gaussian.marginalize_linear), the dense Kalman filter
with the task as an extra Gaussian cause (pgm_wm.kalman), the ac-RKN itself (reduction when the
task term vanishes), explicit per-window loops, numpy SVD, and properties (context permutation
and padding invariance, no future in any context, causality of the window-by-window inference).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from pgm_wm.acrkn import AcRKN, MLPControl
from pgm_wm.aggregation import BayesianContextEncoder
from pgm_wm.factorized import FactorizedBelief, known_input
from pgm_wm.gaussian import Gaussian, marginalize_linear
from pgm_wm.hiprssm import (
    HiPRSSM,
    LinearTaskTransform,
    NonlinearTaskTransform,
    RecurrentContextEncoder,
)
from pgm_wm.kalman import kalman_filter
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder

from _helpers import linear_acrkn

DT = torch.float64
SETTINGS = settings(max_examples=15, deadline=None)


class FixedTask(nn.Module):
    """A 'context encoder' returning a given task belief for every row (for reductions)."""

    def __init__(self, mean: torch.Tensor, var: torch.Tensor, in_dim: int = 3) -> None:
        super().__init__()
        self.mean, self.var, self.in_dim, self.latent_dim = mean, var, in_dim, mean.shape[-1]

    def forward(self, x, mask=None):
        B = x.shape[0]
        return self.mean.expand(B, -1), self.var.expand(B, -1)


def make_acrkn(m=3, do=3, da=2, seed=0, num_basis=3, bandwidth=1):
    torch.manual_seed(seed)
    return AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, num_basis, bandwidth),
                 MLPControl(da, m, (16,)), BeliefDecoder(m, do, (16,), (16,)),
                 diff_shift=torch.full((do,), 0.1), diff_scale=torch.full((do,), 0.5)).to(DT)


def make_hip(m=3, do=3, da=2, task_dim=4, transform="nonlinear", encoder="ba", seed=0):
    acrkn = make_acrkn(m, do, da, seed)
    F = 2 * do + da
    enc = (BayesianContextEncoder(F, task_dim, (16,)) if encoder == "ba"
           else RecurrentContextEncoder(F, task_dim, (16,)))
    tr = (NonlinearTaskTransform(task_dim, m, (16,)) if transform == "nonlinear"
          else LinearTaskTransform(task_dim, m, init_std=0.5))
    return HiPRSSM(acrkn, enc, tr).to(DT)


def seq_data(n=3, T=24, do=3, da=2, seed=1, p_valid=1.0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, T, do, generator=g, dtype=DT).cumsum(1) * 0.3
    act = torch.randn(n, T, da, generator=g, dtype=DT)
    valid = torch.rand(n, T, generator=g) < p_valid
    return obs, act, valid


def window_batch(B=4, k=6, do=3, da=2, seed=2, p_mask=0.7):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, k, do, generator=g, dtype=DT)
    act = torch.randn(B, k, da, generator=g, dtype=DT)
    mask = torch.rand(B, k, generator=g) < p_mask
    ctx = torch.randn(B, 5, 2 * do + da, generator=g, dtype=DT)
    cmask = torch.rand(B, 5, generator=g) < 0.8
    return obs, act, mask, ctx, cmask


# ================================================================ reduction to the ac-RKN

def test_linear_task_with_zero_mean_and_vanishing_variance_is_the_acrkn():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip(transform="linear")
    ref_mean, ref_var = hip.acrkn(obs, act, mask)
    zeros = torch.zeros(obs.shape[0], 4, dtype=DT)
    # exactly zero task term: identical to the ac-RKN
    mean, var = hip(obs, act, mask, task=(zeros, zeros))
    torch.testing.assert_close(mean, ref_mean, rtol=0, atol=1e-13)
    torch.testing.assert_close(var, ref_var, rtol=0, atol=1e-13)
    # sigma_l -> 0 with C mu_l = 0: the difference vanishes (linearly in sigma_l)
    errs = []
    for s in (1e-1, 1e-3, 1e-5):
        m, v = hip(obs, act, mask, task=(zeros, torch.full_like(zeros, s)))
        errs.append(max(float((v - ref_var).abs().max().detach()), float((m - ref_mean).abs().max().detach())))
    assert errs[0] > errs[1] > errs[2] > 0
    assert errs[2] < 1e-3 * errs[0]


def test_zero_C_gives_the_acrkn_whatever_the_context():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip(transform="linear")
    with torch.no_grad():
        hip.task_transform.C.zero_()
    out, _, _ = hip.filter(obs, act, mask, ctx, cmask)
    ref = hip.acrkn.filter(obs, act, mask)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(out.predicted, f), getattr(ref.predicted, f), rtol=0, atol=0)


def test_nonlinear_task_with_zero_mean_net_and_zero_variance_is_the_acrkn():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip(transform="nonlinear")
    with torch.no_grad():
        last = hip.task_transform.mean_net[-1]
        last.weight.zero_()
        last.bias.zero_()
    zeros = torch.zeros(obs.shape[0], 4, dtype=DT)
    mean, var = hip(obs, act, mask, task=(torch.randn_like(zeros), zeros))
    ref_mean, ref_var = hip.acrkn(obs, act, mask)
    torch.testing.assert_close(mean, ref_mean, rtol=0, atol=1e-13)
    torch.testing.assert_close(var, ref_var, rtol=0, atol=1e-13)


# ================================================================ the task-conditional predict

@SETTINGS
@given(m=st.integers(1, 4), k=st.integers(1, 5), seed=st.integers(0, 10_000))
def test_linear_task_cause_is_the_block_diagonal_of_dense_C_Sigma_Ct(m, k, seed):
    g = torch.Generator().manual_seed(seed)
    tr = LinearTaskTransform(k, m).to(DT)
    with torch.no_grad():
        tr.C.copy_(torch.randn(2 * m, k, generator=g, dtype=DT))
    mu = torch.randn(3, k, generator=g, dtype=DT)
    var = torch.rand(3, k, generator=g, dtype=DT) + 0.01
    cause = tr(mu, var)
    dense = marginalize_linear([(tr.C.detach(), Gaussian(mu, torch.diag_embed(var)))])
    proj = FactorizedBelief.from_dense(dense)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(cause, f), getattr(proj, f), rtol=1e-12, atol=1e-12)


@SETTINGS
@given(m=st.integers(1, 4), k=st.integers(1, 5), seed=st.integers(0, 10_000))
def test_task_conditional_predict_equals_dense_marginalization_of_three_causes(m, k, seed):
    """Eq. (hip-predict): A z + b(a) + C mu_l and A Sigma A^T + C Sigma_l C^T + Q, block diagonals,
    for a diagonal-block transition (where the state part is exact) and a full C."""
    g = torch.Generator().manual_seed(seed)
    trans = LocallyLinearTransition(m, num_basis=1, bandwidth=0).to(DT)
    with torch.no_grad():
        for p in (trans.basis_11, trans.basis_12, trans.basis_21, trans.basis_22):
            p.add_(0.3 * torch.randn(p.shape, generator=g, dtype=DT))
    tr = LinearTaskTransform(k, m).to(DT)
    with torch.no_grad():
        tr.C.copy_(torch.randn(2 * m, k, generator=g, dtype=DT))
    B = 2
    su = torch.rand(B, m, generator=g, dtype=DT) + 0.5
    sl = torch.rand(B, m, generator=g, dtype=DT) + 0.5
    ss = (torch.rand(B, m, generator=g, dtype=DT) - 0.5) * (su * sl).sqrt()
    post = FactorizedBelief(torch.randn(B, 2 * m, generator=g, dtype=DT), su, sl, ss)
    b = torch.randn(B, 2 * m, generator=g, dtype=DT)
    mu_l = torch.randn(B, k, generator=g, dtype=DT)
    var_l = torch.rand(B, k, generator=g, dtype=DT) + 0.1
    prior = trans(post, [known_input(b), tr(mu_l, var_l)])
    A = trans.dense_matrix(post.mean).detach()
    dense = marginalize_linear(
        [(A, post.to_dense()), (tr.C.detach(), Gaussian(mu_l, torch.diag_embed(var_l)))],
        noise_cov=torch.diag(trans.trans_var.detach()), offset=b)
    proj = FactorizedBelief.from_dense(dense)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(prior, f), getattr(proj, f), rtol=1e-10, atol=1e-10)


def test_linear_hiprssm_equals_dense_kalman_filter_with_task_cause():
    """Diagonal transition blocks, identity encoder, linear control and a task matrix C whose
    blocks are diagonal (so C Sigma_l C^T has the factorized structure): the HiP-RSSM filter must be
    the dense Kalman filter with F = A, input [B, C] [a_t; mu_l] and noise Q + C Sigma_l C^T."""
    m, da, B, T = 3, 2, 2, 8
    acrkn = linear_acrkn(m, da, seed=5)
    trans, ctrl, r = acrkn.transition, acrkn.control, acrkn.encoder.var
    tr = LinearTaskTransform(m, m).to(DT)
    with torch.no_grad():
        tr.C.copy_(torch.cat([torch.diag(torch.randn(m, dtype=DT)), torch.diag(torch.randn(m, dtype=DT))]))
    g = torch.Generator().manual_seed(0)
    mu_l = torch.randn(B, m, generator=g, dtype=DT)
    var_l = torch.rand(B, m, generator=g, dtype=DT) + 0.2
    hip = HiPRSSM(acrkn, FixedTask(mu_l[0], var_l[0]), tr)
    y = torch.randn(B, T, m, generator=g, dtype=DT)
    u = torch.randn(B, T, da, generator=g, dtype=DT)
    mask = torch.rand(B, T, generator=g) < 0.6
    out, _, _ = hip.filter(y, u, mask, task=(mu_l, var_l))
    F = trans.dense_matrix(torch.zeros(2 * m, dtype=DT)).detach()
    H = torch.cat([torch.eye(m, dtype=DT), torch.zeros(m, m, dtype=DT)], 1)
    init = Gaussian(torch.zeros(2 * m, dtype=DT), 2.0 * torch.eye(2 * m, dtype=DT))
    C = tr.C.detach()
    for i in range(B):
        Q = torch.diag(trans.trans_var.detach()) + C @ torch.diag(var_l[i]) @ C.T
        u_aug = torch.cat([u[i], mu_l[i].expand(T, m)], -1)
        kf = kalman_filter(y[i], init, F, H, Q, torch.diag(r), mask[i],
                           B=torch.cat([ctrl.B.detach(), C], 1), u=u_aug)
        want_mean = torch.cat([kf.predicted.mean[1:], kf.next_prior.mean[None]])
        want_cov = torch.cat([kf.predicted.cov[1:], kf.next_prior.cov[None]])
        dense = out.predicted.to_dense()
        torch.testing.assert_close(dense.mean[i], want_mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(dense.cov[i], want_cov, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(out.posterior.to_dense().cov[i], kf.filtered.cov, rtol=1e-10, atol=1e-10)


@SETTINGS
@given(k=st.integers(1, 6), seed=st.integers(0, 10_000))
def test_nonlinear_variance_term_is_nonnegative_zero_at_zero_and_monotone(k, seed):
    torch.manual_seed(seed)
    tr = NonlinearTaskTransform(k, 3, (8,), var_hidden=5).to(DT)
    g = torch.Generator().manual_seed(seed)
    v = torch.rand(10, k, generator=g, dtype=DT) * 5
    dv = torch.rand(10, k, generator=g, dtype=DT)
    gv, gv2 = tr.var_term(v), tr.var_term(v + dv)
    assert bool((gv >= 0).all())
    assert bool((gv2 >= gv - 1e-12).all())
    torch.testing.assert_close(tr.var_term(torch.zeros(1, k, dtype=DT)), torch.zeros(1, 6, dtype=DT),
                               rtol=0, atol=1e-15)
    cause = tr(torch.randn(10, k, dtype=DT), v)
    assert torch.equal(cause.cov_side, torch.zeros_like(cause.cov_side))
    torch.testing.assert_close(cause.var, gv)


def test_task_mean_moves_prior_mean_and_task_variance_widens_prior():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip(transform="linear")
    B = obs.shape[0]
    z = torch.zeros(B, 4, dtype=DT)
    out0, _, _ = hip.filter(obs, act, mask, task=(z, z))
    out1, _, _ = hip.filter(obs, act, mask, task=(z, torch.ones_like(z)))
    # step 0: same posterior, prior variance grows by exactly diag(C diag(1) C^T) blocks
    cause = hip.task_cause(z, torch.ones_like(z))
    torch.testing.assert_close(out1.predicted.at(0).var - out0.predicted.at(0).var, cause.var)
    mu = torch.randn(B, 4, dtype=DT)
    out2, _, _ = hip.filter(obs, act, mask, task=(mu, z))
    torch.testing.assert_close(out2.predicted.at(0).mean - out0.predicted.at(0).mean,
                               mu @ hip.task_transform.C.detach().T)


# ================================================================ context encoders

def test_context_permutation_and_padding_do_not_change_predictions():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip()
    mean, var = hip(obs, act, mask, ctx, cmask)
    g = torch.Generator().manual_seed(7)
    for _ in range(3):
        perm = torch.randperm(ctx.shape[1], generator=g)
        m2, v2 = hip(obs, act, mask, ctx[:, perm], cmask[:, perm])
        torch.testing.assert_close(m2, mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(v2, var, rtol=1e-12, atol=1e-12)
    # padded junk (even NaN) changes nothing
    junk = torch.full((ctx.shape[0], 3, ctx.shape[2]), float("nan"), dtype=DT)
    m3, v3 = hip(obs, act, mask, torch.cat([ctx, junk], 1),
                 torch.cat([cmask, torch.zeros(ctx.shape[0], 3, dtype=torch.bool)], 1))
    torch.testing.assert_close(m3, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(v3, var, rtol=1e-12, atol=1e-12)


def test_recurrent_context_encoder_is_order_dependent_and_skips_masked_elements():
    obs, act, mask, ctx, cmask = window_batch()
    enc = RecurrentContextEncoder(ctx.shape[-1], 4, (16,)).to(DT)
    mean, var = enc(ctx, cmask)
    assert mean.shape == (ctx.shape[0], 4) and bool((var > 0).all())
    perm = torch.arange(ctx.shape[1]).flip(0)
    full = torch.ones_like(cmask)
    m1, _ = enc(ctx, full)
    m2, _ = enc(ctx[:, perm], full)
    assert not torch.allclose(m1, m2)  # time order matters for a recurrent encoder
    # a masked element's value is never used
    ctx2 = ctx.clone()
    ctx2[~cmask] = 1e6
    torch.testing.assert_close(enc(ctx2, cmask)[0], mean)
    # an empty set: the initial belief N(0, init_var I) only propagated through the transition
    pm, pv = enc(ctx, torch.zeros_like(cmask))
    torch.testing.assert_close(pm, torch.zeros_like(pm))
    belief = enc.rkn.initial_belief((ctx.shape[0],), ctx)
    for _ in range(ctx.shape[1] - 1):
        belief = enc.rkn.transition(belief)
    torch.testing.assert_close(pv, belief.var)


def test_empty_context_gives_the_task_prior():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip()
    mean, var, t_mean, t_var = hip.predict(obs, act, mask, None)
    torch.testing.assert_close(t_mean, torch.zeros_like(t_mean))
    torch.testing.assert_close(t_var, torch.ones_like(t_var))
    m2, v2, _, _ = hip.predict(obs, act, mask, ctx, torch.zeros_like(cmask))
    torch.testing.assert_close(m2, mean)


def test_more_context_shrinks_the_task_variance():
    obs, act, mask, ctx, cmask = window_batch()
    hip = make_hip()
    few = torch.zeros_like(cmask)
    few[:, :2] = True
    _, v_few = hip.infer_task(ctx, few)
    _, v_all = hip.infer_task(ctx, torch.ones_like(cmask))
    assert bool((v_all < v_few).all())


# ================================================================ windows and inference


# ================================================================ evaluation helpers


# ================================================================ bad inputs

def test_bad_inputs_raise_value_error():
    obs, act, valid = seq_data(2, 12)
    with pytest.raises(ValueError, match="var"):
        LinearTaskTransform(3, 2)(torch.zeros(1, 3), torch.zeros(1, 4))
    with pytest.raises(ValueError, match="latent_dim"):
        RecurrentContextEncoder(5, 3)
    with pytest.raises(ValueError, match="task_transform"):
        HiPRSSM(make_acrkn(m=3), BayesianContextEncoder(8, 4), LinearTaskTransform(4, 2))
    with pytest.raises(ValueError, match="context_encoder"):
        HiPRSSM(make_acrkn(m=3), BayesianContextEncoder(8, 5), LinearTaskTransform(4, 3))
    hip = make_hip()
    o, a, m, ctx, cm = window_batch()
    with pytest.raises(ValueError, match="context_mask"):
        hip(o, a, m, ctx, cm[:, :2])
    with pytest.raises(ValueError, match="task"):
        hip(o, a, m, task=(torch.zeros(4, 4, dtype=DT), -torch.ones(4, 4, dtype=DT)))


# ================================================================ chapter-5 plot helpers (smoke + bad input)

def test_chapter5_plot_helpers():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pgm_wm.plotting import plot_graphical_model, plot_latent_scatter, plot_task_over_time

    fig, axes = plt.subplots(1, 3)
    nodes = {"l": (0.0, 1.0, "$l$", "latent"), "r": (1.0, 1.0, "$r$", "observed"), "a": (0.0, 0.0, "$a$", "known")}
    plot_graphical_model(axes[0], nodes, [("l", "r"), ("a", "r")], plates=[(0.5, 0.5, 1.0, 1.0, "set")])
    with pytest.raises(ValueError, match="nodes"):
        plot_graphical_model(axes[0], {"x": (0, 0, "x", "weird")}, [])
    with pytest.raises(ValueError, match="edges"):
        plot_graphical_model(axes[0], nodes, [("l", "nope")])
    xy, vals = np.random.default_rng(0).normal(size=(10, 2)), np.linspace(0, 1, 10)
    plot_latent_scatter(axes[1], xy, vals, markers=np.array(["a"] * 5 + ["b"] * 5))
    assert sum(len(c.get_offsets()) for c in axes[1].collections) == 10
    with pytest.raises(ValueError, match="values"):
        plot_latent_scatter(axes[1], xy, vals[:3])
    fig2, ax2 = plt.subplots(2, 1)
    plot_task_over_time(ax2, np.arange(4) * 0.5, np.arange(4.0), np.arange(20) * 0.1,
                        np.repeat([0.0, 1.0], 10), latent_std=np.ones(4))
    assert len(ax2[1].lines) >= 2  # truth + one switch marker
    with pytest.raises(ValueError, match="latent"):
        plot_task_over_time(ax2, np.arange(4), np.arange(3.0), np.arange(5), np.zeros(5))
    plt.close("all")

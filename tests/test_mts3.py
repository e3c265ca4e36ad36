"""Tests for pgm_wm.mts3 (and the Transformer baseline of Chapter 6).

Oracles: dense Gaussian algebra (pgm_wm.gaussian.marginalize_linear / condition), sequential
factorized Kalman updates, the ac-RKN of Chapter 4 (pgm_wm.acrkn.AcRKN), the general RKN filter
loop, and properties (causality / no look-ahead, parallel == sequential, gradient cuts).
"""

from __future__ import annotations

import copy

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm_wm.aggregation import bayesian_aggregation
from pgm_wm.acrkn import AcRKN, LocallyLinearControl
from pgm_wm.baselines import TransformerBaseline, alibi_causal_bias
from pgm_wm.beliefs import DiagGaussian
from pgm_wm.factorized import (
    FactorizedBelief,
    diagonal_factorized_filter,
    factorized_predict_from_matrix,
    factorized_update,
)
from pgm_wm.filtering import FilterResult
from pgm_wm.datasets.windows import to_windows
from pgm_wm.gaussian import Gaussian, condition, marginalize_linear
from pgm_wm.mts3 import (
    MTS3,
    BlockMatrix,
    TaskSSM,
    build_fast_acrkn,
    build_hierarchical_mts3,
    build_mts3,
    run_fast_level,
    task_predict,
    time_encoding,
)
from pgm_wm.rkn import LocallyLinearTransition, over_time
from pgm_wm.training import prediction_loss

DT = torch.float64
DO, DA, M = 3, 2, 4


# ----------------------------------------------------------------------------- helpers
def rand_belief(batch, m, gen, scale=1.0):
    su = torch.rand(*batch, m, generator=gen, dtype=DT) + 0.5
    sl = torch.rand(*batch, m, generator=gen, dtype=DT) + 0.5
    ss = (torch.rand(*batch, m, generator=gen, dtype=DT) - 0.5) * 0.8 * torch.sqrt(su * sl)
    mean = scale * torch.randn(*batch, 2 * m, generator=gen, dtype=DT)
    return FactorizedBelief(mean, su, sl, ss)


def diag_blocks(m, gen):
    return tuple(torch.diag(torch.randn(m, generator=gen, dtype=DT)) for _ in range(4))


def dense(blocks):
    b11, b12, b21, b22 = blocks
    return torch.cat([torch.cat([b11, b12], -1), torch.cat([b21, b22], -1)], -2)


def perturb(model, scale=0.1, seed=0):
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            if p.requires_grad:
                p.add_(scale * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    return model


def data(B, T, seed=0):
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, T, DO, generator=gen, dtype=DT)
    act = torch.randn(B, T, DA, generator=gen, dtype=DT)
    mask = torch.rand(B, T, generator=gen, dtype=DT) > 0.3
    return obs, act, mask


def mts3(H=4, **kw):
    with torch.random.fork_rng():
        torch.manual_seed(1)
        return perturb(build_mts3(DO, DA, M, H, hidden=(8,), **kw).to(DT))


def close(a, b, tol=1e-10):
    torch.testing.assert_close(a, b, rtol=tol, atol=tol)


# ----------------------------------------------------------------------------- slow-scale algebra
@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 3))
def test_task_predict_matches_dense_marginalization(seed, m):
    gen = torch.Generator().manual_seed(seed)
    post = rand_belief((2,), m, gen)
    X, Yb = diag_blocks(m, gen), diag_blocks(m, gen)
    Y = dense(Yb)
    S = torch.rand(2 * m, generator=gen, dtype=DT) + 0.1
    a_mean = torch.randn(2, 2 * m, generator=gen, dtype=DT)
    a_var = torch.rand(2, 2 * m, generator=gen, dtype=DT) + 0.2
    got = task_predict(post, X, S, Y, a_mean, a_var)
    alpha = Gaussian(a_mean, torch.diag_embed(a_var))
    want = marginalize_linear([(dense(X), post.to_dense()), (Y, alpha)], noise_cov=torch.diag(S))
    close(got.to_dense().mean, want.mean)
    close(got.to_dense().cov, want.cov)
    # the Y Σ_α Yᵀ term is really there (the authors' code drops it): without it the answer differs
    no_term = marginalize_linear([(dense(X), post.to_dense())], noise_cov=torch.diag(S), offset=a_mean @ Y.T)
    assert (got.to_dense().cov - no_term.cov).abs().max() > 1e-3
    close(got.to_dense().cov - no_term.cov, Y @ torch.diag_embed(a_var) @ Y.T)


def test_task_predict_band_blocks_keep_exact_block_diagonals():
    gen = torch.Generator().manual_seed(3)
    m = 4
    post = rand_belief((3,), m, gen)
    band = LocallyLinearTransition(m, num_basis=1, bandwidth=1, add_identity=False).to(DT)
    perturb(band)
    X = band.blocks(post.mean)
    S = band.trans_var.detach()
    Y = torch.randn(2 * m, 2 * m, generator=gen, dtype=DT)
    a_mean, a_var = torch.randn(3, 2 * m, dtype=DT), torch.rand(3, 2 * m, dtype=DT) + 0.1
    got = task_predict(post, X, S, Y, a_mean, a_var)
    want = marginalize_linear([(dense(X), post.to_dense()), (Y, Gaussian(a_mean, torch.diag_embed(a_var)))],
                              noise_cov=torch.diag(S))
    proj = FactorizedBelief.from_dense(want)
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        close(getattr(got, f), getattr(proj, f))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 6))
def test_task_update_equals_sequential_and_dense_conditioning(seed, n):
    gen = torch.Generator().manual_seed(seed)
    m = 3
    slow = TaskSSM(DO, DA, m, n, hidden=(4,)).to(DT)
    prior = rand_belief((2,), m, gen)
    beta = torch.randn(2, n, m, generator=gen, dtype=DT)
    nu = torch.rand(2, n, m, generator=gen, dtype=DT) + 0.1
    mask = torch.rand(2, n, generator=gen) > 0.3
    got = slow.update(prior, beta, nu, mask)
    for b in range(2):
        seq = FactorizedBelief(*(getattr(prior, f)[b] for f in ("mean", "var_upper", "var_lower", "cov_side")))
        order = torch.randperm(n, generator=gen)
        dense_b = seq.to_dense()
        H = torch.cat([torch.eye(m, dtype=DT), torch.zeros(m, m, dtype=DT)], -1)
        for i in order.tolist():
            if mask[b, i]:
                seq = factorized_update(seq, beta[b, i], nu[b, i])
                dense_b = condition(dense_b, H, torch.diag(nu[b, i]), beta[b, i])
        for f in ("mean", "var_upper", "var_lower", "cov_side"):
            close(getattr(got, f)[b], getattr(seq, f))
        close(got.to_dense().cov[b], dense_b.cov)
        close(got.mean[b], dense_b.mean)


def test_abstract_action_is_bayesian_aggregation_with_time_encoding():
    torch.manual_seed(0)
    H = 5
    slow = TaskSSM(DO, DA, M, H, hidden=(8,)).to(DT)
    acts = torch.randn(2, 3, H, DA, dtype=DT)
    present = torch.ones(2, 3, H, dtype=torch.bool)
    present[1, 2, 3:] = False
    mean, var = slow.encode_actions(acts, present)
    x = torch.cat([acts, time_encoding(H, acts).expand(2, 3, H, 1)], -1)
    r, r_var = slow.action_encoder.encode(x)
    want_mean, want_var = bayesian_aggregation(r, r_var, present, 0.0, 1.0)
    close(mean, want_mean)
    close(var, want_var)
    # padded steps do not matter
    acts2 = acts.clone()
    acts2[1, 2, 3:] = 100.0
    mean2, _ = slow.encode_actions(acts2, present)
    close(mean2, mean)


# ----------------------------------------------------------------------------- fast-scale algebra
def test_fast_step_with_task_cause_matches_dense():
    """One fast step of Eq. (mts3-fast-predict) on the diagonal fast path: update, then predict
    with the control term and the task cause C l as independent causes = dense Gaussian algebra."""
    gen = torch.Generator().manual_seed(5)
    m, B = 3, 2
    init = rand_belief((B,), m, gen)
    A = diag_blocks(m, gen)
    C = BlockMatrix(m).to(DT)
    with torch.no_grad():
        for p, blk in zip((C.basis_11, C.basis_12, C.basis_21, C.basis_22), diag_blocks(m, gen)):
            p.copy_(blk[None])
    q = torch.rand(2 * m, generator=gen, dtype=DT) + 0.05
    task_belief = rand_belief((B,), m, gen)
    b = torch.randn(B, 1, 2 * m, generator=gen, dtype=DT)
    w = torch.randn(B, 1, m, generator=gen, dtype=DT)
    w_var = torch.rand(B, 1, m, generator=gen, dtype=DT) + 0.1
    mask = torch.tensor([[True], [False]])
    inputs = FactorizedBelief.known(b) + over_time(C.cause(task_belief), 1)
    out = diagonal_factorized_filter(init, dense(A), q, DiagGaussian(w, w_var), mask, inputs)
    H = torch.cat([torch.eye(m, dtype=DT), torch.zeros(m, m, dtype=DT)], -1)
    for i in range(B):
        prior = Gaussian(init.mean[i], init.to_dense().cov[i])
        post = condition(prior, H, torch.diag(w_var[i, 0]), w[i, 0]) if mask[i, 0] else prior
        l_dense = Gaussian(task_belief.mean[i], task_belief.to_dense().cov[i])
        nxt = marginalize_linear([(dense(A), post), (C.dense().detach(), l_dense)], noise_cov=torch.diag(q),
                                 offset=b[i, 0])
        close(out.posterior.to_dense().mean[i, 0], post.mean)
        close(out.posterior.to_dense().cov[i, 0], post.cov)
        close(out.next_prior.to_dense().mean[i, 0].detach(), nxt.mean)
        close(out.next_prior.to_dense().cov[i, 0].detach(), nxt.cov)  # C Σ_l Cᵀ included


def reference_mts3(model, obs, act, mask):
    """Explicit-loop reference of an N-level MTS3 (T a multiple of the top window, no padding):
    the task levels are computed level by level from the top down (each window's prior reads the
    prior of the enclosing window of the level above), then the fast level step by step with
    factorized_update / factorized_predict_from_matrix and the causes [b(a_t), C l_k(t)]."""
    B, T = mask.shape
    obs0 = torch.where(mask[..., None], obs, torch.zeros((), dtype=obs.dtype))
    levels = list(model.levels)
    priors = [None] * len(levels)
    posts = [None] * len(levels)
    for i in reversed(range(len(levels))):
        lev, H = levels[i], levels[i].window
        beta = lev.encode_observations(to_windows(obs0, H))
        alpha = lev.encode_actions(to_windows(act, H), torch.ones(B, T // H, H, dtype=torch.bool))
        observed = to_windows(mask, H)
        post, pr, po = lev.initial_belief((B,), obs), [], []
        for k in range(T // H):
            above = None if i == len(levels) - 1 else priors[i + 1][k * H // levels[i + 1].window]
            prior = lev.predict(post, None if alpha is None else alpha[:, k], above)
            post = lev.update(prior, beta[:, k], mask=observed[:, k])
            pr.append(prior)
            po.append(post)
        priors[i], posts[i] = pr, po
    fast = model.fast
    w = DiagGaussian(*fast.encoder(obs0))
    b = fast.control(act, torch.zeros(B, T, 2 * M, dtype=obs.dtype))
    tr = fast.transition
    prior = fast.rkn.initial_belief((B,), obs)
    out = {"prior": [], "posterior": [], "next_prior": []}
    for t in range(T):
        post = factorized_update(prior, w.at(t), mask[:, t], validate=False)
        causes = [FactorizedBelief.known(b[:, t])]
        if levels:
            causes.append(model.task_matrix.cause(priors[0][t // levels[0].window]))
        nxt = factorized_predict_from_matrix(post, tr.dense_matrix(post.mean), tr.trans_var, causes, validate=False)
        for k_, v in (("prior", prior), ("posterior", post), ("next_prior", nxt)):
            out[k_].append(v)
        prior = nxt
    res = FilterResult(*(FactorizedBelief.stack(out[k_]) for k_ in ("prior", "posterior", "next_prior")))
    mean, var = fast.decode_predictions(res, obs, mask)
    return mean, var, [FactorizedBelief.stack(p) for p in priors], [FactorizedBelief.stack(p) for p in posts]


# ----------------------------------------------------------------------------- reductions
@pytest.mark.parametrize("windows", [[4], [2, 4], [2, 4, 8]])
def test_mts3_equals_the_explicit_loop_reference(windows):
    """One task level (the 2-level model of the thesis) and two or three task levels."""
    torch.manual_seed(0)
    model = perturb(build_hierarchical_mts3(DO, DA, M, windows, hidden=(8,)).to(DT))
    obs, act, mask = data(2, 16)
    out = model.run(obs, act, mask)
    mean, var, priors, posts = reference_mts3(model, obs, act, mask)
    close(out.mean, mean)
    close(out.var, var)
    for i in range(len(windows)):
        for got, want in ((out.task_priors[i], priors[i]), (out.task_posteriors[i], posts[i])):
            for x, y in zip(got._tensors(), want._tensors()):
                close(x, y)


def test_dropping_the_window_task_cause_gives_the_acrkn():
    """MTS3 fast level = ac-RKN + [window task cause]: its causes minus the last one filter to
    the ac-RKN's beliefs exactly, across window boundaries."""
    model = mts3(H=4)
    obs, act, mask = data(2, 16)
    out = model.run(obs, act, mask)
    causes = model.causes(act, out.task_prior)
    assert len(causes) == len(model.fast.causes(act)) + 1
    w = model.fast.encode(obs, mask)
    dropped = run_fast_level(model.fast, w, mask, causes[:-1], 4)
    ref = model.fast.filter(obs, act, mask)
    for name in ("prior", "posterior", "next_prior"):
        for x, y in zip(getattr(dropped, name)._tensors(), getattr(ref, name)._tensors()):
            close(x, y, 1e-12)
    assert not torch.allclose(out.fast.next_prior.mean, ref.next_prior.mean)


# ----------------------------------------------------------------------------- reductions
def test_one_level_mts3_is_the_acrkn():
    torch.manual_seed(0)
    fast = perturb(build_fast_acrkn(DO, DA, M, (8,)).to(DT))
    one = MTS3(fast, [])
    obs, act, mask = data(3, 17)
    got, want = one(obs, act, mask), fast(obs, act, mask)
    close(got[0], want[0])
    close(got[1], want[1])


def test_zero_task_matrix_gives_the_acrkn_across_windows():
    """With C = 0 the slow level has no effect and the fast belief must run on across windows:
    the prior of the first step of window k is the prior after the last step of window k-1."""
    model = mts3(H=4)
    with torch.no_grad():
        for p in model.task_matrix.parameters():
            p.zero_()
    obs, act, mask = data(2, 14)
    got = model(obs, act, mask)
    want = model.fast(obs, act, mask)
    close(got[0], want[0])
    close(got[1], want[1])  # one variance floor (the fast readout's), not two stacked


def test_three_levels_shapes_and_windows():
    torch.manual_seed(0)
    model = perturb(build_hierarchical_mts3(DO, DA, M, [3, 6], hidden=(8,)).to(DT))
    obs, act, mask = data(2, 17)
    out = model.run(obs, act, mask)
    assert out.mean.shape == (2, 17, DO)
    assert out.task_priors[0].mean.shape == (2, 6, 2 * M)  # 18 padded steps / 3
    assert out.task_priors[1].mean.shape == (2, 3, 2 * M)
    assert torch.isfinite(out.mean).all() and (out.var > 0).all()


# ----------------------------------------------------------------------------- no look-ahead
@pytest.mark.parametrize("kind", ["mts3", "hier3"])
def test_no_lookahead_inside_a_window(kind):
    """Changing observation s changes no prediction before s. In particular the fast scale of window
    k does not see window k's later observations: it is conditioned on the task PRIOR."""
    if kind == "mts3":
        model = mts3(H=5)
    else:
        torch.manual_seed(0)
        model = perturb(build_hierarchical_mts3(DO, DA, M, [5, 10], hidden=(8,)).to(DT))
    obs, act, _ = data(2, 20)
    mask = torch.ones(2, 20, dtype=torch.bool)
    base = model.run(obs, act, mask)
    for s in (6, 8, 9, 13):
        obs2 = obs.clone()
        obs2[:, s] += 3.0
        out = model.run(obs2, act, mask)
        close(out.mean[:, :s], base.mean[:, :s])
        close(out.var[:, :s], base.var[:, :s])
        assert (out.mean[:, s:] - base.mean[:, s:]).abs().max() > 1e-6
        if kind == "mts3":
            k = s // 5
            close(out.task_prior.mean[:, : k + 1], base.task_prior.mean[:, : k + 1])  # prior of window k
            assert (out.task_posterior.mean[:, k] - base.task_posterior.mean[:, k]).abs().max() > 1e-6


def test_task_prior_uses_only_earlier_windows():
    model = mts3(H=4)
    obs, act, mask = data(2, 16)
    base = model.run(obs, act, mask)
    obs2 = obs.clone()
    obs2[:, 8:12] += 2.0  # window 2
    out = model.run(obs2, act, torch.ones_like(mask))
    base = model.run(obs, act, torch.ones_like(mask))
    close(out.task_prior.mean[:, :3], base.task_prior.mean[:, :3])
    close(out.task_prior.var_upper[:, :3], base.task_prior.var_upper[:, :3])
    assert (out.task_prior.mean[:, 3] - base.task_prior.mean[:, 3]).abs().max() > 1e-6


# ----------------------------------------------------------------------------- windows & gradients
def test_parallel_windows_equal_sequential_values_and_gradients():
    a = mts3(H=4)
    b = copy.deepcopy(a)
    b.parallel_windows = False
    obs, act, mask = data(3, 15)
    ga = prediction_loss(a, obs, act, mask)
    gb = prediction_loss(b, obs, act, mask)
    close(ga, gb)
    ga.backward()
    gb.backward()
    for (n, pa), pb in zip(a.named_parameters(), b.parameters()):
        if pa.grad is not None:
            close(pa.grad, pb.grad, 1e-9)


def test_fast_gradients_are_cut_between_windows_but_flow_through_the_slow_scale():
    obs, act, mask = data(2, 12)
    for C_zero, detach, expect_zero in ((True, True, True), (True, False, False), (False, True, False)):
        model = mts3(H=4)
        model.detach_fast = detach
        if C_zero:
            with torch.no_grad():
                for p in model.task_matrix.parameters():
                    p.zero_()
        x = obs.clone().requires_grad_(True)
        mean, var = model(x, act, torch.ones_like(mask))
        (mean[:, 8:].sum() + var[:, 8:].sum()).backward()  # outputs of window 2
        g = x.grad[:, :4].abs().max()  # w.r.t. observations of window 0
        assert (g == 0) if expect_zero else (g > 0), (C_zero, detach, float(g))


def test_partial_last_window_and_batch_of_one():
    model = mts3(H=5)
    obs, act, mask = data(2, 25)
    full = model(obs, act, mask)
    part = model(obs[:, :23], act[:, :23], mask[:, :23])
    close(part[0][:, :20], full[0][:, :20])  # the first four windows are unaffected
    assert part[0].shape == (2, 23, DO)
    one = model(obs[:1], act[:1], mask[:1])  # batch of one (the authors' aggregation breaks here)
    close(one[0], full[0][:1])


def test_diagonal_ablation_keeps_the_covariance_diagonal():
    torch.manual_seed(0)
    model = perturb(build_mts3(DO, DA, M, 4, hidden=(8,), decoupled=True).to(DT))
    obs, act, mask = data(2, 12)
    out = model.run(obs, act, mask)
    assert out.fast.next_prior.cov_side.abs().max() == 0
    assert out.task_posterior.cov_side.abs().max() == 0
    assert not model.fast.transition.basis_12.requires_grad


def test_no_action_ablation_has_no_abstract_action():
    model = mts3(H=4, use_actions=False)
    obs, act, mask = data(2, 12)
    out = model.run(obs, act, mask)
    assert out.alpha_mean is None and model.slow.action_matrix is None
    assert torch.isfinite(out.mean).all()


def test_open_loop_predictions_stay_bounded_at_initialization():
    torch.manual_seed(0)
    model = build_mts3(4, 2, 8, 25)
    T = 1000
    obs, act = torch.randn(2, T, 4), torch.randn(2, T, 2)
    mask = torch.zeros(2, T, dtype=torch.bool)
    mask[:, :50] = True
    with torch.no_grad():
        out = model.run(obs, act, mask)
    assert torch.isfinite(out.mean).all() and out.mean.abs().max() < 10
    assert out.fast.next_prior.var_upper.max() < 100 and out.task_prior.var_upper.max() < 100


# ----------------------------------------------------------------------------- masks and losses


# ----------------------------------------------------------------------------- input checks
def test_invalid_inputs_raise_naming_the_argument():
    model = mts3(H=4)
    obs, act, mask = data(2, 8)
    with pytest.raises(ValueError, match="obs"):
        model(obs[..., :2], act, mask)
    with pytest.raises(ValueError, match="mask"):
        model(obs, act, mask[:, :5])
    with pytest.raises(ValueError, match="actions"):
        model(obs, act[:, :5], mask)
    with pytest.raises(ValueError, match="init"):
        BlockMatrix(3, init=(1.0, 2.0))
    with pytest.raises(ValueError, match="latent_dim"):
        TaskSSM(DO, DA, 0, 4)
    fast = build_fast_acrkn(DO, DA, M)
    top = TaskSSM(DO, DA, M, 8)
    low = TaskSSM(DO, DA, M, 4)  # not conditioned
    with pytest.raises(ValueError, match="levels"):
        MTS3(fast, [low, top], BlockMatrix(M))
    with pytest.raises(ValueError, match="levels"):
        MTS3(fast, [TaskSSM(DO, DA, M, 3, conditioned=True), TaskSSM(DO, DA, M, 8)], BlockMatrix(M))
    with pytest.raises(ValueError, match="task_matrix"):
        MTS3(fast, [top])
    with pytest.raises(ValueError, match="^levels"):
        MTS3(fast, TaskSSM(DO, DA, M, 4, conditioned=True), BlockMatrix(M))
    with pytest.raises(ValueError, match="task_matrix"):
        MTS3(fast, TaskSSM(DO, DA, M, 4), BlockMatrix(M + 1))
    with pytest.raises(ValueError, match="above"):
        top.predict(top.initial_belief((2,), obs.float()), None, top.initial_belief((2,), obs.float()))
    w = fast.encode(obs.float(), mask)
    with pytest.raises(ValueError, match="^causes"):
        run_fast_level(fast, w, mask, [fast.initial_belief((2,), obs.float())], 4)
    with pytest.raises(ValueError, match="^fast"):
        MTS3(fast.encoder, [])
    with pytest.raises(ValueError, match="^fast"):
        MTS3(AcRKN(fast.encoder, fast.transition, LocallyLinearControl(DA, M), fast.decoder), [])
    with pytest.raises(ValueError, match="^obs: need at least one time step"):
        build_mts3(DO, DA, M, 4)(obs[:, :0].float(), act[:, :0].float())


# ----------------------------------------------------------------------------- Transformer baseline
def test_transformer_baseline_is_causal_and_respects_the_mask():
    torch.manual_seed(0)
    model = TransformerBaseline(DO, DA, d_model=8, n_heads=2, n_layers=1, dim_feedforward=16, head_hidden=(8,))
    obs, act = torch.randn(2, 12, DO), torch.randn(2, 12, DA)
    mask = torch.ones(2, 12, dtype=torch.bool)
    mask[:, 6:] = False
    mean, var = model(obs, act, mask)
    assert mean.shape == (2, 12, DO) and (var > 0).all()
    model.eval()
    with torch.no_grad():  # inference mode runs the same computation (no "fast path" surprises)
        close(model(obs, act, mask)[0], mean.detach(), 1e-6)
    obs2 = obs.clone()
    obs2[:, 7:] = 100.0  # hidden observations cannot matter
    close(model(obs2, act, mask)[0], mean, 1e-6)
    act2 = act.clone()
    act2[:, 9] += 1.0  # a later action changes nothing before it
    m2 = model(obs, act2, mask)[0]
    close(m2[:, :9], mean[:, :9], 1e-6)
    assert (m2[:, 9:] - mean[:, 9:]).abs().max() > 1e-6
    bias = alibi_causal_bias(4, 2, obs)
    assert torch.isinf(bias[:, 0, 1:]).all() and (bias[0].diagonal() == 0).all()
    with pytest.raises(ValueError, match="d_model"):
        TransformerBaseline(DO, DA, d_model=7, n_heads=2)


def test_band_blocks_general_path_parallel_equals_sequential_and_is_causal():
    a = mts3(H=4, bandwidth=1)
    b = copy.deepcopy(a)
    b.parallel_windows = False
    obs, act, mask = data(2, 12)
    close(prediction_loss(a, obs, act, mask), prediction_loss(b, obs, act, mask))
    obs2 = obs.clone()
    obs2[:, 6] += 2.0
    with torch.no_grad():
        m1, m2 = a(obs, act, torch.ones_like(mask))[0], a(obs2, act, torch.ones_like(mask))[0]
    close(m1[:, :6], m2[:, :6])




@pytest.mark.parametrize("use_actions", [True, False])
def test_slow_level_as_one_filter_run_equals_the_window_loop(monkeypatch, use_actions):
    """The slow level filtered by one run of the diagonal factorized filter (each window's set
    update as one update with the summed precision, ``slow_level_filter``) gives the window loop's
    task beliefs, predictions and gradients: with a window without any observation, a partial
    last window (padding) and without abstract actions."""
    from pgm_wm.mts3 import TaskSSM

    torch.manual_seed(3)
    a = perturb(build_mts3(DO, DA, M, 4, hidden=(8,), use_actions=use_actions).to(DT))
    b = copy.deepcopy(a)
    obs, act, mask = data(3, 15)
    mask[1, 4:8] = False                                     # window 2 of sequence 1: no observation
    assert a.slow.filters_as_one_run
    out_a = a.run(obs, act, mask)
    loss_a = prediction_loss(a, obs, act, mask)
    monkeypatch.setattr(TaskSSM, "filters_as_one_run", property(lambda self: False))
    out_b = b.run(obs, act, mask)
    loss_b = prediction_loss(b, obs, act, mask)
    close(out_a.mean, out_b.mean)
    close(out_a.var, out_b.var)
    for got, want in ((out_a.task_prior, out_b.task_prior), (out_a.task_posterior, out_b.task_posterior)):
        for x, y in zip(got._tensors(), want._tensors()):
            close(x, y)
    loss_a.backward()
    loss_b.backward()
    for (name, pa), pb in zip(a.named_parameters(), b.parameters()):
        assert (pa.grad is None) == (pb.grad is None), name
        if pa.grad is not None:
            close(pa.grad, pb.grad, 1e-9)

"""Fuzz suite, Chapters 2–3 (issue 13): factorized beliefs, Bayesian aggregation, set encoders
and metrics. Valid random inputs give finite results with positive variances (and positive
definite 2×2 blocks); invalid ones raise a ValueError starting with the argument's name."""

from __future__ import annotations

import torch
from hypothesis import given
from hypothesis import strategies as st

from _fuzz import FUZZ, corrupt, dtypes, finite, gen, pos, raises_named, randn, seeds
from pgm_wm.aggregation import (BayesianContextEncoder, MaxPoolContextEncoder, MeanPoolContextEncoder,
                                bayesian_aggregation, set_update)
from pgm_wm.beliefs import DiagGaussian, FactorizedBelief
from pgm_wm.factorized import (block_inverse, diagonal_factorized_filter, factorized_filter, factorized_predict,
                               factorized_update, linear_cause)
from pgm_wm.metrics import gaussian_nll, rmse, sliding_window_nll, sliding_window_rmse

BAD = ["nan", "inf", "float16", "bfloat16", "mixed", "int"]


def belief(g, batch, m, dtype):
    su, sl = pos(g, *batch, m, dtype=dtype), pos(g, *batch, m, dtype=dtype)
    ss = (torch.rand(*batch, m, generator=g, dtype=torch.float64).to(dtype) * 1.8 - 0.9) * (su * sl).sqrt()
    return FactorizedBelief(randn(g, *batch, 2 * m, dtype=dtype), su, sl, ss)


def blocks_ok(b: FactorizedBelief) -> bool:
    return bool((b.var_upper > 0).all() and (b.var_lower > 0).all()
                and (b.var_upper * b.var_lower - b.cov_side ** 2 >= -1e-5 * b.var_upper * b.var_lower).all())


def diag_A(g, m, dtype):
    return torch.cat([torch.cat([torch.diag(0.9 * torch.rand(m, generator=g, dtype=torch.float64)),
                                 torch.diag(0.1 * torch.rand(m, generator=g, dtype=torch.float64))], 1),
                      torch.cat([torch.diag(-0.1 * torch.rand(m, generator=g, dtype=torch.float64)),
                                 torch.diag(0.9 * torch.rand(m, generator=g, dtype=torch.float64))], 1)], 0).to(dtype)


@FUZZ
@given(seeds, st.integers(1, 4), st.integers(1, 6), dtypes, st.sampled_from([1e-6, 1.0, 1e4]))
def test_factorized_valid_inputs(seed, m, T, dtype, obs_scale):
    g = gen(seed)
    prior = belief(g, (2,), m, dtype)
    obs = DiagGaussian(randn(g, 2, m, dtype=dtype), obs_scale * pos(g, 2, m, dtype=dtype))
    post = factorized_update(prior, obs, torch.tensor([True, False]))
    assert finite(post.mean, post.var) and blocks_ok(post)
    A = diag_A(g, m, dtype)
    nxt = factorized_predict(post, A[:m, :m], A[:m, m:], A[m:, :m], A[m:, m:], pos(g, 2 * m, dtype=dtype),
                             causes=[linear_cause(randn(g, 2 * m, 3, dtype=dtype),
                                                  DiagGaussian(randn(g, 3, dtype=dtype), pos(g, 3, dtype=dtype)))])
    assert finite(nxt.mean, nxt.var) and blocks_ok(nxt)
    iu, il, is_ = block_inverse(post.var_upper, post.var_lower, post.cov_side)
    assert finite(iu, il, is_) and bool((iu > 0).all())
    seq = DiagGaussian(randn(g, 2, T, m, dtype=dtype), obs_scale * pos(g, 2, T, m, dtype=dtype))
    mask = torch.rand(2, T, generator=g) < 0.6
    for f in (factorized_filter, diagonal_factorized_filter):
        res = f(prior, A, pos(g, 2 * m, dtype=dtype), seq, mask)
        for b in (res.prior, res.posterior, res.next_prior):
            assert finite(b.mean, b.var) and blocks_ok(b)


UPDATE_ARGS = ["prior.mean", "prior.var_upper", "prior.var_lower", "prior.cov_side", "observation.mean",
               "observation.var"]


@FUZZ
@given(seeds, st.integers(1, 3), dtypes, st.sampled_from(UPDATE_ARGS), st.sampled_from(BAD))
def test_factorized_update_invalid(seed, m, dtype, arg, kind):
    g = gen(seed)
    p = belief(g, (2,), m, dtype)
    v = {"prior.mean": p.mean, "prior.var_upper": p.var_upper, "prior.var_lower": p.var_lower,
         "prior.cov_side": p.cov_side, "observation.mean": randn(g, 2, m, dtype=dtype),
         "observation.var": pos(g, 2, m, dtype=dtype)}
    v[arg] = corrupt(v[arg], kind)
    names = tuple(UPDATE_ARGS) if kind == "mixed" else (arg,)
    if kind == "int":  # the belief's constructor rejects it, naming the field
        names += (arg.split(".")[-1], "mean", "var")

    def run():
        prior = FactorizedBelief(v["prior.mean"], v["prior.var_upper"], v["prior.var_lower"], v["prior.cov_side"])
        return factorized_update(prior, DiagGaussian(v["observation.mean"], v["observation.var"]))
    raises_named(names, run)


@FUZZ
@given(seeds, st.integers(1, 3), dtypes)
def test_factorized_invalid_values_and_shapes(seed, m, dtype):
    g = gen(seed)
    p = belief(g, (2,), m, dtype)
    obs = DiagGaussian(randn(g, 2, m, dtype=dtype), pos(g, 2, m, dtype=dtype))
    neg = FactorizedBelief(p.mean, -p.var_upper, p.var_lower, p.cov_side)
    raises_named("prior.var_upper", lambda: factorized_update(neg, obs))
    raises_named("observation.var", lambda: factorized_update(p, DiagGaussian(obs.mean, torch.zeros_like(obs.var))))
    raises_named("observation", lambda: factorized_update(p, DiagGaussian(randn(g, 3, m, dtype=dtype),
                                                                          pos(g, 3, m, dtype=dtype))))
    raises_named("mask", lambda: factorized_update(p, obs, torch.tensor([True, False, True])))
    A = diag_A(g, m, dtype)
    q = pos(g, 2 * m, dtype=dtype)
    for kind in BAD[2:]:
        raises_named(("A11", "A12", "A21", "A22", "trans_var", "prior.mean"),
                     lambda: factorized_predict(p, corrupt(A[:m, :m], kind), A[:m, m:], A[m:, :m], A[m:, m:], q))
    raises_named("trans_var", lambda: factorized_predict(p, A[:m, :m], A[:m, m:], A[m:, :m], A[m:, m:], -q))
    raises_named("A11", lambda: factorized_predict(p, A[:m + 1, :m + 1], A[:m, m:], A[m:, :m], A[m:, m:], q))
    seq = DiagGaussian(randn(g, 2, 0, m, dtype=dtype), pos(g, 2, 0, m, dtype=dtype))
    for f in (factorized_filter, diagonal_factorized_filter):
        raises_named("observation", lambda: f(p, A, q, seq))
        raises_named(("A", "prior.mean"), lambda: f(p, A.to(torch.float16), q, DiagGaussian(obs.mean[:, None],
                                                                                        obs.var[:, None])))
    raises_named("side", lambda: block_inverse(p.var_upper, p.var_lower, 10 * (p.var_upper + p.var_lower)))


@FUZZ
@given(seeds, st.integers(1, 4), st.integers(1, 5), dtypes, st.sampled_from([1e-6, 1.0, 1e6]))
def test_aggregation_and_encoders_valid(seed, d, N, dtype, scale):
    g = gen(seed)
    r, r_var = randn(g, 2, N, d, dtype=dtype), scale * pos(g, 2, N, d, dtype=dtype)
    mask = torch.rand(2, N, generator=g) < 0.6
    r_pad = r.masked_fill(~mask[..., None], float("nan"))
    post = bayesian_aggregation(r_pad, r_var, mask)
    assert finite(post.mean, post.var) and bool((post.var > 0).all())
    prior = belief(g, (2,), d, dtype)
    fb = set_update(prior, DiagGaussian(r_pad, r_var), mask)
    assert finite(fb.mean, fb.var) and blocks_ok(fb)
    x = randn(g, 2, N, 3, dtype=torch.float32).masked_fill(~mask[..., None], float("nan"))
    torch.manual_seed(seed % 1000)
    for enc in (BayesianContextEncoder(3, d, (8,)), MeanPoolContextEncoder(3, d, (8,), head_hidden=(8,)),
                MaxPoolContextEncoder(3, d, (8,), head_hidden=(8,))):
        out = enc(x, mask)
        assert finite(out.mean, out.var) and bool((out.var > 0).all())


@FUZZ
@given(seeds, st.integers(1, 3), st.integers(1, 4), dtypes, st.sampled_from(["r", "r_var", "prior_mean", "prior_var"]),
       st.sampled_from(BAD))
def test_aggregation_invalid(seed, d, N, dtype, arg, kind):
    g = gen(seed)
    v = dict(r=randn(g, 2, N, d, dtype=dtype), r_var=pos(g, 2, N, d, dtype=dtype), prior_mean=randn(g, d, dtype=dtype),
             prior_var=pos(g, d, dtype=dtype))
    v[arg] = corrupt(v[arg], kind)
    names = ("r", "r_var", "prior_mean", "prior_var") if kind == "mixed" else (arg,)
    raises_named(names, lambda: bayesian_aggregation(v["r"], v["r_var"], None, v["prior_mean"], v["prior_var"]))
    raises_named("r_var", lambda: bayesian_aggregation(v["r"], -v["r_var"].abs() if v["r_var"].is_floating_point()
                                                       else v["r_var"]) if arg == "r" and kind in ("nan", "inf")
                 else bayesian_aggregation(randn(g, 2, N, d, dtype=dtype), torch.zeros(2, N, d, dtype=dtype)))
    prior = DiagGaussian(randn(g, 2, d, dtype=dtype), pos(g, 2, d, dtype=dtype))
    obs = DiagGaussian(v["r"], v["r_var"]) if arg in ("r", "r_var") else \
        DiagGaussian(randn(g, 2, N, d, dtype=dtype), pos(g, 2, N, d, dtype=dtype))
    if arg in ("r", "r_var"):
        raises_named(("r", "r_var", "observation", "prior"), lambda: set_update(prior, obs))
    raises_named("mask", lambda: set_update(prior, obs, torch.ones(2, N + 1, dtype=torch.bool)))


@FUZZ
@given(seeds, st.integers(1, 3), st.integers(2, 9), dtypes)
def test_metrics_valid(seed, d, T, dtype):
    g = gen(seed)
    pred, target, var = randn(g, 2, T, d, dtype=dtype), randn(g, 2, T, d, dtype=dtype), pos(g, 2, T, d, dtype=dtype)
    mask = torch.ones(2, T, dtype=torch.bool)
    mask[:, 1:] = torch.rand(2, T - 1, generator=g) < 0.5
    assert finite(rmse(pred, target, mask), gaussian_nll(pred, var, target, mask))
    w = max(1, T // 2)
    assert finite(sliding_window_rmse(pred, target, w), sliding_window_nll(pred, var, target, w))


@FUZZ
@given(seeds, st.integers(1, 3), st.integers(2, 6), dtypes, st.sampled_from(["pred", "target", "var"]),
       st.sampled_from(BAD + ["shape"]))
def test_metrics_invalid(seed, d, T, dtype, arg, kind):
    g = gen(seed)
    v = dict(pred=randn(g, 2, T, d, dtype=dtype), target=randn(g, 2, T, d, dtype=dtype), var=pos(g, 2, T, d, dtype=dtype))
    v[arg] = corrupt(v[arg], kind)
    if kind in ("nan", "inf") and arg in ("pred", "target"):
        if arg == "pred":  # gaussian_nll checks the mean; rmse of a NaN prediction is NaN by definition
            raises_named("mean", lambda: gaussian_nll(v["pred"], v["var"], v["target"]))
        return
    names = ("pred", "target", "mean", "var") if kind == "mixed" else \
        {"pred": ("pred", "mean"), "target": ("target",), "var": ("var",)}[arg]
    if kind == "shape":
        names = ("target", "var")
    if arg != "var":
        raises_named(names, lambda: rmse(v["pred"], v["target"]))
    raises_named(names, lambda: gaussian_nll(v["pred"], v["var"], v["target"]))
    raises_named(("var",) if arg == "var" else names + ("var",), lambda: sliding_window_nll(v["pred"], v["var"], v["target"], 1))
    raises_named("var", lambda: gaussian_nll(v["pred"].float(), -v["var"].abs().float(), v["target"].float())
                 if arg == "var" and kind not in ("int",) else gaussian_nll(*(x.float() for x in (
                     randn(g, 2, d), -pos(g, 2, d), randn(g, 2, d)))))

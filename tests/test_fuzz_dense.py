"""Fuzz suite, Chapter 1 (issue 13): every public dense Gaussian / Kalman function.

Random valid inputs give finite results with symmetric PSD covariances; random invalid inputs
(NaN/inf, half precision, mixed dtypes, integer tensors, wrong shapes, non-PD covariances, bad
masks, T = 0) raise a ValueError whose message starts with the argument's name."""

from __future__ import annotations

import torch
from hypothesis import given
from hypothesis import strategies as st

from _fuzz import ALL_KINDS, FUZZ, corrupt, dtypes, finite, gen, psd, raises_named, randn, seeds, spd
from pgm_wm.gaussian import Gaussian, condition, condition_with_evidence, log_density, marginalize_linear
from pgm_wm.kalman import kalman_filter, kf_predict, kf_update, rts_smoother
from pgm_wm.kalman_parallel import parallel_kalman_filter

BACKENDS = ["reference", "fast", "parallel"]


def lgssm(seed: int, n: int, m: int, T: int, dtype: torch.dtype, q: float, r: float, B: int = 2):
    g = gen(seed)
    F = randn(g, n, n, dtype=torch.float64)
    F = (0.95 * F / torch.linalg.eigvals(F).abs().max().clamp_min(1e-3)).to(dtype)
    H = randn(g, m, n, dtype=dtype)
    Q, R = spd(g, n, dtype, q), spd(g, m, dtype, r)
    init = Gaussian(randn(g, n, dtype=dtype), spd(g, n, dtype))
    y = randn(g, B, T, m, dtype=dtype)
    mask = torch.rand(B, T, generator=g) < 0.7
    return dict(y=y, init=init, F=F, H=H, Q=Q, R=R, mask=mask)


dims = st.tuples(st.integers(1, 3), st.integers(1, 3), st.integers(1, 7))
scales = st.sampled_from([1e-3, 1.0, 1e3])


@FUZZ
@given(seeds, dims, dtypes, scales, scales, st.sampled_from(BACKENDS))
def test_kalman_filter_valid_inputs_give_finite_psd_beliefs(seed, d, dtype, q, r, backend):
    n, m, T = d
    p = lgssm(seed, n, m, T, dtype, q, r)
    p["y"][~p["mask"]] = float("nan")  # values at missing steps are ignored
    res = kalman_filter(p["y"], p["init"], p["F"], p["H"], p["Q"], p["R"], p["mask"], backend=backend)
    for b in (res.prior, res.posterior, res.next_prior):
        assert finite(b.mean, b.cov) and psd(b.cov)
    assert finite(res.log_likelihoods)
    sm = rts_smoother(res, p["F"], p["Q"])
    assert finite(sm.mean, sm.cov) and psd(sm.cov)


@FUZZ
@given(seeds, dims, dtypes)
def test_parallel_filter_valid_inputs(seed, d, dtype):
    n, m, T = d
    p = lgssm(seed, n, m, T, dtype, 1.0, 1.0)
    res = parallel_kalman_filter(p["y"], p["init"], p["F"], p["H"], p["Q"], p["R"], p["mask"])
    assert finite(res.posterior.mean, res.posterior.cov) and psd(res.posterior.cov)


FILTER_ARGS = ["y", "init.mean", "init.cov", "F", "H", "Q", "R"]


@FUZZ
@given(seeds, dims, dtypes, st.sampled_from(FILTER_ARGS), st.sampled_from(ALL_KINDS), st.sampled_from(BACKENDS))
def test_kalman_filter_invalid_inputs_name_the_argument(seed, d, dtype, arg, kind, backend):
    n, m, T = d
    p = lgssm(seed, n, m, T, dtype, 1.0, 1.0)
    p["mask"] = None
    if arg.startswith("init."):
        mean, cov = p["init"].mean, p["init"].cov
        if arg == "init.mean":
            mean = corrupt(mean, kind)
        else:
            cov = corrupt(cov, kind) if kind != "shape" else torch.eye(n + 1, dtype=dtype)
        p["init"] = _raw_gaussian(mean, cov)
    else:
        x = p[arg]
        if kind == "shape" and x.ndim >= 2 and arg not in ("y",):
            x = torch.cat([x, x[..., :1, :]], dim=-2) if arg in ("F", "Q", "R") else torch.cat([x, x[..., :1]], -1)
        else:
            x = corrupt(x, kind)
        p[arg] = x
    names = (arg,)
    if kind == "mixed":  # a mix is reported at the first argument whose dtype differs
        names = tuple(FILTER_ARGS)
    if kind == "shape":  # a mismatch between two arguments: y/H or init.mean/init.cov (which sets n)/F
        names = {"y": ("H", "y"), "init.mean": ("init.cov", "F")}.get(arg, (arg,))
    raises_named(names, lambda: kalman_filter(p["y"], p["init"], p["F"], p["H"], p["Q"], p["R"], p["mask"],
                                            backend=backend))


def _raw_gaussian(mean, cov):
    """A Gaussian built without the constructor's own checks (if any), to reach the function's."""
    try:
        return Gaussian(mean, cov)
    except ValueError:
        g = object.__new__(Gaussian)
        g.__dict__.update(mean=mean, cov=cov)
        return g


@FUZZ
@given(seeds, dims, dtypes, st.sampled_from(BACKENDS))
def test_kalman_filter_non_pd_and_bad_masks(seed, d, dtype, backend):
    n, m, T = d
    p = lgssm(seed, n, m, T, dtype, 1.0, 1.0)
    args = lambda **kw: {**p, **kw}  # noqa: E731
    run = lambda a: kalman_filter(a["y"], a["init"], a["F"], a["H"], a["Q"], a["R"], a["mask"], backend=backend)  # noqa: E731
    raises_named("R", lambda: run(args(R=-p["R"])))
    raises_named("Q", lambda: run(args(Q=-p["Q"] - torch.eye(n, dtype=dtype))))
    raises_named("init.cov", lambda: run(args(init=_raw_gaussian(p["init"].mean, -p["init"].cov))))
    raises_named("mask", lambda: run(args(mask=p["mask"][:, :-1] if T > 1 else p["mask"][:1, :].expand(3, 1))))
    raises_named("mask", lambda: run(args(mask=p["mask"].to(torch.int64) + 2)))
    raises_named("y", lambda: run(args(y=p["y"][:, :0], mask=None)))
    y = p["y"].clone()
    y[p["mask"]] = float("nan")
    if bool(p["mask"].any()):
        raises_named("y", lambda: run(args(y=y)))


@FUZZ
@given(seeds, st.integers(1, 3), st.integers(1, 3), dtypes, scales)
def test_steps_valid_inputs(seed, n, m, dtype, scale):
    g = gen(seed)
    prior = Gaussian(randn(g, 2, n, dtype=dtype), spd(g, n, dtype, scale, batch=(2,)))
    F, Q = randn(g, n, n, dtype=dtype), spd(g, n, dtype, scale)
    H, R, y = randn(g, m, n, dtype=dtype), spd(g, m, dtype, 1.0 / scale), randn(g, 2, m, dtype=dtype)
    pred = kf_predict(prior, F, Q)
    assert finite(pred.mean, pred.cov) and psd(pred.cov)
    post, ll = kf_update(prior, H, R, y, torch.tensor([True, False]))
    assert finite(post.mean, post.cov, ll) and psd(post.cov)
    assert torch.equal(post.mean[1], prior.mean[1])
    c = condition(prior, H, R, y)
    c2, ev = condition_with_evidence(prior, H, R, y)
    assert finite(c.mean, c.cov, c2.cov, ev) and psd(c.cov)
    marg = marginalize_linear([(H, prior)], R)
    assert finite(marg.mean, marg.cov) and psd(marg.cov)
    assert finite(log_density(y, marg.mean, marg.cov))


STEP_ARGS = ["prior.mean", "prior.cov", "F", "Q", "H", "R", "y"]


@FUZZ
@given(seeds, st.integers(1, 3), st.integers(1, 3), dtypes, st.sampled_from(STEP_ARGS),
       st.sampled_from(["nan", "inf", "float16", "bfloat16", "mixed", "int"]))
def test_steps_invalid_inputs_name_the_argument(seed, n, m, dtype, arg, kind):
    g = gen(seed)
    v = dict(mean=randn(g, n, dtype=dtype), cov=spd(g, n, dtype), F=randn(g, n, n, dtype=dtype),
             Q=spd(g, n, dtype), H=randn(g, m, n, dtype=dtype), R=spd(g, m, dtype), y=randn(g, m, dtype=dtype))
    key = arg.split(".")[-1]
    names = STEP_ARGS if kind == "mixed" else (arg,)
    v[key] = corrupt(v[key], kind)
    prior = _raw_gaussian(v["mean"], v["cov"])
    if arg in ("prior.mean", "prior.cov", "F", "Q"):
        raises_named(names, lambda: kf_predict(prior, v["F"], v["Q"]))
    if arg in ("prior.mean", "prior.cov", "H", "R", "y"):
        raises_named(names, lambda: kf_update(prior, v["H"], v["R"], v["y"]))
        raises_named(names, lambda: condition(prior, v["H"], v["R"], v["y"]))
        raises_named(names, lambda: condition_with_evidence(prior, v["H"], v["R"], v["y"]))


@FUZZ
@given(seeds, st.integers(1, 3), dtypes, st.sampled_from(["nan", "float16", "mixed", "shape"]),
       st.sampled_from(["x", "mean", "cov"]))
def test_log_density_invalid(seed, n, dtype, kind, arg):
    g = gen(seed)
    v = dict(x=randn(g, n, dtype=dtype), mean=randn(g, n, dtype=dtype), cov=spd(g, n, dtype))
    if kind == "shape" and arg == "cov":
        v["cov"] = spd(g, n + 1, dtype)
    else:
        v[arg] = corrupt(v[arg], kind)
    names = ("x", "mean", "cov") if kind == "mixed" else ("mean",) if (kind, arg) == ("shape", "x") else (arg,)
    raises_named(names, lambda: log_density(v["x"], v["mean"], v["cov"]))


@FUZZ
@given(seeds, st.integers(1, 3), dtypes, st.sampled_from(["nan", "float16", "mixed"]))
def test_rts_smoother_invalid(seed, n, dtype, kind):
    p = lgssm(seed, n, 1, 4, dtype, 1.0, 1.0)
    res = kalman_filter(p["y"], p["init"], p["F"], p["H"], p["Q"], p["R"])
    raises_named("F", lambda: rts_smoother(res, corrupt(p["F"], kind), p["Q"]))
    raises_named("Q", lambda: rts_smoother(res, p["F"], -p["Q"] - torch.eye(n, dtype=dtype)))
    raises_named("result", lambda: rts_smoother((res.posterior,), p["F"], p["Q"]))

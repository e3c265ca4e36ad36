"""The reference filter loop and the diagonal fast path of the factorized filter.

Oracles: a dense Kalman filter written out here with plain matrix algebra (independent of
pgm_wm), and closed forms for the one-step variance.
"""

from __future__ import annotations

import pytest
import torch

from pgm_wm.beliefs import DiagGaussian, FactorizedBelief
from pgm_wm.factorized import diagonal_factorized_filter, factorized_filter, parallel_factorized_filter
from pgm_wm.filtering import FilterResult, filter_loop

FILTERS = [factorized_filter, diagonal_factorized_filter, parallel_factorized_filter]


def random_problem(seed: int, dtype: torch.dtype, B: int = 3, T: int = 7, m: int = 2, obs_var: float | None = None):
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    su, sl = 0.5 + rnd(B, m), 0.5 + rnd(B, m)
    prior = FactorizedBelief(torch.randn(B, 2 * m, generator=g, dtype=dtype), su, sl, 0.6 * (2 * rnd(B, m) - 1) * (su * sl).sqrt())
    d = [torch.diag(0.9 * (2 * rnd(m) - 1)) for _ in range(4)]
    A = torch.cat([torch.cat(d[:2], 1), torch.cat(d[2:], 1)], 0)
    q = 0.05 + 0.1 * rnd(2 * m)
    w = torch.randn(B, T, m, generator=g, dtype=dtype)
    w_var = (0.1 + rnd(B, T, m)) if obs_var is None else torch.full((B, T, m), obs_var, dtype=dtype)
    mask = rnd(B, T) < 0.7
    mask[:, 0] = True
    iu, il = 0.1 * rnd(B, T, m), 0.1 * rnd(B, T, m)
    inputs = FactorizedBelief(torch.randn(B, T, 2 * m, generator=g, dtype=dtype), iu, il, 0.5 * (iu * il).sqrt())
    return prior, A, q, DiagGaussian(w, w_var), mask, inputs


def dense_kalman(prior: FactorizedBelief, A, q, obs: DiagGaussian, mask, inputs: FactorizedBelief):
    """Independent oracle: the dense Kalman filter, Sigma+ = Sigma - K S K^T, in float64."""
    f64 = lambda x: x.to(torch.float64)  # noqa: E731
    d = prior.to(torch.float64).to_dense()
    mean, P = d.mean, d.cov
    m = prior.latent_obs_dim
    H = torch.cat([torch.eye(m), torch.zeros(m, m)], 1).to(torch.float64)
    A, q = f64(A), f64(q)
    inp = inputs.to(torch.float64).to_dense()
    out = {"prior": [], "posterior": [], "next_prior": []}
    for t in range(obs.mean.shape[-2]):
        out["prior"].append((mean, P))
        S = H @ P @ H.T + torch.diag_embed(f64(obs.var[:, t]))
        K = P @ H.T @ torch.linalg.inv(S)
        mean_p = mean + (K @ (f64(obs.mean[:, t]) - mean[:, :m]).unsqueeze(-1)).squeeze(-1)
        P_p = P - K @ S @ K.transpose(-1, -2)
        keep = mask[:, t, None]
        mean, P = torch.where(keep, mean_p, mean), torch.where(keep[..., None], P_p, P)
        out["posterior"].append((mean, P))
        mean = mean @ A.T + inp.mean[:, t]
        P = A @ P @ A.T + torch.diag(q) + inp.cov[:, t]
        out["next_prior"].append((mean, P))
    return {k: (torch.stack([x[0] for x in v], 1), torch.stack([x[1] for x in v], 1)) for k, v in out.items()}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("fn", FILTERS)
def test_filters_equal_the_dense_kalman_filter(fn, dtype):
    prior, A, q, obs, mask, inputs = random_problem(0, dtype)
    res = fn(prior, A, q, obs, mask, inputs)
    assert isinstance(res, FilterResult) and res.log_likelihoods is None
    ref = dense_kalman(prior, A, q, obs, mask, inputs)
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for name in ("prior", "posterior", "next_prior"):
        dense = getattr(res, name).to_dense()
        torch.testing.assert_close(dense.mean.double(), ref[name][0], **tol)
        torch.testing.assert_close(dense.cov.double(), ref[name][1], **tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("obs_var", [1e-6, 1e-3, 1.0, 1e3])
def test_fast_path_equals_the_reference_loop(dtype, obs_var):
    prior, A, q, obs, mask, inputs = random_problem(1, dtype, obs_var=obs_var)
    for inp, msk in ((inputs, mask), (None, None)):
        ref = factorized_filter(prior, A, q, obs, msk, inp)
        fast = diagonal_factorized_filter(prior, A, q, obs, msk, inp)
        tol = dict(rtol=2e-6, atol=1e-7) if dtype == torch.float32 else dict(rtol=1e-13, atol=1e-15)
        for name in ("prior", "posterior", "next_prior"):
            a, b = getattr(ref, name), getattr(fast, name)
            for x, y in zip(a._tensors(), b._tensors()):
                assert x.dtype == y.dtype == dtype
                torch.testing.assert_close(y, x, **tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("fn", FILTERS)
def test_tiny_observation_variance_keeps_full_relative_precision(fn, dtype):
    """Prior variance 10, observation variance 1e-6: sigma_u+ = 10 * 1e-6 / (10 + 1e-6).

    The cancelling form sigma_u * (1 - sigma_u / S) gives 5.96e-7 in float32 (40 % low); the
    product form sigma_u * sigma_obs / S is exact to rounding."""
    m = 3
    prior = FactorizedBelief.isotropic((2,), m, 10.0, dtype=dtype)
    A = torch.eye(2 * m, dtype=dtype)
    obs = DiagGaussian(torch.ones(2, 1, m, dtype=dtype), torch.full((2, 1, m), 1e-6, dtype=dtype))
    res = fn(prior, A, torch.zeros(2 * m, dtype=dtype), obs)
    exact = 10.0 * 1e-6 / (10.0 + 1e-6)
    got = res.posterior.var_upper.double()
    torch.testing.assert_close(got, torch.full_like(got, exact), rtol=1e-6, atol=0.0)
    assert bool((res.posterior.var_lower > 0).all())


def test_masked_steps_leave_the_prior_and_next_prior_is_the_shifted_prior():
    """Exactly for the loops; to rounding for the scan, whose posteriors are prefix products
    and whose priors are predictions from them."""
    prior, A, q, obs, mask, inputs = random_problem(2, torch.float64)
    mask[:, 3] = False
    for fn in FILTERS:
        res = fn(prior, A, q, obs, mask, inputs)
        same = torch.equal if fn is not parallel_factorized_filter else \
            (lambda x, y: bool(torch.allclose(x, y, rtol=1e-12, atol=1e-14)))
        for x, y in zip(res.prior.at(3)._tensors(), res.posterior.at(3)._tensors()):
            assert same(x, y)
        for x, y in zip(res.next_prior._tensors(), res.prior._tensors()):
            assert same(x[:, :-1], y[:, 1:])


def test_filter_loop_calls_update_then_predict_in_order():
    calls = []
    obs = DiagGaussian(torch.zeros(1, 3, 1), torch.ones(1, 3, 1))

    def update(b, y, m):
        calls.append(("u", float(b.mean[0, 0])))
        return DiagGaussian(b.mean + 1.0, b.var)

    def predict(b, t):
        calls.append(("p", t))
        return DiagGaussian(2.0 * b.mean, b.var)

    res = filter_loop(DiagGaussian(torch.zeros(1, 1), torch.ones(1, 1)), update, predict, obs)
    assert calls == [("u", 0.0), ("p", 0), ("u", 2.0), ("p", 1), ("u", 6.0), ("p", 2)]
    assert res.next_prior.mean[0, :, 0].tolist() == [2.0, 6.0, 14.0]
    assert res.posterior.mean.shape == (1, 3, 1)


def test_bad_inputs_name_the_argument():
    prior, A, q, obs, mask, inputs = random_problem(3, torch.float64)
    empty = DiagGaussian(obs.mean[:, :0], obs.var[:, :0])
    for fn in FILTERS:
        with pytest.raises(ValueError, match="^observation"):
            fn(prior, A, q, empty)
        with pytest.raises(ValueError, match="^observation.var"):
            fn(prior, A, q, DiagGaussian(obs.mean, -obs.var))
        with pytest.raises(ValueError, match="^mask"):
            fn(prior, A, q, obs, mask[:, :2])
        with pytest.raises(ValueError, match="^inputs"):
            fn(prior, A, q, obs, mask, inputs.map(lambda x: x[:, :2]))
        with pytest.raises(ValueError, match="^prior"):
            fn(prior.map(lambda x: -x), A, q, obs)
        with pytest.raises(ValueError, match="^A"):
            fn(prior, A[:2], q, obs)
    full = A + 0.01
    with pytest.raises(ValueError, match="^A"):
        diagonal_factorized_filter(prior, full, q, obs)


# ------------------------------------------------------------------------------ long runs (issue 13.5)
def _untrained(name: str):
    from pgm_wm.acrkn import AcRKN, MLPControl, NormBoundedTransition
    from pgm_wm.aggregation import BayesianContextEncoder
    from pgm_wm.hiprssm import HiPRSSM, LinearTaskTransform, NonlinearTaskTransform
    from pgm_wm.mts3 import build_hierarchical_mts3, build_mts3
    from pgm_wm.rkn import RKN, BeliefDecoder, LocallyLinearTransition, ObservationEncoder

    torch.manual_seed(0)
    do, da, m = 3, 2, 4
    enc, dec = ObservationEncoder(do, m, (16,)), BeliefDecoder(m, do, (16,), (16,))
    if name == "rkn":
        return RKN(enc, LocallyLinearTransition(m), dec)
    acrkn = AcRKN(enc, LocallyLinearTransition(m), MLPControl(da, m, (16,)), dec)
    if name == "acrkn":
        return acrkn
    if name == "acrkn-normbounded":
        return AcRKN(enc, NormBoundedTransition(LocallyLinearTransition(m)), MLPControl(da, m, (16,)), dec)
    if name.startswith("hiprssm"):
        tr = LinearTaskTransform(4, m) if name.endswith("linear") else NonlinearTaskTransform(4, m, (16,))
        return HiPRSSM(acrkn, BayesianContextEncoder(2 * do + da, 4, (16,)), tr)
    if name == "mts3":
        return build_mts3(do, da, m, 25, (16,))
    return build_hierarchical_mts3(do, da, m, [25, 100], (16,))


@pytest.mark.parametrize("name", ["rkn", "acrkn", "acrkn-normbounded", "hiprssm-linear", "hiprssm-nonlinear",
                                  "mts3", "mts3-3-levels"])
def test_untrained_models_stay_finite_over_10000_missing_steps(name):
    """The default initial transitions are stable (spectral radius < 1): 10,000 steps without a
    single observation keep every prediction finite with a positive variance (before the fix the
    RKN's prior variance overflowed at step ~2200)."""
    model = _untrained(name)
    T = 10_000
    obs, act = torch.randn(1, T, 3), torch.randn(1, T, 2)
    mask = torch.zeros(1, T, dtype=torch.bool)
    with torch.no_grad():
        mean, var = model(obs, mask) if name == "rkn" else model(obs, act, mask)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(var).all()) and bool((var > 0).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("masked", [True, False])
@pytest.mark.parametrize("backend", ["compiled", "tensor"])
def test_fast_path_gradients_equal_the_reference_loop(dtype, masked, backend):
    """Training differentiates the fast path (MTS3's fast level): its gradients with respect to
    the prior, the observations, the transition, its noise and the inputs equal those of the
    reference loop, with and without a mask, both for the compiled loop with its hand-written
    backward pass (numba) and for the tensor operations (the path with ``PGM_WM_JIT=0``), and
    so do the values without a gradient."""
    from functools import partial

    from pgm_wm import _backends

    if backend == "compiled" and not _backends.compiled_available():
        pytest.skip("numba is not installed or PGM_WM_JIT=0")
    fast_filter = partial(diagonal_factorized_filter, backend=backend)
    prior, A, q, obs, mask, inputs = random_problem(3, dtype)
    mask = mask if masked else None
    leaves = [prior.mean, prior.var_upper, prior.var_lower, prior.cov_side, A, q, obs.mean, obs.var,
              inputs.mean, inputs.var_upper, inputs.var_lower, inputs.cov_side]
    grads = []
    for fn in (factorized_filter, fast_filter):
        xs = [x.detach().clone().requires_grad_(True) for x in leaves]
        p, o = FactorizedBelief(*xs[:4]), DiagGaussian(xs[6], xs[7])
        res = fn(p, xs[4], xs[5], o, mask, FactorizedBelief(*xs[8:]))
        loss = sum((getattr(res, f).mean.square().sum() + getattr(res, f).var_upper.sum() + getattr(res, f).var_lower.sum()
                    + getattr(res, f).cov_side.sum()) for f in ("prior", "posterior", "next_prior"))
        grads.append(torch.autograd.grad(loss, xs, allow_unused=True))
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for a, b in zip(*grads):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(b, a, **tol)
    with torch.no_grad():
        fast = fast_filter(prior, A, q, obs, mask, inputs)
        ref = factorized_filter(prior, A, q, obs, mask, inputs)
    # float32: the compiled loop rounds its float64 intermediates once per step, the tensor
    # operations after every operation (a few ulp apart, more where sigma^l - (sigma^s)^2 g cancels)
    tol = dict(rtol=2e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-13, atol=1e-15)
    for name in ("prior", "posterior", "next_prior"):
        for x, y in zip(getattr(ref, name)._tensors(), getattr(fast, name)._tensors()):
            torch.testing.assert_close(y, x, **tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("masked", [True, False])
@pytest.mark.parametrize("T", [7, 8, 1])
def test_parallel_factorized_filter_equals_the_reference_loop(dtype, masked, T):
    """The associative scan over lanes gives the reference loop's beliefs (to 1e-10 in float64)
    and its gradients with respect to the prior, the observations, the noise, the inputs and the
    block diagonals of A (the entries a transition with diagonal blocks has), for odd and even
    lengths, one step, and a batch of two dimensions."""
    prior, A, q, obs, mask, inputs = random_problem(5, dtype, B=4, T=T)
    split = lambda x: x.reshape(2, 2, *x.shape[1:])  # noqa: E731  batch (4,) -> (2, 2)
    prior, obs, inputs, mask = prior.map(split), obs.map(split), inputs.map(split), split(mask)
    mask = mask if masked else None
    leaves = [prior.mean, prior.var_upper, prior.var_lower, prior.cov_side, A, q, obs.mean, obs.var,
              inputs.mean, inputs.var_upper, inputs.var_lower, inputs.cov_side]
    outs, grads = [], []
    for fn in (factorized_filter, parallel_factorized_filter):
        xs = [x.detach().clone().requires_grad_(True) for x in leaves]
        res = fn(FactorizedBelief(*xs[:4]), xs[4], xs[5], DiagGaussian(xs[6], xs[7]), mask, FactorizedBelief(*xs[8:]))
        loss = sum((getattr(res, f).mean.square().sum() + getattr(res, f).var_upper.sum()
                    + getattr(res, f).var_lower.sum() + getattr(res, f).cov_side.sum())
                   for f in ("prior", "posterior", "next_prior"))
        outs.append(res)
        grads.append(list(torch.autograd.grad(loss, xs)))
    m = prior.latent_obs_dim
    block_diagonals = torch.eye(m, dtype=torch.bool).repeat(2, 2)
    for g in grads:
        g[4] = g[4][block_diagonals]
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-4, atol=2e-5)
    for name in ("prior", "posterior", "next_prior"):
        for x, y in zip(getattr(outs[0], name)._tensors(), getattr(outs[1], name)._tensors()):
            assert x.shape == y.shape
            torch.testing.assert_close(y, x, **tol)
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, **tol)

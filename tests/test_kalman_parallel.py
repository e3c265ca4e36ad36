"""Parallel-in-time Kalman filter and smoother (pgm_wm.kalman_parallel) against the sequential
reference loop of pgm_wm.kalman (itself tested against filterpy and the dense joint), and the
generic associative scan against plain sequential folds."""

from __future__ import annotations

import math

import pytest
import torch

from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter, kalman_filter_reference, rts_smoother_reference
from pgm_wm.kalman_parallel import associative_scan, parallel_kalman_filter, parallel_rts_smoother

from test_kalman_backends import TOLS, assert_results_close, random_model


@pytest.mark.parametrize("T", [1, 2, 3, 8, 31, 64, 100])
@pytest.mark.parametrize("reverse", [False, True])
def test_associative_scan_equals_sequential_fold(T: int, reverse: bool) -> None:
    """A non-commutative operator (2×2 matrix products, later @ earlier) and a sum, on a batch."""
    g = torch.Generator().manual_seed(T)
    mats = torch.randn(T, 3, 2, 2, generator=g, dtype=torch.float64) * 0.7
    vals = torch.randn(T, 3, generator=g, dtype=torch.float64)
    calls = []

    def fn(a, b):
        calls.append(1)
        return b[0] @ a[0], a[1] + b[1]

    out_m, out_v = associative_scan(fn, (mats, vals), reverse=reverse)
    order = range(T - 1, -1, -1) if reverse else range(T)
    acc_m, acc_v, ref_m, ref_v = None, None, {}, {}
    for t in order:
        if acc_m is None:
            acc_m, acc_v = mats[t], vals[t]
        elif reverse:   # e[t] ⊗ (e[t+1] ⊗ …): later @ earlier with e[t] the earlier
            acc_m, acc_v = acc_m @ mats[t], vals[t] + acc_v
        else:
            acc_m, acc_v = mats[t] @ acc_m, acc_v + vals[t]
        ref_m[t], ref_v[t] = acc_m, acc_v
    torch.testing.assert_close(out_m, torch.stack([ref_m[t] for t in range(T)]), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out_v, torch.stack([ref_v[t] for t in range(T)]), rtol=1e-12, atol=1e-12)
    assert len(calls) <= 2 * max(1, math.ceil(math.log2(T)))   # O(log T) sequential depth


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("mask_kind", ["none", "per_sequence", "all_missing", "batched_params"])
@pytest.mark.parametrize("T", [1, 2, 37])
def test_parallel_filter_and_smoother_equal_sequential(dtype, mask_kind, T) -> None:
    n, m, N = 3, 2, 4
    model, B = random_model(7, n, m, dtype, k=1)
    g = torch.Generator().manual_seed(8)
    y = torch.randn(N, T, m, generator=g, dtype=torch.float64).to(dtype)
    u = torch.randn(N, T, 1, generator=g, dtype=torch.float64).to(dtype)
    mask = {"none": None, "per_sequence": torch.rand(N, T, generator=g) > 0.3,
            "all_missing": torch.zeros(N, T, dtype=torch.bool), "batched_params": torch.rand(N, T, generator=g) > 0.3}[mask_kind]
    if mask_kind == "batched_params":
        model["R"] = model["R"] * torch.linspace(0.5, 2.0, N, dtype=dtype)[:, None, None]
    args = (y, model["init"], model["F"], model["H"], model["Q"], model["R"], mask, B, u)
    ref = kalman_filter_reference(*args)
    par = parallel_kalman_filter(*args)
    rtol, atol = TOLS[dtype]
    assert_results_close(par, ref, rtol, atol)
    torch.testing.assert_close(par.log_likelihood, ref.log_likelihood, rtol=rtol, atol=atol * 10)
    assert_results_close(kalman_filter(*args, backend="parallel"), ref, rtol, atol)
    sm_ref = rts_smoother_reference(ref, model["F"], model["Q"])
    sm = parallel_rts_smoother(ref, model["F"], model["Q"])
    torch.testing.assert_close(sm.mean, sm_ref.mean, rtol=rtol, atol=atol)
    torch.testing.assert_close(sm.cov, sm_ref.cov, rtol=rtol, atol=atol)


def test_parallel_loglik_exact_on_long_tracking_run() -> None:
    """2000 steps of a 4-d constant-velocity model with 10 % missing: the parallel
    log-likelihood equals the sequential one to 1e-10 (relative), float64."""
    dt = 0.1
    i2, z2 = torch.eye(2, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64)
    F = torch.cat([torch.cat([i2, dt * i2], 1), torch.cat([z2, i2], 1)])
    Q = 0.5 * torch.cat([torch.cat([dt**3 / 3 * i2, dt**2 / 2 * i2], 1), torch.cat([dt**2 / 2 * i2, dt * i2], 1)])
    H = torch.cat([i2, z2], 1)
    g = torch.Generator().manual_seed(0)
    y = torch.randn(3, 2000, 2, generator=g, dtype=torch.float64).cumsum(1)
    mask = torch.rand(3, 2000, generator=g) >= 0.1
    init = Gaussian(torch.zeros(4, dtype=torch.float64), 25 * torch.eye(4, dtype=torch.float64))
    ref = kalman_filter(y, init, F, H, Q, i2, mask)
    par = parallel_kalman_filter(y, init, F, H, Q, i2, mask)
    rel = ((par.log_likelihood - ref.log_likelihood).abs() / ref.log_likelihood.abs()).max()
    assert float(rel) < 1e-10
    torch.testing.assert_close(par.posterior.mean, ref.posterior.mean, rtol=1e-10, atol=1e-8)


def test_parallel_checks_name_the_argument() -> None:
    model, _ = random_model(0, 2, 1, torch.float64)
    y = torch.zeros(2, 5, 1, dtype=torch.float64)
    with pytest.raises(ValueError, match="^R"):
        parallel_kalman_filter(y, model["init"], model["F"], model["H"], model["Q"], -model["R"])
    with pytest.raises(ValueError, match="^elems"):
        associative_scan(lambda a, b: a, (torch.zeros(3), torch.zeros(4)))

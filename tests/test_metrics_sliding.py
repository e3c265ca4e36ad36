"""Sliding-window RMSE / NLL (pgm_wm.metrics, Chapter 6) against a direct numpy computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm_wm.metrics import gaussian_nll, rmse, sliding_window_nll, sliding_window_rmse



def numpy_sliding(per_entry: np.ndarray, weights: np.ndarray, window: int) -> np.ndarray:
    """Direct loops: for every t, the weighted mean over b, i in [t-W+1, t] and all other axes."""
    B, T = per_entry.shape[:2]
    out = np.empty(T)
    for t in range(T):
        num = den = 0.0
        for b in range(B):
            for i in range(max(0, t - window + 1), t + 1):
                num += float((per_entry[b, i] * weights[b, i]).sum())
                den += float(weights[b, i].sum())
        out[t] = num / den
    return out


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 4), st.integers(1, 12), st.integers(1, 15), st.booleans())
def test_sliding_rmse_and_nll_match_numpy_loops(seed, B, T, W, use_mask):
    rng = np.random.default_rng(seed)
    pred = rng.normal(size=(B, T, 3))
    target = rng.normal(size=(B, T, 3))
    var = rng.uniform(0.1, 2.0, size=(B, T, 3))
    mask = rng.uniform(size=(B, T)) > 0.3 if use_mask else np.ones((B, T), dtype=bool)
    mask[0, :] = True  # every time step (hence every window) selects something
    w = np.broadcast_to(mask[..., None], pred.shape).astype(float)
    tm = torch.as_tensor(mask) if use_mask else None
    got_r = sliding_window_rmse(torch.as_tensor(pred), torch.as_tensor(target), W, tm).numpy()
    want_r = np.sqrt(numpy_sliding((pred - target) ** 2, w, W))
    np.testing.assert_allclose(got_r, want_r, rtol=1e-10, atol=1e-12)
    nll = 0.5 * (math.log(2 * math.pi) + np.log(var) + (target - pred) ** 2 / var)
    got_n = sliding_window_nll(torch.as_tensor(pred), torch.as_tensor(var), torch.as_tensor(target), W, tm).numpy()
    np.testing.assert_allclose(got_n, numpy_sliding(nll, w, W), rtol=1e-10, atol=1e-12)


def test_window_one_is_per_step_and_long_window_is_running_mean():
    torch.manual_seed(0)
    pred, target = torch.randn(3, 8, 2, dtype=torch.float64), torch.randn(3, 8, 2, dtype=torch.float64)
    var = torch.rand(3, 8, 2, dtype=torch.float64) + 0.5
    torch.testing.assert_close(sliding_window_rmse(pred, target, 1), rmse(pred, target, dim=(0, 2)))
    torch.testing.assert_close(sliding_window_nll(pred, var, target, 1), gaussian_nll(pred, var, target, dim=(0, 2)))
    # a window longer than the sequence: the value at the last step is the overall metric
    torch.testing.assert_close(sliding_window_rmse(pred, target, 50)[-1], rmse(pred, target))
    torch.testing.assert_close(sliding_window_nll(pred, var, target, 50)[-1], gaussian_nll(pred, var, target))


def test_sliding_metrics_validate_inputs():
    p, t = torch.randn(2, 5, 3), torch.randn(2, 5, 3)
    with pytest.raises(ValueError, match="window"):
        sliding_window_rmse(p, t, 0)
    with pytest.raises(ValueError, match="target"):
        sliding_window_rmse(p, t[:, :4], 2)
    with pytest.raises(ValueError, match="var"):
        sliding_window_nll(p, -torch.ones_like(p), t, 2)
    with pytest.raises(ValueError, match="mask"):
        sliding_window_rmse(p, t, 2, torch.zeros(2, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask"):
        sliding_window_rmse(p, t, 2, torch.ones(2, 4, dtype=torch.bool))


def test_interval_coverage_of_calibrated_and_miscalibrated_predictions():
    """Closed form: draws from the predicted Gaussian are inside mean ± zσ with probability
    erf(z/√2) (scipy's normal CDF as the independent reference); a variance four times too small
    (σ halved) covers P(|Z| <= z/2); masks and dims as for rmse, against a numpy count."""
    from scipy.stats import norm as _norm

    from pgm_wm.metrics import interval_coverage, nominal_coverage

    g = torch.Generator().manual_seed(0)
    mean = torch.randn(400, 250, 2, generator=g, dtype=torch.float64)
    var = torch.rand(400, 250, 2, generator=g, dtype=torch.float64) + 0.1
    target = mean + var.sqrt() * torch.randn(400, 250, 2, generator=g, dtype=torch.float64)
    for z in (1.0, 2.0):
        assert nominal_coverage(z) == pytest.approx(_norm.cdf(z) - _norm.cdf(-z), abs=1e-12)
        assert float(interval_coverage(mean, var, target, z)) == pytest.approx(nominal_coverage(z), abs=3e-3)
        assert float(interval_coverage(mean, var / 4, target, z)) == pytest.approx(nominal_coverage(z / 2), abs=3e-3)
    mask = torch.rand(400, 250, generator=g) < 0.3
    per_t = interval_coverage(mean, var, target, 2.0, mask=mask, dim=(0, 2))
    inside = (np.abs(target.numpy() - mean.numpy()) <= 2.0 * np.sqrt(var.numpy())) & mask.numpy()[..., None]
    expected = inside.sum(axis=(0, 2)) / (2 * mask.numpy().sum(axis=0))
    np.testing.assert_allclose(per_t.numpy(), expected, rtol=1e-12)


def test_interval_coverage_bad_inputs_name_the_argument():
    from pgm_wm.metrics import interval_coverage, nominal_coverage

    m = torch.zeros(2, 3, 1)
    with pytest.raises(ValueError, match="^var"):
        interval_coverage(m, torch.zeros(2, 3, 1), m)
    with pytest.raises(ValueError, match="^z"):
        interval_coverage(m, torch.ones(2, 3, 1), m, z=0.0)
    with pytest.raises(ValueError, match="^z"):
        nominal_coverage(float("nan"))
    with pytest.raises(ValueError, match="^var"):
        interval_coverage(m, torch.ones(2, 3, 2), m)

"""Probes (pgm_wm.probes) against closed forms: R² of a known linear relation with known noise,
a nonlinear relation a linear probe cannot read and a small MLP can, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.probes import linear_probe_r2, mlp_probe_r2, r2_score


def test_r2_score_is_one_minus_sse_over_sst():
    y = torch.tensor([[1.0, 0.0], [2.0, 1.0], [3.0, 5.0]])
    pred = torch.tensor([[1.5, 0.0], [2.0, 2.0], [2.5, 4.0]])
    sse = 0.25 + 0 + 0.25 + 0 + 1 + 1
    sst = (1 + 0 + 1) + (4 + 1 + 9)          # column means 2 and 2
    assert r2_score(pred, y) == pytest.approx(1 - sse / sst)
    assert r2_score(y, y) == 1.0
    with pytest.raises(ValueError, match="^target"):
        r2_score(torch.ones(4), torch.ones(4))


def test_linear_probe_recovers_a_noisy_linear_read_out_with_the_expected_r2():
    g = torch.Generator().manual_seed(0)
    X = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    w = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    noise_sd = 1.0
    y = X @ w + 3.0 + noise_sd * torch.randn(4000, generator=g, dtype=torch.float64)
    expected = 1 - noise_sd**2 / (float(w @ w) + noise_sd**2)    # signal variance |w|² = 5.25
    assert linear_probe_r2(X[:3000], y[:3000], X[3000:], y[3000:]) == pytest.approx(expected, abs=0.02)
    assert linear_probe_r2(X[:3000], X[:3000, :1], X[3000:], X[3000:, :1]) == pytest.approx(1.0)


def test_mlp_probe_reads_a_curved_relation_the_linear_probe_misses():
    g = torch.Generator().manual_seed(1)
    x = 3 * (2 * torch.rand(1500, 1, generator=g, dtype=torch.float64) - 1)
    y = torch.cos(x) + 0.05 * torch.randn(1500, 1, generator=g, dtype=torch.float64)
    lin = linear_probe_r2(x[:1000], y[:1000], x[1000:], y[1000:])
    mlp = mlp_probe_r2(x[:1000], y[:1000], x[1000:], y[1000:], seed=0)
    assert lin < 0.05 and mlp > 0.9
    assert mlp == mlp_probe_r2(x[:1000], y[:1000], x[1000:], y[1000:], seed=0)      # seeded


def test_probes_reject_bad_input():
    X, y = torch.randn(10, 2), torch.randn(10)
    with pytest.raises(ValueError, match="Y_fit"):
        linear_probe_r2(X, y[:5], X, y)
    with pytest.raises(ValueError, match="^X"):
        linear_probe_r2(X, y, X[:, :1], y)
    with pytest.raises(ValueError, match="X_fit"):
        linear_probe_r2(X.clone().fill_(float("nan")), y, X, y)
    with pytest.raises(ValueError, match="hidden"):
        mlp_probe_r2(X, y, X, y, hidden=0)
    assert np.isfinite(linear_probe_r2(X, y, X, y))

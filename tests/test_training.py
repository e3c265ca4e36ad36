"""Tests for pgm_wm.training and pgm_wm.metrics: masks, crops, the fit loop, open-loop
prediction without leakage, and the metrics against direct numpy/scipy computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from pgm_wm.acrkn import AcRKN, DifferenceReadout, MLPControl
from pgm_wm.metrics import denormalize, denormalize_var, gaussian_nll, normalize, rmse
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder
from pgm_wm.training import (
    fit,
    imputation_loss_fn,
    imputation_mask,
    multistep_predict,
    prediction_loss,
    random_crop,
    set_seed,
    sliding_windows,
)

DT = torch.float64


# ----------------------------------------------------------------------------- masks and seeds

def test_imputation_mask_fraction_and_context():
    g = torch.Generator().manual_seed(0)
    B, T, c, p = 200, 150, 5, 0.25
    mask = imputation_mask((B, T), p, c, g)
    assert mask.dtype == torch.bool and mask.shape == (B, T)
    assert bool(mask[:, :c].all())
    rest = mask[:, c:].double()
    n = rest.numel()
    sd = math.sqrt(p * (1 - p) / n)
    assert abs(float(rest.mean()) - p) < 5 * sd
    # per-position frequencies are also close to p (no position bias after the context)
    col = rest.mean(0)
    assert float((col - p).abs().max()) < 5 * math.sqrt(p * (1 - p) / B)


def test_imputation_mask_is_seeded_and_resampled():
    m1 = imputation_mask((4, 50), 0.5, 3, torch.Generator().manual_seed(1))
    m2 = imputation_mask((4, 50), 0.5, 3, torch.Generator().manual_seed(1))
    assert torch.equal(m1, m2)
    g = torch.Generator().manual_seed(1)
    a, b = imputation_mask((4, 50), 0.5, 3, g), imputation_mask((4, 50), 0.5, 3, g)
    assert not torch.equal(a, b)
    assert bool(imputation_mask((3, 4), 0.0, 10).all())  # context longer than T: all kept
    assert not bool(imputation_mask((3, 40), 0.0, 2)[:, 2:].any())


def test_set_seed_reproducible():
    g1 = set_seed(7)
    a = torch.randn(3), np.random.rand(), torch.rand(2, generator=g1)
    g2 = set_seed(7)
    b = torch.randn(3), np.random.rand(), torch.rand(2, generator=g2)
    assert torch.equal(a[0], b[0]) and a[1] == b[1] and torch.equal(a[2], b[2])


def test_random_crop_is_consistent_and_contiguous():
    B, T = 6, 40
    x = torch.arange(B * T, dtype=DT).reshape(B, T, 1)
    y = x * 2
    per_seq = torch.arange(B, dtype=DT)[:, None]
    cx, cy, cp = random_crop((x, y, per_seq), 10, torch.Generator().manual_seed(0))
    assert cx.shape == (B, 10, 1) and torch.equal(cy, 2 * cx) and torch.equal(cp, per_seq)
    steps = cx[:, 1:, 0] - cx[:, :-1, 0]
    assert bool((steps == 1).all())
    assert torch.equal((cx[:, 0, 0] // T), torch.arange(B, dtype=DT))  # row stays its own sequence


def test_sliding_windows():
    x = torch.arange(2 * 10, dtype=DT).reshape(2, 10)
    w = sliding_windows(x, 4, 3)
    assert w.shape == (2 * 3, 4)
    torch.testing.assert_close(w[1], x[0, 3:7])
    torch.testing.assert_close(w[3], x[1, 0:4])


# ----------------------------------------------------------------------------- fit

def _regression_problem():
    g = torch.Generator().manual_seed(0)
    X = torch.randn(256, 3, generator=g, dtype=DT)
    w_true = torch.tensor([1.0, -2.0, 0.5], dtype=DT)
    y = X @ w_true + 0.01 * torch.randn(256, generator=g, dtype=DT)
    return X, y


def test_fit_reaches_least_squares_and_is_seeded():
    X, y = _regression_problem()
    results = []
    for _ in range(2):
        w = torch.zeros(3, dtype=DT, requires_grad=True)
        hist = fit(lambda b, g: ((b[0] @ w - b[1]) ** 2).mean(), [w], (X, y), batch_size=32, epochs=60,
                   lr=0.05, seed=3, progress=False, valid_fn=lambda: float(((X @ w - y) ** 2).mean()))
        results.append(w.detach().clone())
    w_ls = torch.linalg.lstsq(X, y[:, None]).solution[:, 0]
    torch.testing.assert_close(results[0], w_ls, atol=2e-2, rtol=0)
    assert torch.equal(results[0], results[1])
    assert len(hist.train_loss) == 60 == len(hist.valid_metric) == len(hist.epoch_time)
    assert hist.train_loss[-1] < 0.01 * hist.train_loss[0]
    assert hist.wall_time > 0


def test_fit_keep_best_restores_best_epoch():
    X, y = _regression_problem()
    model = torch.nn.Linear(3, 1).double()
    metric = iter([5.0, 1.0, 3.0, 4.0])
    saved = {}

    def valid():
        v = next(metric)
        saved[v] = model.weight.detach().clone()
        return v

    hist = fit(lambda b, g: ((model(b[0])[:, 0] - b[1]) ** 2).mean(), model, (X, y), 64, 4, lr=0.1,
               valid_fn=valid, keep_best=True, progress=False)
    assert hist.best_epoch == 1
    torch.testing.assert_close(model.weight, saved[1.0])


def test_fit_bad_inputs():
    X, y = _regression_problem()
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    loss = lambda b, g: ((b[0] @ w - b[1]) ** 2).mean()  # noqa: E731
    with pytest.raises(ValueError, match="train_tensors"):
        fit(loss, [w], (X, y[:10]), 8, 1, progress=False)
    with pytest.raises(ValueError, match="lr"):
        fit(loss, [w], (X, y), 8, 1, lr=0.0, progress=False)
    with pytest.raises(ValueError, match="batch_size"):
        fit(loss, [w], (X, y), 0, 1, progress=False)
    with pytest.raises(ValueError, match="keep_best"):
        fit(loss, [w], (X, y), 8, 1, keep_best=True, progress=False)
    with pytest.raises(ValueError, match="loss_fn"):
        fit(lambda b, g: (b[0] @ w - b[1]) ** 2, [w], (X, y), 8, 1, progress=False)
    with pytest.raises(ValueError, match="keep_prob"):
        imputation_mask((2, 3), 1.5)
    with pytest.raises(ValueError, match="shape"):
        imputation_mask((2, 3, 4), 0.5)
    with pytest.raises(ValueError, match="context_steps"):
        imputation_mask((2, 3), 0.5, -1)


# ----------------------------------------------------------------------------- world-model helpers

class CountingModel(torch.nn.Module):
    """A toy world model whose normalized difference is always +1: o_hat_{t+1} = m_t + 1."""

    def __init__(self):
        super().__init__()
        self.readout = DifferenceReadout(2)

    def forward(self, obs, actions, mask):
        delta = torch.ones_like(obs)
        return self.readout(obs, mask, delta + 0 * actions.sum(-1, keepdim=True), torch.ones_like(obs))


def _acrkn(m=4, do=2, da=2):
    torch.manual_seed(0)
    return AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, 3, 1), MLPControl(da, m, (16,)),
                 BeliefDecoder(m, do, (16,), (16,))).double()


def test_multistep_indexing_with_counting_model():
    obs = torch.randn(3, 20, 2, dtype=DT)
    act = torch.randn(3, 20, 2, dtype=DT)
    mean, var = multistep_predict(CountingModel(), obs, act, context_len=6, horizon=7)
    assert mean.shape == (3, 7, 2)
    k = torch.arange(1, 8, dtype=DT)[None, :, None]
    torch.testing.assert_close(mean, obs[:, 5:6] + k)  # k-step prediction = last context obs + k


@pytest.mark.parametrize("model_fn", [_acrkn, CountingModel])
def test_multistep_uses_no_future_observation(model_fn):
    model = model_fn()
    g = torch.Generator().manual_seed(2)
    obs, act = torch.randn(2, 30, 2, generator=g, dtype=DT), torch.randn(2, 30, 2, generator=g, dtype=DT)
    c, h = 8, 15
    mean, var = multistep_predict(model, obs, act, c, h)
    corrupt = obs.clone()
    corrupt[:, c:] = float("nan")
    act2 = act.clone()
    act2[:, c + h - 1:] = 1e3  # actions after the last predicted step are irrelevant too
    mean2, var2 = multistep_predict(model, corrupt, act2, c, h)
    torch.testing.assert_close(mean2, mean)
    torch.testing.assert_close(var2, var)
    # and the result equals one call with the future masked out
    mask = torch.zeros(2, c + h - 1, dtype=torch.bool)
    mask[:, :c] = True
    m3, _ = model(torch.where(mask[..., None], obs[:, :c + h - 1], 0.0), act[:, :c + h - 1], mask)
    torch.testing.assert_close(m3[:, c - 1:], mean)


def test_multistep_bad_inputs():
    obs = torch.randn(2, 10, 2)
    with pytest.raises(ValueError, match="context_len"):
        multistep_predict(CountingModel(), obs, obs, 10)
    with pytest.raises(ValueError, match="horizon"):
        multistep_predict(CountingModel(), obs, obs, 5, 6)
    with pytest.raises(ValueError, match="actions"):
        multistep_predict(CountingModel(), obs, obs[:, :9], 5)


def test_prediction_loss_matches_metrics_and_imputation_loss_trains():
    model = _acrkn()
    g = torch.Generator().manual_seed(0)
    obs, act = torch.randn(4, 12, 2, generator=g, dtype=DT), torch.randn(4, 12, 2, generator=g, dtype=DT)
    mask = imputation_mask((4, 12), 0.5, 2, g)
    mean, var = model(obs, act, mask)
    torch.testing.assert_close(prediction_loss(model, obs, act, mask),
                               gaussian_nll(mean[:, :-1], var[:, :-1], obs[:, 1:]))
    torch.testing.assert_close(prediction_loss(model, obs, act, mask, loss="rmse"),
                               rmse(mean[:, :-1], obs[:, 1:]))
    with pytest.raises(ValueError, match="loss"):
        prediction_loss(model, obs, act, mask, loss="l1")
    # a smooth toy system: training with the imputation loss lowers the loss
    t = torch.linspace(0, 6, 40, dtype=DT)
    X = torch.stack([torch.sin(t + p) for p in torch.linspace(0, 3, 16, dtype=DT)])[..., None].repeat(1, 1, 2)
    A = torch.cos(torch.stack([t] * 16))[..., None].repeat(1, 1, 2)
    lf = imputation_loss_fn(model, 0.5, 5)
    with torch.no_grad():
        before = float(lf((X, A), torch.Generator().manual_seed(9)))
    fit(lf, model, (X, A), 8, 8, lr=1e-2, crop_len=20, progress=False)
    with torch.no_grad():
        after = float(lf((X, A), torch.Generator().manual_seed(9)))
    assert after < before


# ----------------------------------------------------------------------------- metrics

def test_rmse_against_numpy():
    g = np.random.default_rng(0)
    p, y = g.normal(size=(3, 5, 2)), g.normal(size=(3, 5, 2))
    mask = g.random((3, 5)) < 0.6
    P, Y, M = torch.tensor(p), torch.tensor(y), torch.tensor(mask)
    assert np.isclose(float(rmse(P, Y)), np.sqrt(np.mean((p - y) ** 2)))
    assert np.isclose(float(rmse(P, Y, M)), np.sqrt(np.mean(((p - y) ** 2)[mask])))
    per_t = rmse(P, Y, dim=(0, 2)).numpy()
    assert np.allclose(per_t, np.sqrt(np.mean((p - y) ** 2, axis=(0, 2))))
    full_mask = np.broadcast_to(mask[..., None], p.shape)
    assert np.isclose(float(rmse(P, Y, torch.tensor(full_mask))), float(rmse(P, Y, M)))


def test_gaussian_nll_against_scipy():
    g = np.random.default_rng(1)
    mu, y = g.normal(size=(4, 6, 3)), g.normal(size=(4, 6, 3))
    var = g.uniform(0.1, 2.0, size=(4, 6, 3))
    mask = g.random((4, 6)) < 0.5
    ref = -norm.logpdf(y, mu, np.sqrt(var))
    T = lambda a: torch.tensor(a)  # noqa: E731
    assert np.isclose(float(gaussian_nll(T(mu), T(var), T(y))), ref.mean())
    assert np.isclose(float(gaussian_nll(T(mu), T(var), T(y), T(mask))), ref[mask].mean())
    assert np.allclose(gaussian_nll(T(mu), T(var), T(y), dim=(0, 1)).numpy(), ref.mean(axis=(0, 1)))


def test_denormalized_metrics_relations():
    g = torch.Generator().manual_seed(0)
    mean_n, y_n = torch.randn(5, 7, 2, generator=g, dtype=DT), torch.randn(5, 7, 2, generator=g, dtype=DT)
    var_n = torch.rand(5, 7, 2, generator=g, dtype=DT) + 0.1
    mu, sd = torch.tensor([1.0, -2.0], dtype=DT), torch.tensor([0.5, 3.0], dtype=DT)
    torch.testing.assert_close(normalize(denormalize(y_n, mu, sd), mu, sd), y_n)
    m_o, v_o, y_o = denormalize(mean_n, mu, sd), denormalize_var(var_n, sd), denormalize(y_n, mu, sd)
    # NLL in original units = NLL normalized + mean log std (change of variables)
    torch.testing.assert_close(gaussian_nll(m_o, v_o, y_o), gaussian_nll(mean_n, var_n, y_n) + sd.log().mean())
    # RMSE per dimension scales with std
    torch.testing.assert_close(rmse(m_o, y_o, dim=(0, 1)), sd * rmse(mean_n, y_n, dim=(0, 1)))


def test_metric_bad_inputs():
    x = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match="target"):
        rmse(x, torch.zeros(2, 3, 1))
    with pytest.raises(ValueError, match="mask"):
        rmse(x, x, torch.ones(3, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask"):
        rmse(x, x, torch.zeros(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="var"):
        gaussian_nll(x, torch.zeros_like(x), x)
    with pytest.raises(ValueError, match="var"):
        gaussian_nll(x, torch.ones(2, 3, 1), x)
    with pytest.raises(ValueError, match="std"):
        normalize(x, 0.0, torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match="std"):
        denormalize(x, 0.0, torch.ones(3))


def test_multistep_metrics_matches_manual_windows():
    from pgm_wm.training import multistep_metrics

    g = torch.Generator().manual_seed(4)
    obs, act = torch.randn(2, 30, 2, generator=g, dtype=DT), torch.randn(2, 30, 2, generator=g, dtype=DT)
    mu, sd = torch.tensor([1.0, -1.0], dtype=DT), torch.tensor([2.0, 0.5], dtype=DT)
    res = multistep_metrics(CountingModel(), obs, act, 5, 4, stride=7, obs_mean=mu, obs_std=sd)
    starts = list(range(0, 30 - 9 + 1, 7))
    assert res["mean"].shape == (2 * len(starts), 4, 2)
    errs = []
    for b in range(2):
        for s in starts:
            pred = obs[b, s + 4] + torch.arange(1, 5, dtype=DT)[:, None]  # counting model: last obs + k
            errs.append((denormalize(pred, mu, sd) - denormalize(obs[b, s + 5:s + 9], mu, sd)) ** 2)
    want = torch.stack(errs).mean(dim=(0, 2)).sqrt()
    torch.testing.assert_close(res["rmse"], want)
    assert res["nll"].shape == (4,)

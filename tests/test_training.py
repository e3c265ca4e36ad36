"""Tests for pgm_wm.training and pgm_wm.metrics: the observation masks, crops, the one loss
factory, the one fit loop (budget, early stopping, keep-best, non-finite stops), and the metrics
against direct numpy/scipy computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from pgm_wm.acrkn import AcRKN, MLPControl
from pgm_wm.datasets.windows import make_windows
from pgm_wm.metrics import denormalize, denormalize_var, gaussian_nll, normalize, rmse
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder

from _helpers import seq_data, small_hip, small_mts3
from pgm_wm.training import (
    fit,
    floor_variance,
    imputation_loss_fn,
    observation_mask,
    prediction_loss,
    random_crop,
    set_seed,
    show_progress,
)

DT = torch.float64
assert_close = torch.testing.assert_close


# ----------------------------------------------------------------------------- masks and seeds

def test_observation_mask_fraction_and_context():
    g = torch.Generator().manual_seed(0)
    B, T, c, p = 200, 150, 5, 0.25
    mask = observation_mask((B, T), p, c, generator=g)
    assert mask.dtype == torch.bool and mask.shape == (B, T)
    assert bool(mask[:, :c].all())
    rest = mask[:, c:].double()
    n = rest.numel()
    sd = math.sqrt(p * (1 - p) / n)
    assert abs(float(rest.mean()) - p) < 5 * sd
    # per-position frequencies are also close to p (no position bias after the context)
    col = rest.mean(0)
    assert float((col - p).abs().max()) < 5 * math.sqrt(p * (1 - p) / B)


def test_observation_mask_is_seeded_and_resampled():
    m1 = observation_mask((4, 50), 0.5, 3, generator=torch.Generator().manual_seed(1))
    m2 = observation_mask((4, 50), 0.5, 3, generator=torch.Generator().manual_seed(1))
    assert torch.equal(m1, m2)
    g = torch.Generator().manual_seed(1)
    a, b = observation_mask((4, 50), 0.5, 3, generator=g), observation_mask((4, 50), 0.5, 3, generator=g)
    assert not torch.equal(a, b)
    assert bool(observation_mask((3, 4), 0.0, 10).all())  # context longer than T: all kept
    assert not bool(observation_mask((3, 40), 0.0, 2)[:, 2:].any())


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
    assert len(hist.train_loss) == 60 == len(hist.valid_loss) == len(hist.epoch_time)
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
        observation_mask((2, 3), 1.5)
    with pytest.raises(ValueError, match="shape"):
        observation_mask((2, 3, 4), 0.5)
    with pytest.raises(ValueError, match="context_steps"):
        observation_mask((2, 3), 0.5, -1)


# ----------------------------------------------------------------------------- world-model helpers

def _acrkn(m=4, do=2, da=2):
    torch.manual_seed(0)
    return AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, 3, 1), MLPControl(da, m, (16,)),
                 BeliefDecoder(m, do, (16,), (16,))).double()


def test_prediction_loss_matches_metrics_and_imputation_loss_trains():
    model = _acrkn()
    g = torch.Generator().manual_seed(0)
    obs, act = torch.randn(4, 12, 2, generator=g, dtype=DT), torch.randn(4, 12, 2, generator=g, dtype=DT)
    mask = observation_mask((4, 12), 0.5, 2, generator=g)
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




# ----------------------------------------------------------------------------- one mask generator

def test_window_drops_keep_or_drop_whole_windows():
    gen = torch.Generator().manual_seed(0)
    m = observation_mask((400, 60), 1.0, 20, window=10, window_drop_prob=0.5, generator=gen)
    assert m.shape == (400, 60) and m.dtype == torch.bool
    assert m[:, :20].all()
    w = m.reshape(400, 6, 10)
    assert ((w.all(-1)) | (~w.any(-1))).all()  # whole windows kept or dropped
    assert abs(float((~w[:, 2:].any(-1)).double().mean()) - 0.5) < 0.03
    m2 = observation_mask((400, 60), 0.7, 0, window=10, generator=gen)
    assert abs(float(m2.double().mean()) - 0.7) < 0.02
    m3 = observation_mask((2, 23), 0.0, 10, window=10)
    assert m3[:, :10].all() and not m3[:, 10:].any()


def test_fixed_open_loop_cut_masks_are_seeded_and_hide_the_open_loop_part():
    a = observation_mask((50, 10), 0.5, 1, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, observation_mask((50, 10), 0.5, 1, generator=torch.Generator().manual_seed(3)))
    assert bool(a[:, 0].all()) and 0.35 < float(a[:, 1:].float().mean()) < 0.65
    b = observation_mask((50, 10), 1.0, 1, open_loop_prob=1.0, open_loop_start=4)
    assert bool(b[:, :4].all()) and not bool(b[:, 4:].any())


def test_open_loop_cut_hides_everything_after_a_random_cut():
    g = torch.Generator().manual_seed(0)
    m = observation_mask((500, 30), 1.0, 4, open_loop_prob=0.5, generator=g)
    assert bool(m[:, :4].all())
    cut = m.sum(1)  # with keep_prob 1 the kept steps are exactly 0..cut-1
    assert torch.equal(m, torch.arange(30)[None, :] < cut[:, None])
    # half of the sequences get a cut, uniform on [4, 30): a cut at 4..29 leaves 4..29 steps
    frac_cut = float((cut < 30).double().mean())
    assert 0.5 * 25 / 26 - 0.07 < frac_cut < 0.5 + 0.07 and int(cut.min()) >= 4


def test_observation_mask_bad_inputs():
    with pytest.raises(ValueError, match="window"):
        observation_mask((2, 8), 0.5, window=0)
    with pytest.raises(ValueError, match="window_drop_prob"):
        observation_mask((2, 8), 0.5, window=4, window_drop_prob=-0.1)
    with pytest.raises(ValueError, match="window_drop_prob"):
        observation_mask((2, 8), 0.5, window_drop_prob=0.5)
    with pytest.raises(ValueError, match="open_loop_prob"):
        observation_mask((2, 8), 0.5, open_loop_prob=2.0)
    with pytest.raises(ValueError, match="open_loop_start"):
        observation_mask((2, 8), 0.5, open_loop_prob=1.0, open_loop_start=9)


# ----------------------------------------------------------------------------- one loss factory

def test_two_scale_imputation_loss_masks_are_real():
    """The masking probabilities are real arguments (the authors' code hard-codes one)."""
    model = small_mts3(H=4)
    obs, act, _ = seq_data(3, 12)
    gen = torch.Generator().manual_seed(0)
    full = imputation_loss_fn(model, 1.0, 4, window=4, open_loop_start=4)((obs, act), gen)
    assert_close(full, prediction_loss(model, obs, act, None))
    hidden = imputation_loss_fn(model, 0.0, 4, window=4, open_loop_start=4)((obs, act), gen)
    mask = torch.zeros(3, 12, dtype=torch.bool)
    mask[:, :4] = True
    assert_close(hidden, prediction_loss(model, obs, act, mask))


def test_loss_factory_on_hip_windows_reaches_every_part_of_the_model():
    obs, act, valid = seq_data(4, 24)
    w = make_windows(obs, act, 6, valid)
    for encoder in ("ba", "recurrent"):
        hip = small_hip(encoder=encoder)
        loss = imputation_loss_fn(hip, 0.5, 1, min_var=1e-8)(w.tensors(), torch.Generator().manual_seed(0))
        assert loss.ndim == 0 and torch.isfinite(loss)
        loss.backward()
        for part in (hip.context_encoder, hip.task_transform, hip.acrkn.control, hip.acrkn.transition):
            grads = [p.grad for p in part.parameters() if p.requires_grad]
            assert any(gr is not None and float(gr.abs().sum()) > 0 for gr in grads), type(part).__name__


def test_floor_variance_only_lifts_tiny_variances():
    model = lambda x: (x, x.abs())  # noqa: E731
    x = torch.tensor([0.0, -1e-12, 0.5, -2.0], dtype=DT)
    mean, var = floor_variance(model, 1e-8)(x)
    assert torch.equal(mean, x)
    assert torch.equal(var, torch.tensor([1e-8, 1e-8, 0.5, 2.0], dtype=DT))
    with pytest.raises(ValueError, match="min_var"):
        floor_variance(model, 0.0)


def test_filtering_loss_is_the_nll_of_the_targets_with_the_drawn_mask():
    g = torch.Generator().manual_seed(0)
    obs, targets = torch.randn(3, 10, 2, generator=g, dtype=DT), torch.randn(3, 10, 1, generator=g, dtype=DT)
    valid = torch.rand(3, 10, generator=g) < 0.8
    seen = {}

    def filt(o, mask):
        seen["mask"] = mask
        return o[..., :1] * 0.5, torch.full_like(o[..., :1], 2.0)

    lf = imputation_loss_fn(filt, 0.6, 2, filtering=True)
    loss = lf((obs, valid, targets), torch.Generator().manual_seed(5))
    want_mask = observation_mask((3, 10), 0.6, 2, generator=torch.Generator().manual_seed(5)) & valid
    assert torch.equal(seen["mask"], want_mask)
    ref = 0.5 * (math.log(2 * math.pi * 2.0) + (targets - 0.5 * obs[..., :1]) ** 2 / 2.0).mean()
    torch.testing.assert_close(loss, ref)


# ----------------------------------------------------------------------------- fit: budget, patience, stops

def _linear_fit(**kw):
    X, y = _regression_problem()
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    hist = fit(lambda b, g: ((b[0] @ w - b[1]) ** 2).mean(), [w], (X, y), 32, **{"progress": False, **kw})
    return w, hist


def test_fit_stops_at_the_cpu_budget():
    import time

    t0 = time.process_time()
    _, hist = _linear_fit(epochs=None, budget_s=0.3)
    used = time.process_time() - t0
    assert hist.stopped == "budget" and hist.cpu_time >= 0.3
    assert used < 0.3 + 1.0  # one batch at most past the budget, plus set-up
    _, capped = _linear_fit(epochs=2, budget_s=100.0)
    assert capped.stopped == "epochs" and capped.epochs == 2 and capped.steps == [8, 16]


@pytest.mark.parametrize("progress", [False, True])
def test_fit_with_max_steps_only_stops_there(progress):
    # max_steps alone (no epoch cap, no budget) used to crash building the progress bar
    _, hist = _linear_fit(epochs=None, max_steps=13, progress=progress)
    assert hist.stopped == "budget" and hist.steps[-1] == 13 and hist.epochs == 2


def test_fit_early_stopping_with_patience_and_keep_best_on_parameters():
    X, y = _regression_problem()
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    metric = iter([3.0, 1.0, 2.0, 2.5, 0.5, 0.1])
    saved = []

    def valid():
        saved.append(w.detach().clone())
        return next(metric)

    hist = fit(lambda b, g: ((b[0] @ w - b[1]) ** 2).mean(), [w], (X, y), 64, 6, lr=0.1, valid_fn=valid,
               patience=2, progress=False)
    assert hist.stopped == "patience" and hist.epochs == 4 and hist.best_epoch == 1
    assert hist.valid_loss == [3.0, 1.0, 2.0, 2.5] and hist.best_valid_loss == 1.0
    assert torch.equal(w.detach(), saved[1])  # keep-best restores a parameter list too


def test_fit_stops_at_the_first_non_finite_loss_naming_epoch_and_sequences():
    g = torch.Generator().manual_seed(0)
    obs, act = torch.randn(16, 12, 2, generator=g, dtype=DT), torch.randn(16, 12, 2, generator=g, dtype=DT)
    obs[11, 4, 0] = float("nan")
    model = _acrkn()
    for loss in ("mse", "nll"):
        with pytest.raises(ValueError, match=r"loss_fn: .*epoch 0, batch \d+ \(sequence indices \[.*\b11\b.*\]\).*obs"):
            fit(imputation_loss_fn(model, 1.0, 1, loss), model, (obs, act), 4, 3, progress=False)
        assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
    # a non-finite value that reaches the loss itself: the same stop, the parameters stay finite
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _regression_problem()
    y[100] = float("inf")
    with pytest.raises(ValueError, match=r"loss_fn: non-finite loss .* epoch 0, batch \d+ \(sequence indices .*\b100\b"):
        fit(lambda b, g: ((b[0] @ w - b[1]) ** 2).mean(), [w], (X, y), 32, 2, progress=False)
    assert bool(torch.isfinite(w).all())


def test_fit_with_a_sampler_and_bad_budget_arguments():
    w = torch.zeros(1, dtype=DT, requires_grad=True)
    sample = lambda g: torch.randn(8, generator=g, dtype=DT) + 2.0  # noqa: E731
    hist = fit(lambda b, g: ((b - w) ** 2).mean(), [w], sample, 8, 30, lr=0.1, max_batches=5, progress=False)
    assert hist.steps[-1] == 150 and abs(float(w.detach()) - 2.0) < 0.2
    with pytest.raises(ValueError, match="max_batches"):
        fit(lambda b, g: ((b - w) ** 2).mean(), [w], sample, 8, 3, progress=False)
    with pytest.raises(ValueError, match="epochs"):
        _linear_fit(epochs=None)
    with pytest.raises(ValueError, match="budget_s"):
        _linear_fit(epochs=1, budget_s=0.0)
    with pytest.raises(ValueError, match="patience"):
        _linear_fit(epochs=1, patience=2)


def test_progress_follows_the_environment(monkeypatch):
    monkeypatch.setenv("PGM_WM_PROGRESS", "0")
    assert show_progress(None) is False and show_progress(True) is True
    monkeypatch.setenv("PGM_WM_PROGRESS", "1")
    assert show_progress(None) is True and show_progress(False) is False
    monkeypatch.delenv("PGM_WM_PROGRESS")
    # unset: a bar in interactive use only (a terminal, or a Jupyter kernel), not in logs
    import io
    import sys

    monkeypatch.delitem(sys.modules, "ipykernel", raising=False)

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert show_progress(None) is False
    monkeypatch.setattr(sys, "stderr", Terminal())
    assert show_progress(None) is True

"""Tests for pgm_wm.evaluation: open-loop prediction without leakage, the one open-loop evaluator
(per-horizon and sliding-window metrics, divergence as inf), and the window-wise evaluation of
Chapter 5, each against an explicit loop or a direct computation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.acrkn import AcRKN, DifferenceReadout, MLPControl
from pgm_wm.datasets.windows import HiPWindows, context_features, make_windows
from pgm_wm.evaluation import (
    evaluate_open_loop,
    evaluate_windows,
    infer_trajectory,
    latent_pca,
    multistep_predict,
    predict_windows,
    sliding_windows,
    window_rmse,
)
from pgm_wm.metrics import denormalize
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder
from pgm_wm.training import observation_mask

from _helpers import seq_data, small_hip, small_mts3

DT = torch.float64
assert_close = torch.testing.assert_close


class CountingModel(torch.nn.Module):
    """A toy world model whose normalized difference is always +1: o_hat_{t+1} = m_t + 1."""

    def __init__(self):
        super().__init__()
        self.readout = DifferenceReadout(2, var_floor=0.0)

    def forward(self, obs, actions, mask):
        delta = torch.ones_like(obs)
        return self.readout(obs, mask, delta + 0 * actions.sum(-1, keepdim=True), torch.ones_like(obs))


def _acrkn(m=4, do=2, da=2):
    torch.manual_seed(0)
    return AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, 3, 1), MLPControl(da, m, (16,)),
                 BeliefDecoder(m, do, (16,), (16,))).double()


def test_sliding_windows():
    x = torch.arange(2 * 10, dtype=DT).reshape(2, 10)
    w = sliding_windows(x, 4, 3)
    assert w.shape == (2 * 3, 4)
    torch.testing.assert_close(w[1], x[0, 3:7])
    torch.testing.assert_close(w[3], x[1, 0:4])


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
        multistep_predict(CountingModel(), obs, obs, 11)
    with pytest.raises(ValueError, match="horizon"):
        multistep_predict(CountingModel(), obs, obs, 10)        # no action left to predict with
    with pytest.raises(ValueError, match="horizon"):
        multistep_predict(CountingModel(), obs, obs, 5, 7)
    with pytest.raises(ValueError, match="actions"):
        multistep_predict(CountingModel(), obs, obs[:1], 5)


def test_per_horizon_open_loop_metrics_match_manual_windows():
    g = torch.Generator().manual_seed(4)
    obs, act = torch.randn(2, 30, 2, generator=g, dtype=DT), torch.randn(2, 30, 2, generator=g, dtype=DT)
    mu, sd = torch.tensor([1.0, -1.0], dtype=DT), torch.tensor([2.0, 0.5], dtype=DT)
    res = evaluate_open_loop(CountingModel(), obs, act, 5, 4, stride=7, obs_mean=mu, obs_std=sd)
    starts = list(range(0, 30 - 9 + 1, 7))
    assert res.mean.shape == (2 * len(starts), 4, 2)
    errs = []
    for b in range(2):
        for s in starts:
            pred = obs[b, s + 4] + torch.arange(1, 5, dtype=DT)[:, None]  # counting model: last obs + k
            errs.append((denormalize(pred, mu, sd) - denormalize(obs[b, s + 5:s + 9], mu, sd)) ** 2)
    want = torch.stack(errs).mean(dim=(0, 2)).sqrt()
    torch.testing.assert_close(res.rmse, want)
    assert res.nll.shape == (4,)


def test_per_horizon_nll_matches_the_closed_form():
    g = torch.Generator().manual_seed(4)
    obs, act = torch.randn(2, 20, 2, generator=g, dtype=DT), torch.randn(2, 20, 2, generator=g, dtype=DT)
    res = evaluate_open_loop(CountingModel(), obs, act, 5)
    # counting model: mean = obs[4] + k, var = 1 -> NLL = 0.5 (log 2 pi + err^2)
    err2 = (obs[:, 4:5] + torch.arange(1, 16, dtype=DT)[None, :, None] - obs[:, 5:]) ** 2
    assert_close(res.nll, (0.5 * (np.log(2 * np.pi) + err2)).mean((0, 2)))
    assert_close(res["rmse"], err2.mean((0, 2)).sqrt())


def test_evaluate_open_loop_uses_only_the_context_and_original_units():
    model = small_mts3(H=4)
    obs, act, _ = seq_data(2, 16, seed=0)
    mu, sd = torch.tensor([1.0, -2.0, 0.5], dtype=DT), torch.tensor([2.0, 0.5, 3.0], dtype=DT)
    res = evaluate_open_loop(model, obs, act, 8, obs_mean=mu, obs_std=sd, metric_window=3)
    obs2 = obs.clone()
    obs2[:, 8:] += 5.0  # future observations must not matter
    res2 = evaluate_open_loop(model, obs2, act, 8, obs_mean=mu, obs_std=sd, metric_window=3)
    assert_close(res.mean, res2.mean)
    mask = torch.zeros(2, 15, dtype=torch.bool)
    mask[:, :8] = True
    mean, var = model(torch.where(mask[..., None], obs[:, :15], 0.0), act[:, :15], mask)
    assert_close(res.mean, mean[:, 7:] * sd + mu)
    assert_close(res.var, var[:, 7:] * sd**2)
    assert_close(res.target, obs[:, 8:] * sd + mu)
    err = ((res.mean - res.target) ** 2).mean((0, 2))
    assert_close(res.rmse[2], err[:3].mean().sqrt())


def test_evaluate_open_loop_reports_divergence_as_inf():
    def diverging(o, a, mk):  # NaN from output index 8 on = horizon index 5 (context 4)
        mean = torch.zeros(o.shape, dtype=o.dtype)
        mean[:, 8:] = float("nan")
        return mean, torch.ones_like(mean)

    obs, act, _ = seq_data(2, 16, seed=0)
    one = torch.ones(3, dtype=DT)
    res = evaluate_open_loop(diverging, obs, act, 4, obs_mean=0 * one, obs_std=one, metric_window=3)
    assert torch.isfinite(res.rmse[:5]).all() and torch.isfinite(res.nll[:5]).all()
    assert torch.isinf(res.rmse[5:]).all() and torch.isinf(res.nll[5:]).all()


def test_infer_trajectory_equals_explicit_window_loop_and_is_causal():
    n, T, k = 2, 23, 5
    obs, act, valid = seq_data(n, T, p_valid=0.85)
    hip = small_hip()
    shift, scale = torch.full((3,), 0.1, dtype=DT), torch.full((3,), 0.5, dtype=DT)
    mean, var, t_mean, t_var = infer_trajectory(hip, obs, act, k, valid, shift, scale)
    assert mean.shape == (n, 20, 3) and t_mean.shape == (n, 4, 4)
    with torch.no_grad():
        for j in range(4):
            sl = slice(j * k, (j + 1) * k)
            if j == 0:
                ctx, cm = None, None
            else:
                ctx, cm = context_features(obs[:, sl.start - k:sl.start], act[:, sl.start - k:sl.start],
                                           valid[:, sl.start - k:sl.start], shift, scale)
            mu, v, tm, tv = hip.predict(obs[:, sl], act[:, sl], valid[:, sl], ctx, cm)
            torch.testing.assert_close(mean[:, sl], mu)
            torch.testing.assert_close(var[:, sl], v)
            torch.testing.assert_close(t_mean[:, j], tm)
    # causality: changing o_s (and a_s) never changes a prediction made at an index < s
    for s in (3, 5, 11, 15):
        obs2, act2 = obs.clone(), act.clone()
        obs2[:, s:] += 5.0
        act2[:, s:] -= 5.0
        m2, _, _, _ = infer_trajectory(hip, obs2, act2, k, valid, shift, scale)
        torch.testing.assert_close(m2[:, :s], mean[:, :s], rtol=0, atol=0)
        assert not torch.allclose(m2[:, s:], mean[:, s:])


def test_predict_windows_hides_masked_observations_and_window_rmse_units():
    obs, act, valid = seq_data(3, 24)
    w = make_windows(obs, act, 6, valid)
    hip = small_hip()
    mask = observation_mask((w.n_windows, 6), 1.0, 1, open_loop_prob=1.0, open_loop_start=3)
    mu, _ = predict_windows(hip, w, mask)
    w_bad = HiPWindows(**{**w.__dict__, "obs": torch.where(mask[..., None], w.obs, torch.nan)})
    mu_bad, _ = predict_windows(hip, w_bad, mask)
    torch.testing.assert_close(mu_bad, mu)
    std = torch.tensor([2.0, 0.5, 3.0], dtype=DT)
    got = window_rmse(mu, w, std, from_step=2)
    err = ((mu[:, 2:5] - w.obs[:, 3:]) * std).numpy()
    assert abs(float(got) - float(np.sqrt((err**2).mean()))) < 1e-12
    # a plain world model with the previous window as history
    mu_h, _ = predict_windows(hip.acrkn, w, mask, use_context=False, use_history=True)
    ho, ha, hv = w.with_history()
    full_mask = torch.cat([hv[:, :6], mask & w.valid], 1)
    ref, _ = hip.acrkn(torch.where(full_mask[..., None], ho, 0.0), ha, full_mask)
    torch.testing.assert_close(mu_h, ref[:, 6:])
    res = evaluate_windows(hip, w, std)
    assert set(res) == {"one_step", "one_step_imp", "multi_step", "multi_step_imp"}
    assert all(np.isfinite(v) and v > 0 for v in res.values())


def test_latent_pca_matches_numpy_svd():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(40, 5, generator=g, dtype=DT) @ torch.randn(5, 5, generator=g, dtype=DT)
    scores, ratio = latent_pca(x, 2)
    xc = x.numpy() - x.numpy().mean(0)
    u, s, vt = np.linalg.svd(xc, full_matrices=False)
    np.testing.assert_allclose(ratio.numpy(), (s**2 / (s**2).sum())[:2], rtol=1e-10)
    np.testing.assert_allclose(np.abs(scores.numpy()), np.abs(xc @ vt[:2].T), rtol=1e-8, atol=1e-10)


def test_evaluation_bad_inputs():
    obs = torch.randn(2, 10, 2)
    with pytest.raises(ValueError, match="metric_window"):
        evaluate_open_loop(CountingModel(), obs, obs, 5, metric_window=6)
    with pytest.raises(ValueError, match="obs_std"):
        evaluate_open_loop(CountingModel(), obs, obs, 5, obs_mean=torch.zeros(2))
    with pytest.raises(ValueError, match="n_components"):
        latent_pca(torch.randn(4, 3), 5)


def test_trajectory_world_model_pads_to_windows_and_equals_infer_trajectory():
    from pgm_wm.evaluation import trajectory_world_model

    obs, act, valid = seq_data(2, 23, p_valid=0.8)
    hip = small_hip()
    shift, scale = torch.full((3,), 0.1, dtype=DT), torch.full((3,), 0.5, dtype=DT)
    f = trajectory_world_model(hip, 5, shift, scale)
    with torch.no_grad():
        mean, var = f(obs, act, valid)
    assert mean.shape == var.shape == obs.shape
    pad = lambda x: torch.cat([x, torch.zeros_like(x[:, :2])], 1)  # noqa: E731  23 -> 25 steps
    ref_mean, ref_var, _, _ = infer_trajectory(hip, pad(obs), pad(act), 5, pad(valid), shift, scale)
    assert_close(mean, ref_mean[:, :23])
    assert_close(var, ref_var[:, :23])
    res = evaluate_open_loop(f, obs, act, 10)
    assert res.mean.shape == (2, 13, 3) and bool(torch.isfinite(res.rmse).all())


def test_forecast_past_the_end_of_the_data_needs_no_dummy_observations():
    """issue 24: the observations that exist (the context) and the planned actions are enough; the
    result equals the old call that padded the observations with dummies."""
    torch.manual_seed(0)
    model = AcRKN(ObservationEncoder(2, 3, (8,)), LocallyLinearTransition(3, 2, 1), MLPControl(1, 3, (8,)),
                  BeliefDecoder(3, 2, (8,), (8,))).double()
    c, h = 6, 9
    obs = torch.randn(2, c, 2, dtype=torch.float64)                 # only the context exists
    act = torch.randn(2, c + h - 1, 1, dtype=torch.float64)         # the planned actions
    mean, var = multistep_predict(model, obs, act, c, h)
    dummy = torch.cat([obs, torch.full((2, h - 1, 2), 123.0, dtype=torch.float64)], 1)
    ref_mean, ref_var = multistep_predict(model, dummy, act, c, h)
    torch.testing.assert_close(mean, ref_mean, rtol=0, atol=0)
    torch.testing.assert_close(var, ref_var, rtol=0, atol=0)
    assert mean.shape == (2, h, 2)
    with pytest.raises(ValueError, match="^actions"):
        multistep_predict(model, obs, act[:1], c, h)

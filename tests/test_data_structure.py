"""The chapter-4/5/6 datasets with the structure (issue 12, item 1): each diagnostic of
pgm_wm.datasets.structure is asserted here (numbers in data/README.md), plus closed-form
checks of the new simulators."""

from __future__ import annotations

import numpy as np
import pytest

from pgm_wm.datasets import load
from pgm_wm.datasets.memory_arm import DEFAULT_PARAMS as MEMORY_PARAMS
from pgm_wm.datasets.memory_arm import initial_state, rollout_memory_arm
from pgm_wm.datasets.slow_payload_arm import DEFAULT_PARAMS as SLOW_PARAMS
from pgm_wm.datasets.slow_payload_arm import tank_payload
from pgm_wm.datasets.structure import hidden_payload_checks, memory_checks, slow_payload_checks
from pgm_wm.datasets.two_link_arm import rollout_two_link_arm
from pgm_wm.datasets.hidden_payload_arm import DEFAULT_PARAMS as HIDDEN_PARAMS


def test_memory_arm_history_still_matters_at_25_and_50_steps():
    r = memory_checks()
    # different pasts, same future actions: still far apart after 1 and 2 s
    # (the old hysteresis_arm: 0.54 rad at the start, 0.05 rad after 1 s)
    assert r["divergence_1s"] > 0.08 and r["divergence_2s"] > 0.08
    assert r["divergence_2s"] > 0.15 * r["divergence_0s"]
    for h in (25, 50):
        assert r[f"linear_h{h}_long"] < 0.85 * r[f"linear_h{h}_short"], h
        assert r[f"rf_h{h}_long"] < 0.8 * r[f"rf_h{h}_short"], h


def test_memory_arm_play_operators_follow_their_closed_form():
    """From the all-zero state, under a monotone rising pressure, play operator i outputs
    max(p - r_i, 0), so H = sum_i w_i max(p - r_i, 0) exactly."""
    p = {**MEMORY_PARAMS}
    T = 400
    u = np.repeat(np.linspace(0.0, 0.9, T)[None, :, None], 2, axis=2)
    rec, _ = rollout_memory_arm(u, initial_state(1, p), p)
    pr = rec["pressure"][0, :, 0]
    assert (np.diff(pr) >= 0).all()
    expected = sum(w * np.maximum(pr - r, 0.0) for w, r in zip(p["play_weights"], p["play_radii"]))
    np.testing.assert_allclose(rec["hysteresis"][0, :, 0], expected, atol=1e-12)
    # and coming back down the output lags: a hysteresis loop of width sum_i 2 w_i r_i at the bottom
    down = np.repeat(np.linspace(0.9, -0.9, T)[None, :, None], 2, axis=2)
    up = np.repeat(np.linspace(-0.9, 0.9, T)[None, :, None], 2, axis=2)
    rec2, _ = rollout_memory_arm(np.concatenate([down, up], 1), initial_state(1, p), p)
    H = rec2["hysteresis"][0, :, 0]
    pr2 = rec2["pressure"][0, :, 0]
    i_down = T // 2 + np.argmin(np.abs(pr2[T // 2:T] - 0.0))
    i_up = T + T // 2 + np.argmin(np.abs(pr2[T + T // 2:] - 0.0))
    width = sum(2 * w * r for w, r in zip(p["play_weights"], p["play_radii"]))
    assert H[i_down] - H[i_up] == pytest.approx(width, rel=0.1)


def test_hidden_payload_matters_but_a_short_window_does_not_reveal_it():
    r = hidden_payload_checks()
    assert r["oracle_nominal"] > 4 * r["oracle_true"]
    assert r["oracle_true"] < 0.05 * r["repeat_last"]
    assert r["identify_target5_r2"] < 0.1 and r["identify_target12_r2"] < 0.2
    assert r["identify_context50_r2"] > 0.6 and r["identify_context25_r2"] > r["identify_target12_r2"] + 0.3


def test_hidden_payload_leaves_no_static_trace():
    """Horizontal plane: once settled on a constant target the arm sits there whatever the
    payload, while the transient on the way depends strongly on it."""
    p = HIDDEN_PARAMS
    n, T = 2, 500
    ref = np.tile(np.array([0.4, -0.6]), (n, T, 1))
    x, _ = rollout_two_link_arm(np.zeros((n, 4)), ref, np.zeros((n, T, 2)),
                                np.array([[0.0] * T, [3.0] * T]), p)
    np.testing.assert_allclose(x[:, -1, :2], ref[:, -1], atol=2e-3)
    assert np.abs(x[0, :20, :2] - x[1, :20, :2]).max() > 0.05


def test_hidden_payload_split_sizes_and_constant_payload():
    data = load("hidden_payload_arm", "train")
    pay = data.hidden["payload"].numpy()
    assert (pay == pay[:, :1]).all() and pay.min() >= 0 and pay.max() <= 3
    assert data.obs.shape == (192, 250, 4) and data.meta["action"] == "pd_target"


def test_slow_payload_is_predictable_across_the_8s_horizon_and_matters():
    r = slow_payload_checks()
    assert r["autocorr_1s"] > r["autocorr_2s"] > r["autocorr_4s"] > r["autocorr_8s"] > 0.9
    assert r["predict8s_r2_with_pump"] > 0.95 and r["predict8s_r2_with_pump"] > r["predict8s_r2_no_actions"] + 0.05
    assert r["oracle8s_nominal"] > 5 * r["oracle8s_true"]
    assert r["oracle8s_frozen"] > 1.5 * r["oracle8s_true"]


def test_slow_payload_tank_matches_its_recursion_and_data_is_positions_only():
    rng = np.random.default_rng(0)
    pump = rng.uniform(-1, 1, (3, 50))
    s0 = rng.standard_normal(3)
    s, m = tank_payload(s0, pump, SLOW_PARAMS)
    ref = np.empty_like(s)
    ref[:, 0] = s0
    for t in range(1, 50):
        ref[:, t] = ref[:, t - 1] + SLOW_PARAMS["pump_rate"] * SLOW_PARAMS["dt"] * pump[:, t - 1]
    np.testing.assert_allclose(s, ref, atol=1e-12)
    np.testing.assert_allclose(m, SLOW_PARAMS["payload_max"] / (1 + np.exp(-ref)), atol=1e-12)
    data = load("slow_payload_arm", "valid")
    assert data.obs_dim == 2 and data.action_dim == 3 and data.seq_len == 1500
    # the stored payload follows the stored pump actions through the tank recursion
    pay = data.hidden["payload"].double().numpy()
    s_back = np.log(pay / (SLOW_PARAMS["payload_max"] - pay))
    step = np.diff(s_back, axis=1)
    np.testing.assert_allclose(step, SLOW_PARAMS["pump_rate"] * SLOW_PARAMS["dt"] * data.actions[:, :-1, 2].double().numpy(),
                               atol=2e-4)

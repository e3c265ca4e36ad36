"""Tests for pgm_wm.datasets.windows: whole windows of the slow time scale, and the windows with
context sets of Chapter 5 (no context may contain its window or its future)."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pgm_wm.datasets.windows import (
    HiPWindows,
    context_features,
    make_windows,
    pad_to_windows,
    resample_past_contexts,
    to_windows,
)

from _helpers import seq_data

DT = torch.float64
SETTINGS = settings(max_examples=15, deadline=None)


def test_pad_and_reshape_to_windows_against_explicit_slices():
    x = torch.arange(2 * 11 * 3, dtype=DT).reshape(2, 11, 3)
    p = pad_to_windows(x, 4)
    assert p.shape == (2, 12, 3) and torch.equal(p[:, :11], x) and not bool(p[:, 11:].any())
    assert pad_to_windows(x[:, :8], 4) is not None and torch.equal(pad_to_windows(x[:, :8], 4), x[:, :8])
    w = to_windows(p, 4)
    for k in range(3):
        assert torch.equal(w[:, k], p[:, 4 * k:4 * k + 4])
    with pytest.raises(ValueError, match="window"):
        to_windows(x, 3)
    with pytest.raises(ValueError, match="window"):
        pad_to_windows(x, 0)
    with pytest.raises(ValueError, match="obs"):
        to_windows(torch.zeros(3), 1, name="obs")


@SETTINGS
@given(n=st.integers(1, 3), k=st.integers(2, 7), extra=st.integers(0, 6), include_first=st.booleans())
def test_windows_never_put_the_window_or_its_future_into_the_context(n, k, extra, include_first):
    T = 3 * k + extra
    obs, act, valid = seq_data(n, T, p_valid=0.9)
    w = make_windows(obs, act, k, valid, include_first=include_first)
    n_win = T // k
    assert w.n_windows == n * (n_win - (0 if include_first else 1))
    present = w.context_mask
    assert bool((w.context_time[present] < w.start[:, None].expand_as(present)[present]).all())
    assert bool((w.context_time[present] >= (w.start[:, None] - k).expand_as(present)[present]).all())
    # reference: the context of window (s, j) is built from raw steps (j-1)k .. jk-1 only
    for i in range(w.n_windows):
        s, t0 = int(w.seq[i]), int(w.start[i])
        torch.testing.assert_close(w.obs[i], obs[s, t0:t0 + k])
        if t0 == 0:
            assert not bool(w.context_mask[i].any())
            continue
        x, cm = context_features(obs[s, t0 - k:t0], act[s, t0 - k:t0], valid[s, t0 - k:t0])
        assert torch.equal(w.context_mask[i], cm)
        torch.testing.assert_close(w.context[i][cm], x[cm])
    # perturbing everything at or after a window's start leaves its context unchanged
    j = 1 if include_first else 0
    t0 = int(w.start[j])
    obs2, act2 = obs.clone(), act.clone()
    obs2[:, t0:] += 100.0
    act2[:, t0:] -= 100.0
    w2 = make_windows(obs2, act2, k, valid, include_first=include_first)
    torch.testing.assert_close(w2.context[j], w.context[j])


def test_resampled_contexts_come_from_earlier_windows_of_the_same_trajectory():
    obs, act, valid = seq_data(3, 40, p_valid=0.9)
    w = make_windows(obs, act, 5, valid)
    r = resample_past_contexts(w, torch.Generator().manual_seed(0))
    picked_other = 0
    for i in range(w.n_windows):
        # the resampled set is the (unchanged) context of a window j' of the same trajectory, j' <= j
        cands = [j for j in range(w.n_windows) if w.seq[j] == w.seq[i] and w.start[j] <= w.start[i]
                 and torch.equal(w.context[j], r.context[i]) and torch.equal(w.context_mask[j], r.context_mask[i])]
        assert cands, i
        picked_other += int(cands[-1] != i)
        present = r.context_mask[i]
        assert bool((r.context_time[i][present] < w.start[i]).all())
    assert picked_other > w.n_windows // 3           # most windows got an earlier context
    torch.testing.assert_close(r.obs, w.obs)
    assert not torch.equal(r.context, resample_past_contexts(w, torch.Generator().manual_seed(1)).context)


def test_context_features_standardize_the_difference_and_mask_pairs():
    obs, act, valid = seq_data(2, 6, p_valid=0.7)
    shift, scale = torch.tensor([0.1, -0.2, 0.3], dtype=DT), torch.tensor([0.5, 2.0, 1.5], dtype=DT)
    x, m = context_features(obs, act, valid, shift, scale)
    o = torch.where(valid[..., None], obs, 0.0)
    torch.testing.assert_close(x[..., -3:], (o[:, 1:] - o[:, :-1] - shift) / scale)
    torch.testing.assert_close(x[..., :3], o[:, :-1])
    torch.testing.assert_close(x[..., 3:5], act[:, :-1])
    assert torch.equal(m, valid[:, 1:] & valid[:, :-1])


def test_window_history_is_the_previous_window():
    obs, act, valid = seq_data(2, 20)
    w = make_windows(obs, act, 5, valid, hidden={"p": obs[..., 0]})
    ho, ha, hv = w.with_history()
    for i in range(w.n_windows):
        s, t0 = int(w.seq[i]), int(w.start[i])
        torch.testing.assert_close(ho[i], obs[s, t0 - 5:t0 + 5])
        torch.testing.assert_close(ha[i], act[s, t0 - 5:t0 + 5])
        torch.testing.assert_close(w.hidden["p"][i], obs[s, t0:t0 + 5, 0])
    sub = w.select(torch.tensor([2, 0]))
    assert isinstance(sub, HiPWindows) and sub.n_windows == 2
    torch.testing.assert_close(sub.obs[1], w.obs[0])


def test_bad_inputs_raise_value_error():
    obs, act, valid = seq_data(2, 12)
    with pytest.raises(ValueError, match="window_len"):
        make_windows(obs, act, 1)
    with pytest.raises(ValueError, match="window_len"):
        make_windows(obs, act, 7)  # only one window and no first window allowed
    with pytest.raises(ValueError, match="actions"):
        make_windows(obs, act[:, :5], 3)
    with pytest.raises(ValueError, match="valid"):
        make_windows(obs, act, 3, valid[:, :5])
    with pytest.raises(ValueError, match="diff_scale"):
        context_features(obs, act, None, None, torch.tensor([1.0, 0.0, 1.0], dtype=DT))

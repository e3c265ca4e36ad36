"""The real pneumatic-muscle arm (data/pam_arm.npz): faithful to its source, split by a stored seeded
draw, normalised with training statistics, and the action representation chosen by measurement."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.datasets import compute_stats, data_dir, load
from pgm_wm.datasets._io import read_npz
from pgm_wm.datasets.pam_arm import (SPLIT_FRACTIONS, SPLIT_SEED, action_representation_check, convert,
                                     find_source)
from pgm_wm.datasets.sequences import split_indices

SOURCE = find_source()
needs_source = pytest.mark.skipif(SOURCE is None, reason="pam_arm_subset.npz (the conversion source) not found")


@pytest.fixture(scope="module")
def splits():
    return {split: load("pam_arm", split, dtype=torch.float64) for split in ("train", "valid", "test")}


def test_split_is_the_stored_seeded_draw_disjoint_and_covering(splits):
    idx = {k: np.asarray(v.meta["split_info"]["indices"]) for k, v in splits.items()}
    assert [len(v) for v in idx.values()] == [432, 92, 92]
    assert sorted(np.concatenate(list(idx.values())).tolist()) == list(range(616))
    for got, want in zip(idx.values(), split_indices(616, SPLIT_FRACTIONS, SPLIT_SEED)):
        np.testing.assert_array_equal(got, want)


def test_padding_lengths_and_command_is_the_running_sum(splits):
    arrays, _ = read_npz(data_dir() / "pam_arm.npz")
    for split, data in splits.items():
        lengths = data.valid.sum(1).numpy()
        np.testing.assert_array_equal(lengths, arrays["length"][data.meta["split_info"]["indices"]])
        assert bool(data.valid[:, 0].all()) and (lengths >= 86).all() and (lengths <= 146).all()
        # valid is a prefix: True up to the length, then padding
        np.testing.assert_array_equal(data.valid.numpy(), np.arange(146)[None] < lengths[:, None])
        inc = data.hidden["increment"]
        torch.testing.assert_close(data.actions, torch.cumsum(inc, 1) * data.valid[..., None])
        assert bool((data.obs[~data.valid] == 0).all())
        assert data.meta["action"] == "command" and len(data.meta["action_names"]) == 8
    raw = load("pam_arm", "valid", action="increment", dtype=torch.float64)
    torch.testing.assert_close(raw.actions, splits["valid"].hidden["increment"])
    torch.testing.assert_close(raw.hidden["command"], splits["valid"].actions)


def test_statistics_come_from_the_training_split(splits):
    tr = splits["train"]
    ref = compute_stats(tr.obs, tr.actions, tr.valid)
    for data in splits.values():
        for key, val in ref.items():
            torch.testing.assert_close(data.stats[key], val, rtol=1e-9, atol=1e-12, msg=key)
    # direct masked numpy check of one entry, padding excluded
    x = tr.obs.numpy()[tr.valid.numpy()]
    np.testing.assert_allclose(tr.stats["obs_std"].numpy(), x.std(0), rtol=1e-9)


def test_licence_citation_and_provenance_travel_with_the_file():
    meta = load("pam_arm", "test").meta
    assert "MIT" in meta["licence"] and "vaisakh-shaj" in meta["licence"]
    assert "Action-Conditional Recurrent Kalman Networks" in meta["citation"]
    assert "7a8ae18" in meta["source"] and meta["left_out"]
    readme = (data_dir() / "README.md").read_text()
    assert "vaisakh-shaj" in readme and "CoRL 2020" in readme


@needs_source
def test_bundled_values_equal_the_source_exactly(splits):
    with np.load(SOURCE, allow_pickle=False) as src:
        ob, act = src["ob"], src["action"]
    for data in splits.values():
        idx = np.asarray(data.meta["split_info"]["indices"])
        v = data.valid.numpy()
        np.testing.assert_array_equal(data.obs.float().numpy()[v], ob[idx][v][:, :4])
        np.testing.assert_array_equal(data.hidden["increment"].float().numpy()[v], act[idx][v])
        np.testing.assert_array_equal(data.hidden["pressure"].float().numpy()[v], ob[idx][v][:, 8:16])


@needs_source
def test_conversion_is_byte_reproducible(tmp_path):
    arrays, meta = convert(SOURCE)
    committed, committed_meta = read_npz(data_dir() / "pam_arm.npz")
    assert set(arrays) == set(committed)
    for key in arrays:
        np.testing.assert_array_equal(arrays[key], committed[key], err_msg=key)
    for m in (meta, committed_meta):
        for key in ("build", "dataset", "format_version"):
            m.pop(key, None)
    assert meta == committed_meta


def test_action_representation_chosen_by_measurement(splits):
    """Ridge predictors of the angle change h steps ahead, fitted on train, scored on valid
    (numbers in data/README.md): the running sum of the increments (the default action)
    beats the raw increments at every horizon from 10 steps, and any actions beat none.
    The measured pressures do better still, but they are outputs of the arm, not inputs."""
    r = action_representation_check(load("pam_arm", "train"), load("pam_arm", "valid"), horizons=(1, 10, 25, 50))
    for h in (10, 25, 50):
        assert r["command"][h] < 0.985 * r["increment"][h], h
        assert r["increment"][h] < 0.9 * r["none"][h], h
        assert r["pressure"][h] < r["command"][h], h
        assert r["command"][h] < 0.7 * r["repeat_last"][h], h
    assert r["command"][1] == pytest.approx(r["increment"][1], rel=0.02)

"""The public data API for users' own sequences (issue 11, item 8): from_arrays, compute_stats,
split_sequences; every check raises a ValueError starting with the argument's name."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.datasets import SequenceData, compute_stats, load, split_sequences
from pgm_wm.datasets.sequences import split_indices


def _arrays(n=12, T=30, d=3, da=2, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(2.0, 3.0, (n, T, d))
    act = rng.normal(-1.0, 0.5, (n, T, da))
    valid = rng.random((n, T)) > 0.3
    lengths = rng.integers(5, T + 1, n)
    valid &= np.arange(T)[None, :] < lengths[:, None]  # padded tails too
    valid[:, 0] = True
    obs[~valid] = np.nan  # what a user would put there; must be ignored
    return obs, act, valid


def _numpy_reference(obs, act, valid):
    """Masked statistics written with boolean indexing (an independent route)."""
    x = obs[valid]
    a = act[valid]
    pair = valid[:, 1:] & valid[:, :-1]
    dx = (obs[:, 1:] - obs[:, :-1])[pair]
    return {"obs_mean": x.mean(0), "obs_std": x.std(0), "act_mean": a.mean(0), "act_std": a.std(0),
            "diff_mean": dx.mean(0), "diff_std": dx.std(0)}


def test_compute_stats_matches_numpy_on_masked_data():
    obs, act, valid = _arrays()
    got = compute_stats(obs, act, valid)
    ref = _numpy_reference(obs, act, valid)
    assert set(got) == set(ref)
    for key, val in ref.items():
        assert got[key].dtype == torch.float64
        np.testing.assert_allclose(got[key].numpy(), val, rtol=1e-12, atol=1e-12, err_msg=key)
    # the invalid entries really are ignored: changing them changes nothing
    obs2 = obs.copy()
    obs2[~valid] = 1e6
    np.testing.assert_allclose(compute_stats(obs2, act, valid)["obs_std"].numpy(), ref["obs_std"], rtol=1e-12)
    # tensors and float32 in, same numbers (float32 accumulation is done in float64)
    got32 = compute_stats(torch.tensor(np.nan_to_num(obs), dtype=torch.float32), None,
                          torch.tensor(valid), with_diff=False, dtype=torch.float32)
    assert set(got32) == {"obs_mean", "obs_std"} and got32["obs_mean"].dtype == torch.float32
    np.testing.assert_allclose(got32["obs_mean"].numpy(), ref["obs_mean"], rtol=1e-5)


def test_compute_stats_floors_constant_features():
    obs = np.ones((2, 4, 1))
    assert float(compute_stats(obs)["obs_std"]) == pytest.approx(1e-6)


@pytest.mark.parametrize("kwargs,name", [
    (dict(obs=np.zeros((4, 5))), "obs"),
    (dict(obs=np.zeros((4, 5, 2), dtype=np.int64)), "obs"),
    (dict(obs=np.zeros((0, 5, 2))), "obs"),
    (dict(obs=np.full((2, 5, 2), np.nan)), "obs"),
    (dict(obs=np.zeros((2, 5, 2)), actions=np.zeros((2, 4, 1))), "actions"),
    (dict(obs=np.zeros((2, 5, 2)), actions=np.full((2, 5, 1), np.inf)), "actions"),
    (dict(obs=np.zeros((2, 5, 2)), actions=np.zeros((2, 5, 1), dtype=np.int32)), "actions"),
    (dict(obs=np.zeros((2, 5, 2)), valid=np.ones((2, 4), dtype=bool)), "valid"),
    (dict(obs=np.zeros((2, 5, 2)), valid=np.ones((2, 5))), "valid"),
    (dict(obs=np.zeros((2, 5, 2)), valid=np.zeros((2, 5), dtype=bool)), "valid"),
    (dict(obs=[[[0.0]]]), "obs"),
])
def test_bad_inputs_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        compute_stats(**kwargs)
    with pytest.raises(ValueError, match=f"^{name}"):
        SequenceData.from_arrays(**kwargs)


def test_from_arrays_builds_a_checked_sequence_data():
    obs, act, valid = _arrays()
    data = SequenceData.from_arrays(obs, act, valid, hidden={"mass": np.ones(valid.shape)}, name="mine")
    assert data.obs.dtype == torch.float32 and data.valid.dtype == torch.bool
    assert data.obs.shape == obs.shape and data.action_dim == 2 and data.name == "mine"
    assert bool((data.obs[~data.valid] == 0).all()) and torch.isfinite(data.obs).all()
    ref = _numpy_reference(obs, act, valid)
    np.testing.assert_allclose(data.stats["diff_std"].numpy(), ref["diff_std"], rtol=1e-6)
    z = data.normalize_obs(data.obs.double())[data.valid]
    np.testing.assert_allclose(z.mean(0).numpy(), 0, atol=1e-5)
    # given statistics are used as they are (e.g. the training split's)
    other = SequenceData.from_arrays(obs[:3], act[:3], valid[:3], stats=data.stats, dtype=torch.float64)
    torch.testing.assert_close(other.stats["obs_mean"], data.stats["obs_mean"].double())
    with pytest.raises(ValueError, match="^stats"):
        SequenceData.from_arrays(obs, act, valid, stats={"obs_mean": np.zeros(3), "obs_std": np.ones(3)})
    with pytest.raises(ValueError, match=r"^stats\['obs_std'\]"):
        SequenceData.from_arrays(obs, None, valid, stats={"obs_mean": np.zeros(3), "obs_std": -np.ones(3)})
    with pytest.raises(ValueError, match=r"^stats\['obs_mean'\]"):
        SequenceData.from_arrays(obs, None, valid, stats={"obs_mean": np.zeros(2), "obs_std": np.ones(3)})
    with pytest.raises(ValueError, match=r"^hidden\['mass'\]"):
        SequenceData.from_arrays(obs, act, valid, hidden={"mass": np.ones(4)})
    with pytest.raises(ValueError, match="^targets"):
        SequenceData.from_arrays(obs, act, valid, targets=np.ones((2, 2, 2)))
    with pytest.raises(ValueError, match="^dtype"):
        SequenceData.from_arrays(obs, act, valid, dtype=torch.int64)


def test_from_arrays_round_trips_a_bundled_split():
    ref = load("hysteresis_arm", "valid")
    data = SequenceData.from_arrays(ref.obs, ref.actions, ref.valid, stats=ref.stats)
    torch.testing.assert_close(data.obs, ref.obs)
    torch.testing.assert_close(data.normalize_actions(data.actions), ref.normalize_actions(ref.actions))


def test_split_is_disjoint_covering_seeded_and_uses_training_stats():
    obs, act, valid = _arrays(n=40)
    data = SequenceData.from_arrays(obs, act, valid, dtype=torch.float64)
    parts = split_sequences(data, (0.6, 0.2, 0.2), seed=3)
    idx = {k: np.asarray(p.meta["split_info"]["indices"]) for k, p in parts.items()}
    assert [len(v) for v in idx.values()] == [24, 8, 8]
    allidx = np.concatenate(list(idx.values()))
    assert sorted(allidx.tolist()) == list(range(40))  # disjoint and covering
    again = split_sequences(data, (0.6, 0.2, 0.2), seed=3)
    other = split_sequences(data, (0.6, 0.2, 0.2), seed=4)
    for k in idx:
        np.testing.assert_array_equal(again[k].meta["split_info"]["indices"], idx[k])
        torch.testing.assert_close(parts[k].obs, data.obs[idx[k]])
        torch.testing.assert_close(parts[k].actions, data.actions[idx[k]])
    assert not np.array_equal(other["train"].meta["split_info"]["indices"], idx["train"])
    # every part normalises with the statistics of the training part only
    ref = _numpy_reference(obs[idx["train"]], act[idx["train"]], valid[idx["train"]])
    for part in parts.values():
        for key, val in ref.items():
            np.testing.assert_allclose(part.stats[key].numpy(), val, rtol=1e-10, err_msg=key)
    assert abs(float(parts["test"].stats["obs_mean"][0]) - float(data.stats["obs_mean"][0])) > 1e-6


def test_split_sizes_and_bad_arguments():
    for n in (3, 7, 10, 101):
        parts = split_indices(n, (0.7, 0.15, 0.15), seed=0)
        assert sum(len(p) for p in parts) == n and min(len(p) for p in parts) >= 1
    data = SequenceData.from_arrays(np.zeros((5, 4, 1)))
    with pytest.raises(ValueError, match="^fractions"):
        split_sequences(data, (0.5, 0.6))
    with pytest.raises(ValueError, match="^fractions"):
        split_sequences(data, (1.0, 0.0), names=("a", "b"))
    with pytest.raises(ValueError, match="^names"):
        split_sequences(data, (0.5, 0.5))
    with pytest.raises(ValueError, match="^data"):  # 2 sequences cannot fill 3 parts
        split_sequences(SequenceData.from_arrays(np.zeros((2, 4, 1))), (0.4, 0.3, 0.3))
    with pytest.raises(ValueError, match="^data"):
        split_sequences(np.zeros((5, 4, 1)))
    with pytest.raises(ValueError, match="^index"):
        data.subset([7])


def test_split_sequences_unpacks_into_train_valid_test():
    """issue 24: a dict made `train, valid, test = split_sequences(...)` unpack the key strings."""
    from pgm_wm.datasets import SequenceSplits

    rng = np.random.default_rng(0)
    data = SequenceData.from_arrays(rng.normal(size=(20, 6, 2)), rng.normal(size=(20, 6, 1)))
    train, valid, test = split_sequences(data, (0.6, 0.2, 0.2), seed=1)
    assert (train.split, valid.split, test.split) == ("train", "valid", "test")
    torch.testing.assert_close(valid.stats["obs_mean"], train.stats["obs_mean"])
    parts = split_sequences(data, (0.6, 0.2, 0.2), seed=1)
    assert isinstance(parts, SequenceSplits) and isinstance(parts, tuple)
    assert parts.valid is parts["valid"] is parts[1] and parts.keys() == ("train", "valid", "test")
    assert [k for k, _ in parts.items()] == ["train", "valid", "test"] and len(parts.values()) == 3
    with pytest.raises(KeyError):
        parts["nope"]
    a, b = split_sequences(data, (0.5, 0.5), names=("fit", "holdout"))
    assert (a.split, b.split) == ("fit", "holdout")
    assert split_sequences(data, (0.5, 0.5), names=("fit", "holdout")).holdout.split == "holdout"
    with pytest.raises(ValueError, match="^names"):
        split_sequences(data, (0.5, 0.5), names=("a b", "c"))


def test_variances_are_rescaled_to_original_units():
    """denormalize_obs_var / denormalize_diff_var: the variance of the denormalized quantity
    (checked on samples: Var(std * x + mean) = std^2 Var(x))."""
    rng = np.random.default_rng(2)
    data = SequenceData.from_arrays(rng.normal(3.0, [2.0, 0.5], size=(30, 40, 2)), rng.normal(size=(30, 40, 1)))
    g = torch.Generator().manual_seed(0)
    var_norm = torch.tensor([0.3, 2.0])
    samples = torch.randn(200_000, 2, generator=g) * var_norm.sqrt()
    emp = data.denormalize_obs(samples).var(0)
    torch.testing.assert_close(data.denormalize_obs_var(var_norm), emp, rtol=1e-2, atol=0)
    emp_d = data.denormalize_diff(samples).var(0)
    torch.testing.assert_close(data.denormalize_diff_var(var_norm), emp_d, rtol=1e-2, atol=0)
    with pytest.raises(ValueError, match="^var_norm"):
        data.denormalize_obs_var(torch.ones(3))

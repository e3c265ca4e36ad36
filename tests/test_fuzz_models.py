"""Fuzz suite, model entry points, ``fit`` and the dataset API (issue 13).

Every world model (built with :mod:`pgm_wm.builders`) gets random valid sequences (random
masks, NaN at missing steps) and must return finite means and positive variances; invalid
ones (NaN at observed steps, wrong dims, float64 data in a float32 model, half precision,
mixed obs/actions dtypes, bad masks, T = 0) raise a ValueError starting with the argument's
name."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from _fuzz import FUZZ_SLOW, finite, gen, raises_named, randn, seeds
from pgm_wm import builders
from pgm_wm.baselines import LinearARX, RepeatLast, TrainingMean
from pgm_wm.datasets import SequenceData, load
from pgm_wm.training import fit

DO, DA = 2, 2


def _models() -> dict[str, torch.nn.Module]:
    torch.manual_seed(0)
    arx = LinearARX(DO, DA)
    return {
        "acrkn": builders.build_acrkn(DO, DA, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1),
        "acrkn_bounded": builders.build_acrkn(DO, DA, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1,
                                              bounded=True),
        "hiprssm": builders.build_hiprssm(DO, DA, latent_obs_dim=3, task_dim=2, hidden=8, num_basis=2, bandwidth=1),
        "mts3": builders.build_mts3(DO, DA, 3, window=3, hidden=(8,)),
        "mts3_2": builders.build_hierarchical_mts3(DO, DA, 3, windows=(2, 4), hidden=(8,)),
        "lstm": builders.build_baseline("lstm", DO, DA, hidden=8, rnn_hidden=8),
        "gru": builders.build_baseline("gru", DO, DA, hidden=8, rnn_hidden=8),
        "ffnn": builders.build_baseline("ffnn", DO, DA, hidden=8),
        "transformer": builders.build_baseline("transformer", DO, DA, hidden=8),
        "rkn_actions_as_obs": builders.build_baseline("rkn_actions_as_obs", DO, DA, hidden=8, latent_obs_dim=3,
                                                      num_basis=3, bandwidth=1),
        "repeat_last": RepeatLast(DO),
        "training_mean": TrainingMean(torch.zeros(DO), torch.ones(DO)),
        "linear_arx": arx,
    }


MODELS = _models()
LEARNED = [k for k in MODELS if k not in ("repeat_last", "training_mean", "linear_arx")]


def seqs(seed: int, B: int, T: int, dtype=torch.float32):
    g = gen(seed)
    obs, act = randn(g, B, T, DO, dtype=dtype), randn(g, B, T, DA, dtype=dtype)
    mask = torch.rand(B, T, generator=g) < 0.6
    mask[:, 0] = True
    return obs, act, mask


@pytest.mark.parametrize("name", list(MODELS))
@FUZZ_SLOW
@given(seeds, st.integers(1, 2), st.integers(1, 9), st.sampled_from([1e-3, 1.0, 1e4]))
def test_models_valid_inputs_finite(name, seed, B, T, scale):
    obs, act, mask = seqs(seed, B, T)
    obs = (scale * obs).masked_fill(~mask[..., None], float("nan"))  # ignored at missing steps
    with torch.no_grad():
        mean, var = MODELS[name](obs, act, mask)
    assert mean.shape == (B, T, DO) and var.shape == (B, T, DO)
    assert finite(mean, var) and bool((var > 0).all())


@pytest.mark.parametrize("name", list(MODELS))
@FUZZ_SLOW
@given(seeds, st.sampled_from(["obs_nan", "obs_dim", "actions_nan", "actions_len", "mask_shape", "mask_values",
                               "T0", "float16", "mixed", "float64_model"]))
def test_models_invalid_inputs_name_the_argument(name, seed, kind):
    model = MODELS[name]
    obs, act, mask = seqs(seed, 2, 6)
    name_ = {"obs_nan": "obs", "obs_dim": "obs", "actions_nan": "actions", "actions_len": "actions",
             "mask_shape": "mask", "mask_values": "mask", "T0": "obs", "float16": "obs", "mixed": "actions",
             "float64_model": "obs"}[kind]
    if kind == "obs_nan":
        obs[0, 0, 0] = float("nan")
    elif kind == "obs_dim":
        obs = torch.cat([obs, obs[..., :1]], -1)
    elif kind == "actions_nan":
        act[1, -1, 0] = float("inf")
    elif kind == "actions_len":
        act = act[:, :-1]
    elif kind == "mask_shape":
        mask = mask[:, :-1]
    elif kind == "mask_values":
        mask = mask.to(torch.int64) + 2
    elif kind == "T0":
        obs, act, mask = obs[:, :0], act[:, :0], mask[:, :0]
    elif kind == "float16":
        obs, act = obs.half(), act.half()
    elif kind == "mixed":
        act = act.double()
    elif kind == "float64_model":
        if name not in LEARNED:
            return  # the statistics baselines compute in the data's dtype (no parameters)
        obs, act = obs.double(), act.double()
    if name in ("repeat_last", "training_mean") and kind.startswith("actions"):
        return  # these ignore actions (documented)
    with torch.no_grad():
        raises_named(name_, lambda: model(obs, act, mask))


def test_fit_valid_and_non_finite_data():
    torch.manual_seed(0)
    model = builders.build_acrkn(DO, DA, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1)
    obs, act, _ = seqs(1, 4, 6)

    def loss_fn(batch, g):
        o, a = batch
        mean, var = model(o, a)
        return ((mean[:, :-1] - o[:, 1:]) ** 2).mean()

    hist = fit(loss_fn, model, (obs, act), batch_size=2, epochs=1, progress=False)
    assert all(np.isfinite(hist.train_loss))
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
    bad = obs.clone()
    bad[2, 3, 0] = float("nan")
    with pytest.raises(ValueError):
        fit(loss_fn, model, (bad, act), batch_size=2, epochs=1, progress=False)
    with pytest.raises(ValueError, match="^batch_size"):
        fit(loss_fn, model, (obs, act), batch_size=0, epochs=1, progress=False)


@FUZZ_SLOW
@given(seeds, st.integers(1, 3), st.integers(1, 6), st.sampled_from(["obs_nan", "valid_shape", "actions_len", "T0",
                                                                     "obs_ndim"]))
def test_sequence_data_from_arrays(seed, n, T, kind):
    g = gen(seed)
    obs, act = randn(g, n, T, DO).numpy(), randn(g, n, T, DA).numpy()
    valid = np.ones((n, T), dtype=bool)
    d = SequenceData.from_arrays(obs, act, valid)
    assert d.obs.shape == (n, T, DO) and bool(torch.isfinite(d.obs).all())
    name = {"obs_nan": "obs", "valid_shape": "valid", "actions_len": "actions", "T0": "obs", "obs_ndim": "obs"}[kind]
    if kind == "obs_nan":
        obs[0, 0, 0] = np.nan
    elif kind == "valid_shape":
        valid = valid[:, :0]
    elif kind == "actions_len":
        act = act[:, : T - 1] if T > 1 else act[:, :0]
    elif kind == "T0":
        obs, act, valid = obs[:, :0], act[:, :0], valid[:, :0]
    elif kind == "obs_ndim":
        obs = obs[0]
    raises_named(name, lambda: SequenceData.from_arrays(obs, act, valid))


def test_load_invalid_arguments():
    raises_named("name", lambda: load("no_such_dataset"))
    raises_named("split", lambda: load("nile", "no_such_split"))
    raises_named("dtype", lambda: load("nile", "train", dtype=torch.int64))


@FUZZ_SLOW
@given(seeds, st.integers(1, 5), st.sampled_from(["valid", "unflattened", "nan", "T0", "float64", "mask"]))
def test_image_rkn_entry_point(seed, T, kind):
    torch.manual_seed(0)
    model = builders.build_rkn((8, 8), DO, latent_obs_dim=3, num_basis=3, bandwidth=1, decoder_hidden=(8,))
    g = gen(seed)
    obs = torch.rand(2, T, 64, generator=g)
    mask = torch.rand(2, T, generator=g) < 0.5
    with torch.no_grad():
        if kind == "valid":
            mean, var = model(obs.masked_fill(~mask[..., None], float("nan")), mask)
            assert finite(mean, var) and bool((var > 0).all())
            return
        name = "mask" if kind == "mask" else "obs"
        obs = {"unflattened": obs.reshape(2, T, 8, 8), "nan": obs.masked_fill(torch.ones_like(obs, dtype=torch.bool),
               float("nan")), "T0": obs[:, :0], "float64": obs.double(), "mask": obs}[kind]
        mask = {"T0": mask[:, :0], "mask": mask[:1], "nan": None}.get(kind, mask)
        raises_named(name, lambda: model(obs, mask))

"""Saving and loading (issue 13.11): a ``state_dict`` saved with ``torch.save`` loads with the
default ``torch.load`` (``weights_only=True``) into a freshly built model and gives bit-identical
predictions, for one model per chapter; pickling the whole module is refused by that default."""

from __future__ import annotations

import pickle

import pytest
import torch

from pgm_wm import builders


def _case(name: str):
    g = torch.Generator().manual_seed(3)
    seq = (torch.randn(2, 7, 2, generator=g), torch.randn(2, 7, 2, generator=g))
    mask = torch.rand(2, 7, generator=g) < 0.7
    return {
        "ch2_set": (lambda: builders.build_set_model("bayesian", 3, 2, (8,)), (torch.randn(2, 5, 3, generator=g),)),
        "ch3_rkn": (lambda: builders.build_rkn((8, 8), 2, latent_obs_dim=3, num_basis=3, bandwidth=1,
                                               decoder_hidden=(8,)), (torch.rand(2, 4, 64, generator=g), mask[:, :4])),
        "ch4_acrkn": (lambda: builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1),
                      (*seq, mask)),
        "ch5_hiprssm": (lambda: builders.build_hiprssm(2, 2, latent_obs_dim=3, task_dim=2, hidden=8), (*seq, mask)),
        "ch6_mts3": (lambda: builders.build_mts3(2, 2, 3, window=3, hidden=(8,)), (*seq, mask)),
    }[name]


@pytest.mark.parametrize("name", ["ch2_set", "ch3_rkn", "ch4_acrkn", "ch5_hiprssm", "ch6_mts3"])
def test_state_dict_round_trip_is_bit_identical(name, tmp_path):
    build, inputs = _case(name)
    torch.manual_seed(0)
    model = build()
    with torch.no_grad():  # perturb every parameter, so the fresh model differs before loading
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    path = tmp_path / "model.pt"
    torch.save(model.state_dict(), path)
    torch.manual_seed(1)
    fresh = build()
    fresh.load_state_dict(torch.load(path))  # the default: weights_only=True
    model.eval(), fresh.eval()
    with torch.no_grad():
        a, b = model(*inputs), fresh(*inputs)
    a, b = tuple(a), tuple(b)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


def test_pickled_module_is_refused_by_the_default_load(tmp_path):
    model = builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1)
    path = tmp_path / "whole.pt"
    torch.save(model, path)
    with pytest.raises(pickle.UnpicklingError):
        torch.load(path)


# ----------------------------------------------------------------------------- issue 24: the configuration travels
@pytest.mark.parametrize("name", ["ch2_set", "ch3_rkn", "ch4_acrkn", "ch5_hiprssm", "ch6_mts3"])
def test_save_model_rebuilds_the_model_bit_identically(name, tmp_path):
    build, inputs = _case(name)
    torch.manual_seed(0)
    model = build()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    path = tmp_path / "model.pt"
    builders.save_model(model, path)
    assert set(torch.load(path)) == {"format", "builder", "kwargs", "state_dict"}   # weights_only=True reads it
    torch.manual_seed(1)
    fresh = builders.load_model(path)                   # rebuilt from the saved builder call
    same = builders.load_model(path, build())           # or loaded into a model built the same way
    model.eval()
    with torch.no_grad():
        a = tuple(model(*inputs))
        for other in (fresh, same):
            for x, y in zip(a, tuple(other(*inputs))):
                assert torch.equal(x, y)


MISMATCHES = {
    "bandwidth": (lambda: builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=1),
                  lambda: builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, num_basis=3, bandwidth=2)),
    "readout": (lambda: builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, readout="absolute"),
                lambda: builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8, readout="difference")),
    "window": (lambda: builders.build_mts3(2, 2, 3, window=3, hidden=(8,)),
               lambda: builders.build_mts3(2, 2, 3, window=5, hidden=(8,))),
    "diagonal_only": (lambda: builders.build_rkn((8, 8), 2, latent_obs_dim=3, num_basis=3, bandwidth=1),
                      lambda: builders.build_rkn((8, 8), 2, latent_obs_dim=3, num_basis=3, bandwidth=1,
                                                 diagonal_only=True)),
}


@pytest.mark.parametrize("arg", sorted(MISMATCHES))
def test_loading_into_a_model_built_otherwise_is_an_error(arg, tmp_path):
    """Before: a plain state_dict of these pairs loads silently (equal shapes) and predicts
    differently; load_model names the differing argument."""
    saved_build, other_build = MISMATCHES[arg]
    torch.manual_seed(0)
    saved, other = saved_build(), other_build()
    path = tmp_path / "m.pt"
    builders.save_model(saved, path)
    if arg != "bandwidth":  # the plain state_dict does not notice (bandwidth changes the band mask only)
        other.load_state_dict(saved.state_dict())
    with pytest.raises(ValueError, match=f"^model: built with another configuration.*{arg}="):
        builders.load_model(path, other_build())


def test_save_and_load_refuse_what_they_cannot_check(tmp_path):
    from pgm_wm.mts3 import build_mts3

    with pytest.raises(ValueError, match="^model: not made by a builder"):
        builders.save_model(build_mts3(2, 2, 3, window=3, hidden=(8,)), tmp_path / "x.pt")
    plain = builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8)
    torch.save(plain.state_dict(), tmp_path / "plain.pt")
    with pytest.raises(ValueError, match="^path: .* not a file written by pgm_wm.builders.save_model"):
        builders.load_model(tmp_path / "plain.pt")
    builders.save_model(plain, tmp_path / "ok.pt")
    with pytest.raises(ValueError, match="^model: not made by a builder"):
        builders.load_model(tmp_path / "ok.pt", build_mts3(2, 2, 3, window=3, hidden=(8,)))
    with pytest.raises(ValueError, match="^model: built by build_hiprssm"):
        builders.load_model(tmp_path / "ok.pt", builders.build_hiprssm(2, 2, latent_obs_dim=3, task_dim=2, hidden=8))

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

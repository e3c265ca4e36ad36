"""Long runs without observations (issue 13.5), built through :mod:`pgm_wm.builders`: the image
RKN of Chapter 3 (10,000 steps) and the Transformer baseline (2,000 steps: its attention is O(T²)
in memory) stay finite with positive variances.

Covered elsewhere and not repeated here: 10,000 all-missing steps for the untrained RKN, ac-RKN,
norm-bounded ac-RKN, both HiP-RSSM task terms and MTS3 with 1 and 2 task levels
(``test_filtering.py``), and 10,000 open-loop steps for the feedback baselines LSTM, GRU, FFNN and
RKN-with-actions-as-observations (``test_baselines.py``).
"""

from __future__ import annotations

import pytest
import torch

from pgm_wm import builders

LONG = 10_000
DO, DA = 2, 2


def _build(name: str) -> torch.nn.Module:
    torch.manual_seed(0)
    return {
        "rkn": lambda: builders.build_rkn((8, 8), out_dim=DO, latent_obs_dim=3, num_basis=3, bandwidth=1,
                                          decoder_hidden=(8,)),
        "transformer": lambda: builders.build_baseline("transformer", DO, DA, hidden=8),
    }[name]()


@pytest.mark.parametrize("name", ["rkn", "transformer"])
def test_untrained_model_stays_finite_over_all_missing_steps(name):
    model = _build(name)
    T = 2_000 if name == "transformer" else LONG
    g = torch.Generator().manual_seed(1)
    mask = torch.zeros(1, T, dtype=torch.bool)
    mask[:, :5] = True  # a few observations at the start, then nothing
    with torch.no_grad():
        if name == "rkn":
            obs = torch.rand(1, T, 64, generator=g)
            mean, var = model(obs, mask)
        else:
            obs, act = torch.randn(1, T, DO, generator=g), torch.randn(1, T, DA, generator=g)
            mean, var = model(obs, act, mask)
    assert mean.shape[:2] == (1, T)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(var).all())
    assert bool((var > 0).all())

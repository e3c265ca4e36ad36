"""Errors name the argument the caller got wrong, and a too small variance in float32 is an error
instead of a NaN mean (issue 24, "smaller" failure classes)."""

from __future__ import annotations

import pytest
import torch

from pgm_wm import builders
from pgm_wm.aggregation import bayesian_aggregation, set_condition
from pgm_wm.factorized import factorized_update
from pgm_wm.testing import random_factorized_belief


def test_factorized_update_names_the_observation_mean():
    b = random_factorized_belief((3,), 2, dtype=torch.float32)
    w, w_var = torch.randn(3, 2), torch.rand(3, 2) + 0.1
    with pytest.raises(ValueError, match=r"^observation\.mean: expected a floating-point tensor"):
        factorized_update(b, w.long(), w_var)


def test_acrkn_names_the_actions():
    model = builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8)
    with pytest.raises(ValueError, match=r"^actions: expected shape \(\.\.\., 2\)"):
        model(torch.randn(2, 5, 2), torch.randn(2, 5, 3), None)


@pytest.mark.parametrize("encoder", ["set", "recurrent"])
def test_hiprssm_names_the_context(encoder):
    model = builders.build_hiprssm(2, 2, latent_obs_dim=3, task_dim=2, hidden=8, encoder=encoder)
    with pytest.raises(ValueError, match=r"^context: expected shape"):
        model(torch.randn(2, 5, 2), torch.randn(2, 5, 2), None, torch.randn(2, 4, 7), torch.ones(2, 4, dtype=torch.bool))


@pytest.mark.parametrize("value", [1e-40, 1e-38])
def test_tiny_set_variance_in_float32_is_an_error_not_a_nan_mean(value):
    """Before: 1 / 1e-40 overflows float32, the mean came out NaN and the variance 0, silently."""
    r = torch.randn(2, 4, 3)
    with pytest.raises(ValueError, match=r"^r_var: .* too small for torch.float32"):
        bayesian_aggregation(r, torch.full((2, 4, 3), value))
    with pytest.raises(ValueError, match=r"^r_var"):
        set_condition(random_factorized_belief((2,), 3, dtype=torch.float32), r, torch.full((2, 4, 3), value))
    exact = bayesian_aggregation(r.double(), torch.full((2, 4, 3), value, dtype=torch.float64))
    assert bool(torch.isfinite(exact.mean).all())          # float64 holds it
    mask = torch.ones(2, 4, dtype=torch.bool)
    mask[:, 0] = False                                      # a masked-out tiny entry is ignored
    r_var = torch.ones(2, 4, 3)
    r_var[:, 0] = value
    torch.testing.assert_close(bayesian_aggregation(r, r_var, mask).var, torch.full((2, 3), 0.25))

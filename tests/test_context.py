"""Tests for pgm_wm.context: the set-model metrics in physical units and fitting a set model with
the package's one fit loop."""

from __future__ import annotations

import math

import torch
from torch import nn

from pgm_wm.context import ContextBatch, ContextSetSampler, evaluate_set_model, fit_set_model


class FixedSetModel(nn.Module):
    """Returns given (mean, var) for every set, whatever the elements."""

    def __init__(self, mean, var):
        super().__init__()
        self.mean, self.var = mean, var
        self.w = nn.Parameter(torch.zeros(()))

    def forward(self, x, mask=None):
        return self.mean + 0 * self.w, self.var


def test_evaluate_set_model_reports_physical_units_for_any_target_scale():
    y = torch.tensor([[0.5], [-1.0], [2.0]], dtype=torch.float64)
    mean = torch.tensor([[0.0], [-0.5], [1.0]], dtype=torch.float64)
    var = torch.tensor([[0.25], [1.0], [4.0]], dtype=torch.float64)
    batch = ContextBatch(torch.zeros(3, 2, 1), torch.ones(3, 2, dtype=torch.bool), y, torch.arange(3),
                         torch.zeros(3, 2, dtype=torch.bool), torch.zeros(3, 2))
    s, c = 3.0, 7.0
    res = evaluate_set_model(FixedSetModel(mean, var), batch, target_scale=s)
    # closed form in physical units: Y = c + s y, mean c + s mu, var s^2 var (the shift c cancels)
    Y, M, V = c + s * y, c + s * mean, s * s * var
    assert math.isclose(res["rmse"], float(((M - Y) ** 2).mean().sqrt()), rel_tol=1e-12)
    nll_phys = float((0.5 * (torch.log(2 * math.pi * V) + (Y - M) ** 2 / V)).mean())
    assert math.isclose(res["nll"], nll_phys, rel_tol=1e-12)
    assert math.isclose(res["std"], float(V.sqrt().mean()), rel_tol=1e-12)
    unit = evaluate_set_model(FixedSetModel(mean, var), batch)
    assert math.isclose(res["rmse"], s * unit["rmse"]) and not math.isclose(res["nll"], unit["nll"])


def test_fit_set_model_uses_the_fit_loop_with_budget_and_selection():
    g = torch.Generator().manual_seed(0)
    feats, targets = torch.randn(8, 20, 3, generator=g), torch.randn(8, 1, generator=g)
    sampler = ContextSetSampler(feats, targets)
    valid = sampler.sample(16, 5, 1, torch.Generator().manual_seed(1))
    torch.manual_seed(0)
    from pgm_wm.aggregation import BayesianContextEncoder

    model = BayesianContextEncoder(3, 1, hidden=(8,))
    hist = fit_set_model(model, sampler, valid, steps=40, batch_size=8, n_max=5, eval_every=10)
    assert hist.steps == [10, 20, 30, 40] and len(hist.valid_loss) == 4
    assert math.isclose(evaluate_set_model(model, valid)["nll"], hist.best_valid_loss, rel_tol=1e-9)
    short = fit_set_model(BayesianContextEncoder(3, 1, hidden=(8,)), sampler, valid, steps=10**6, batch_size=8,
                          n_max=5, eval_every=5, budget_s=0.2)
    assert short.stopped == "budget" and short.steps[-1] < 10**6

"""Tests for pgm_wm.layers: the MLP, the Gaussian head and the positive variance maps (one floor
policy: positive and finite for every finite input, in float32 and float64)."""

from __future__ import annotations

import math

import pytest
import torch

from pgm_wm.layers import GaussianHead, elup1, mlp, positive_variance, variance_floor


def test_elup1_is_elu_plus_one_and_never_underflows_to_zero():
    x = torch.linspace(-30.0, 5.0, 701)
    ref = torch.nn.functional.elu(x.double()) + 1.0
    torch.testing.assert_close(elup1(x).double(), ref, rtol=1e-6, atol=1e-12)
    assert bool((elup1(torch.tensor([-20.0, -50.0])) > 0).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_variance_maps_are_bounded_away_from_zero_for_every_finite_input(dtype):
    info = torch.finfo(dtype)
    x = torch.tensor([info.min, -1e30, -1e4 * 37.0, -1e4, -200.0, -104.0, -88.0, -17.0, 0.0, 3.0, 1e30, info.max],
                     dtype=dtype)
    floor = variance_floor(dtype)
    assert floor == math.sqrt(info.tiny) and 1.0 / floor < info.max and floor * floor > 0
    for fn in (elup1, positive_variance):
        v = fn(x)
        assert v.dtype == dtype and bool(torch.isfinite(v).all()) and bool((v >= floor).all()), fn.__name__
        assert bool(torch.isfinite(1.0 / v).all())
    # the old elup1 was exp(x): exactly 0 for float32 inputs scaled by 1e4 (issue 13, finding 6)
    if dtype == torch.float32:
        assert float(torch.exp(torch.tensor(-1e4))) == 0.0


def test_variance_maps_equal_their_closed_forms_and_take_min_var():
    x = torch.linspace(-20.0, 20.0, 401, dtype=torch.float64)
    softplus = torch.log1p(torch.exp(x))
    torch.testing.assert_close(positive_variance(x, 1e-4), softplus + 1e-4)
    torch.testing.assert_close(elup1(x, 0.5), torch.where(x > 0, x + 1, torch.exp(x)) + 0.5)
    with pytest.raises(ValueError, match="min_var"):
        elup1(x, 0.0)
    with pytest.raises(ValueError, match="min_var"):
        positive_variance(x, -1.0)
    with pytest.raises(ValueError, match="dtype"):
        variance_floor(torch.int64)


def test_mlp_and_gaussian_head_shapes_and_structure():
    net = mlp(3, (8, 4), 2)
    assert [type(m).__name__ for m in net] == ["Linear", "ReLU", "Linear", "ReLU", "Linear"]
    trunk = mlp(3, (8,))
    assert trunk(torch.randn(5, 3)).shape == (5, 8) and bool((trunk(torch.randn(5, 3)) >= 0).all())
    with pytest.raises(ValueError, match="hidden"):
        mlp(3, ())
    head = GaussianHead(6, 2, (16,))
    h = torch.randn(4, 7, 6)
    mean, var = head(h)
    assert mean.shape == var.shape == (4, 7, 2) and bool((var > 0).all())
    lin = GaussianHead(6, 2, ())
    assert len(lin.mean_net) == 1  # a linear head
    with pytest.raises(ValueError, match="h"):
        head(torch.randn(4, 5))
    with pytest.raises(ValueError, match="out_dim"):
        GaussianHead(6, 0)

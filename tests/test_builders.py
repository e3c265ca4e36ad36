"""Tests for pgm_wm.builders: every chapter builder returns the model the chapter describes
(same class, same parameter count as the explicit construction) and runs with the world-model
or filter interface; bad choices raise ValueError naming the argument."""

from __future__ import annotations

import pytest
import torch

from pgm_wm import builders as B
from pgm_wm.acrkn import AcRKN, MLPControl, NormBoundedTransition
from pgm_wm.aggregation import BayesianContextEncoder
from pgm_wm.hiprssm import HiPRSSM, NonlinearTaskTransform
from pgm_wm.mts3 import MTS3, build_mts3
from pgm_wm.rkn import RKN, BeliefDecoder, LocallyLinearTransition, ObservationEncoder
from pgm_wm.rnn_filters import RecurrentFilter, count_parameters


def test_chapter4_acrkn_matches_the_explicit_construction():
    torch.manual_seed(0)
    model = B.build_acrkn(2, 2)
    torch.manual_seed(0)
    ref = AcRKN(ObservationEncoder(2, 15, (64,)), LocallyLinearTransition(15, 15, 3), MLPControl(2, 15, (64, 64)),
                BeliefDecoder(15, 2, (64,), (64,)))
    assert isinstance(model, AcRKN) and count_parameters(model) == count_parameters(ref)
    assert isinstance(B.build_acrkn(bounded=True).rkn.transition, NormBoundedTransition)
    obs, act = torch.randn(2, 9, 2), torch.randn(2, 9, 2)
    for control in ("mlp", "linear", "locally_linear"):
        mean, var = B.build_acrkn(control=control)(obs, act, torch.rand(2, 9) > 0.3)
        assert mean.shape == var.shape == obs.shape and bool((var > 0).all())
    with pytest.raises(ValueError, match="control"):
        B.build_acrkn(control="pid")


@pytest.mark.parametrize("name", ["rkn_actions_as_obs", "lstm", "gru", "ffnn", "transformer"])
def test_baseline_builders_have_the_world_model_interface(name):
    model = B.build_baseline(name, 3, 2, hidden=16)
    obs, act = torch.randn(2, 7, 3), torch.randn(2, 7, 2)
    mean, var = model(obs, act, torch.rand(2, 7) > 0.3)
    assert mean.shape == var.shape == obs.shape and bool((var > 0).all())


def test_chapter5_and_6_builders():
    hip = B.build_hiprssm()
    assert isinstance(hip, HiPRSSM) and isinstance(hip.context_encoder, BayesianContextEncoder)
    assert isinstance(hip.task_transform, NonlinearTaskTransform) and hip.acrkn.rkn.latent_obs_dim == 8
    obs, act = torch.randn(3, 10, 4), torch.randn(3, 10, 2)
    ctx, cmask = torch.randn(3, 9, 10), torch.rand(3, 9) > 0.2
    mean, var = hip(obs, act, None, ctx, cmask)
    assert mean.shape == (3, 10, 4) and bool((var > 0).all())
    assert B.build_mts3.__wrapped__ is build_mts3 and isinstance(B.build_mts3(4, 2, 3, 5), MTS3)  # + recording
    with pytest.raises(ValueError, match="encoder"):
        B.build_hiprssm(encoder="attention")


def test_chapter2_and_3_builders():
    for kind in ("bayesian", "mean", "max"):
        mean, var = B.build_set_model(kind, 5)(torch.randn(4, 6, 5), torch.rand(4, 6) > 0.3)
        assert mean.shape == var.shape == (4, 1) and bool((var > 0).all())
    rkn = B.build_rkn((8, 8))
    assert isinstance(rkn, RKN)
    frames = torch.rand(2, 5, 64)
    mean, var = rkn(frames, torch.rand(2, 5) > 0.3)
    assert mean.shape == (2, 5, 2) and bool((var > 0).all())
    lstm = B.build_recurrent_filter("lstm", (8, 8))
    assert isinstance(lstm, RecurrentFilter)
    # the recurrent layer is no larger than the RKN's transition model
    assert count_parameters(lstm.rnn) <= count_parameters(rkn.transition)
    with pytest.raises(ValueError, match="kind"):
        B.build_set_model("sum", 5)
    with pytest.raises(ValueError, match="cell"):
        B.build_recurrent_filter("rnn", (8, 8))

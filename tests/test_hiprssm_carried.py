"""CarriedHiPRSSM: a HiP-RSSM that carries its state and task beliefs from window to window."""

from __future__ import annotations

import pytest
import torch

from pgm_wm.builders import build_hiprssm
from pgm_wm.datasets.windows import context_features
from pgm_wm.hiprssm import CarriedHiPRSSM


def _model(dtype: torch.dtype, readout: str = "difference") -> CarriedHiPRSSM:
    torch.manual_seed(0)
    hip = build_hiprssm(3, 2, latent_obs_dim=4, task_dim=3, hidden=8, num_basis=2, bandwidth=1,
                        task="linear", readout=readout).to(dtype)
    return CarriedHiPRSSM(hip, 5, torch.tensor([0.1, 0.0, -0.1]), torch.tensor([0.5, 1.0, 2.0])).to(dtype)


def _data(dtype: torch.dtype, B: int = 3, T: int = 23):
    g = torch.Generator().manual_seed(1)
    return (torch.randn(B, T, 3, generator=g, dtype=dtype), torch.randn(B, T, 2, generator=g, dtype=dtype),
            torch.rand(B, T, generator=g) < 0.8)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("readout", ["difference", "absolute"])
def test_open_loop_windows_equal_one_filter_with_the_carried_state_and_task(dtype, readout):
    """Window 0 observed, everything after it hidden: windows 1.. must equal ONE filter run over
    steps 5.. that starts from window 0's last prior, with the task inferred from window 0's
    interactions throughout (the empty context sets of the open-loop windows keep it)."""
    model = _model(dtype, readout)
    obs, act, _ = _data(dtype)
    mask = torch.zeros(obs.shape[:2], dtype=torch.bool)
    mask[:, :5] = True
    mean, var = model(obs, act, mask)
    hip, k = model.hip, model.window
    ctx, cmask = context_features(obs[:, :k], act[:, :k], None, model.diff_shift, model.diff_scale)
    task0 = hip.infer_task(None, None, obs.shape[0], obs)
    out0, _ = hip.filter(obs[:, :k], act[:, :k], mask[:, :k], task=task0)
    d0 = hip.acrkn.rkn.decoder(out0.next_prior)
    mu0, _ = hip.acrkn.readout(obs[:, :k], mask[:, :k], *d0)
    task1 = hip.infer_task(ctx, cmask)
    rest = slice(k, None)
    obs_rest = torch.zeros_like(obs[:, rest])
    out1, _ = hip.filter(obs_rest, act[:, rest], mask[:, rest], task=task1, init=out0.next_prior[:, -1])
    d1 = hip.acrkn.rkn.decoder(out1.next_prior)
    mu1, var1 = hip.acrkn.readout(obs_rest, mask[:, rest], *d1, last=mu0[:, -1])
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(mean[:, :k], mu0, **tol)
    torch.testing.assert_close(mean[:, k:], mu1, **tol)
    torch.testing.assert_close(var[:, k:], var1, **tol)
    assert mean.dtype == dtype and mean.shape == obs.shape


def test_observed_windows_reinfer_the_task_and_the_state_is_not_restarted():
    """With window 1 observed, window 2's task comes from window 1 (not window 0); and window 1
    differs from a run that restarts the state there (the trajectory_world_model behaviour)."""
    dtype = torch.float64
    model = _model(dtype)
    obs, act, _ = _data(dtype, T=15)
    mask = torch.ones(obs.shape[:2], dtype=torch.bool)
    mask[:, 12:] = False
    mean, _ = model(obs, act, mask)
    hip, k = model.hip, 5
    ctx, cmask = context_features(obs[:, k:2 * k], act[:, k:2 * k], None, model.diff_shift, model.diff_scale)
    restarted, _ = hip(obs[:, k:2 * k], act[:, k:2 * k], mask[:, k:2 * k],
                       task=hip.infer_task(*context_features(obs[:, :k], act[:, :k], None, model.diff_shift,
                                                             model.diff_scale)))
    assert (mean[:, k:2 * k] - restarted).abs().max() > 1e-6
    # window 2's task: replace window 0 entirely -> window 2 changes only through the state
    task_w1 = hip.infer_task(ctx, cmask)
    assert task_w1.mean.shape == (3, 3)
    obs2 = obs.clone()
    obs2[:, :k] += 5.0
    mean2, _ = model(obs2, act, mask)
    assert (mean2[:, :k] - mean[:, :k]).abs().max() > 1e-3


def test_no_future_or_masked_observation_reaches_a_prediction_and_gradients_flow():
    dtype = torch.float64
    model = _model(dtype)
    obs, act, mask = _data(dtype)
    mean, var = model(obs, act, mask)
    obs2 = obs.clone()
    obs2[:, 13:] = 100.0                       # the future of index 12
    obs2[~mask] = float("nan")                 # masked values
    mean2, var2 = model(obs2, act, mask)
    torch.testing.assert_close(mean2[:, :13], mean[:, :13])
    torch.testing.assert_close(var2[:, :13], var[:, :13])
    assert bool((var > 0).all())
    (mean.square().mean() + var.log().mean()).backward()
    assert all(p.grad is not None for p in model.hip.context_encoder.parameters())


def test_bad_arguments_name_themselves():
    model = _model(torch.float32)
    with pytest.raises(ValueError, match="^window"):
        CarriedHiPRSSM(model.hip, 1)
    with pytest.raises(ValueError, match="^hip"):
        CarriedHiPRSSM(torch.nn.Linear(2, 2), 5)
    obs, act, mask = _data(torch.float32)
    with pytest.raises(ValueError, match="^mask"):
        model(obs, act, mask[:, :-1])
    with pytest.raises(ValueError, match="^obs"):
        model(obs[..., :2], act, mask)

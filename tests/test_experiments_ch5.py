"""Chapter 5's experiment: the HiP-RSSM scored through the runner sees its context (the previous
window) and its own first observed steps, nothing later; its own training runs on windows."""

from __future__ import annotations

import numpy as np
import torch

from pgm_wm.builders import build_hiprssm
from pgm_wm.datasets import SequenceData, split_sequences
from pgm_wm.datasets.windows import context_features
from pgm_wm.experiments.chapters import EXPERIMENTS, HiPRSSMWindowModel, ch5_experiment, train_hiprssm
from pgm_wm.experiments.runner import Experiment, ModelSpec, Protocol, Splits, train_model
from pgm_wm.evaluation import multistep_predict

H, C = 6, 2


def _model(seed: int = 0) -> HiPRSSMWindowModel:
    torch.manual_seed(seed)
    hip = build_hiprssm(2, 1, 3, 2, 8, 2, 1, task="linear")
    return HiPRSSMWindowModel(hip, H, torch.full((2,), 0.1), torch.full((2,), 2.0)).eval()


def test_scored_window_uses_previous_window_as_context_and_own_prefix_only():
    model = _model()
    gen = torch.Generator().manual_seed(1)
    obs, act = torch.randn(3, 2 * H, 2, generator=gen), torch.randn(3, 2 * H, 1, generator=gen)
    mean, var = multistep_predict(model, obs, act, H + C, H - C)
    # independent reference: the context set built by hand from the first window, the HiP-RSSM
    # filtering the second window with its first C steps observed
    ctx, cmask = context_features(obs[:, :H], act[:, :H], None, model.diff_shift, model.diff_scale)
    mask = torch.zeros(3, H, dtype=torch.bool)
    mask[:, :C] = True
    ref_m, ref_v, _, _ = model.hip.predict(obs[:, H:] * mask[..., None], act[:, H:], mask, ctx, cmask)
    torch.testing.assert_close(mean, ref_m[:, C - 1:H - 1])
    torch.testing.assert_close(var, ref_v[:, C - 1:H - 1])
    # the context matters: another first window changes the prediction
    other = obs.clone()
    other[:, :H] += 1.0
    assert not torch.allclose(multistep_predict(model, other, act, H + C, H - C)[0], mean)
    # later observations of the scored window do not
    later = obs.clone()
    later[:, H + C:] = 100.0
    torch.testing.assert_close(multistep_predict(model, later, act, H + C, H - C)[0], mean)


def _splits(n: int = 30, T: int = 4 * H) -> Splits:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(n, T, 1))
    o = np.zeros((n, T, 2))
    g = rng.uniform(0.5, 1.5, size=(n, 1))                       # a per-sequence gain: the task
    for t in range(T - 1):
        o[:, t + 1, 0] = 0.9 * o[:, t, 0] + g[:, 0] * a[:, t, 0]
        o[:, t + 1, 1] = 0.5 * o[:, t, 1] + 0.1 * rng.normal(size=n)
    parts = split_sequences(SequenceData.from_arrays(o, a), (0.6, 0.2, 0.2), seed=0)
    return Splits(*parts)


def test_train_hiprssm_fits_on_windows_within_the_budget():
    splits = _splits()
    p = Protocol(context_len=H + C, horizon=H - C, horizons=(1, H - C), eval_stride=2 * H, batch_size=8)
    exp = Experiment("t", "t", lambda: splits, {"hip": ModelSpec(lambda s: _model(), train=train_hiprssm)}, p)
    before = {k: v.clone() for k, v in _model().state_dict().items()}
    model, info = train_model(exp, "hip", seed=0, budget_s=0.5)
    assert info["epochs"] >= 1 and np.isfinite(info["best_valid"])
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_ch5_experiment_is_registered_with_the_two_window_protocol():
    exp = EXPERIMENTS["ch5"]()
    assert exp.name == "ch5_hidden_payload_arm"
    p = exp.protocol
    assert p.context_len == 25 + 12 and p.window == 50 and p.eval_stride == 50
    assert {"HiP-RSSM (linear task term)", "its ac-RKN core, no task", "LSTM", "GRU",
            "physics oracle (true parameters)", "physics oracle (nominal parameters)"} <= set(exp.models)
    assert exp.models["HiP-RSSM (linear task term)"].train is train_hiprssm
    assert ch5_experiment(window=20, observed=5).protocol.horizon == 15

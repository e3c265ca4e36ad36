"""fit as users run it (issue 24): no hang with zero batches, clear errors for an empty
validation set and a NaN gradient without clipping, Ctrl-C keeps the best parameters, a per-batch
progress bar, checkpoint and resume, a device argument, validation every k steps and the learning
curve. Each test failed (or hung) before the change it checks."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from pgm_wm.evaluation import evaluate_open_loop, multistep_predict
from pgm_wm.training import FitHistory, fit

DT = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def _problem(n: int = 96):
    g = torch.Generator().manual_seed(0)
    X = torch.randn(n, 3, generator=g, dtype=DT)
    y = X @ torch.tensor([1.0, -2.0, 0.5], dtype=DT) + 0.05 * torch.randn(n, generator=g, dtype=DT)
    return X, y


def _mse(w):
    return lambda b, g: ((b[0] @ w - b[1]) ** 2).mean()


# ----------------------------------------------------------------------------- zero batches, empty sets
def test_empty_training_set_is_an_error_not_zero_losses():
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    with pytest.raises(ValueError, match="^train_tensors: the training set is empty"):
        fit(_mse(w), [w], (X[:0], y[:0]), 8, epochs=3, progress=False)
    with pytest.raises(ValueError, match="^max_batches"):
        fit(_mse(w), [w], (X, y), 8, epochs=3, max_batches=0, progress=False)


def test_zero_batches_under_a_budget_returns_at_once():
    """Before: the budget was only checked after a batch, so with no batch the loop never ended."""
    code = textwrap.dedent(f"""
        import sys, torch
        sys.path.insert(0, {str(ROOT)!r})
        from pgm_wm.training import fit
        w = torch.zeros(3, requires_grad=True)
        for kw in (dict(), dict(max_batches=0)):
            X, y = (torch.zeros(0, 3), torch.zeros(0)) if not kw else (torch.zeros(8, 3), torch.zeros(8))
            try:
                fit(lambda b, g: ((b[0] @ w - b[1]) ** 2).mean(), [w], (X, y), 4, budget_s=5.0, progress=False, **kw)
                print("returned")
            except ValueError as err:
                print("ValueError", str(err).split(":")[0])
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split("\n")[:2] == ["ValueError train_tensors", "ValueError max_batches"]


def test_empty_validation_set_is_a_clear_error():
    model = lambda o, a, m: (o * 0, o * 0 + 1)  # noqa: E731
    obs, act = torch.zeros(0, 10, 2), torch.zeros(0, 10, 1)
    with pytest.raises(ValueError, match="^obs: no sequences"):
        evaluate_open_loop(model, obs, act, 3)
    with pytest.raises(ValueError, match="^obs: no sequences"):
        multistep_predict(model, obs, act, 3)
    # and fit names the validation when valid_fn raises
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    with pytest.raises(ValueError, match="^valid_fn: failed after 12 steps"):
        fit(_mse(w), [w], (X, y), 8, epochs=2, progress=False,
            valid_fn=lambda: float(evaluate_open_loop(model, obs, act, 3).rmse.mean()))


# ----------------------------------------------------------------------------- NaN gradient, Ctrl-C
def test_nan_gradient_without_clipping_is_an_error():
    w = torch.ones(3, dtype=DT, requires_grad=True)

    def loss(b, g):  # finite value (0), NaN gradient (d sqrt(x)/dx = inf at 0, times 0)
        return ((b[0] @ w - b[1]) ** 2).mean() * 0 + torch.sqrt(w - w.detach()).sum()

    X, y = _problem()
    with pytest.raises(ValueError, match="non-finite gradient norm at epoch 0, batch 0"):
        fit(loss, [w], (X, y), 8, epochs=1, clip_norm=None, progress=False)
    assert torch.equal(w.detach(), torch.ones(3, dtype=DT))


def test_a_run_that_diverges_can_stop_and_keep_its_best_parameters():
    """on_divergence="stop": a model output that turns non-finite after some steps ends the run
    (stopped "diverged", the message kept) with the best validated parameters, instead of raising;
    the default still raises, and so does a non-finite value at the very first step."""
    from pgm_wm._checks import check_positive

    X, y = _problem()

    def run(on_divergence, blow_up_at):
        w = torch.zeros(3, dtype=DT, requires_grad=True)
        calls, seen = [0], []

        def loss(b, g):
            calls[0] += 1
            var = torch.ones(1, dtype=DT) * (float("nan") if calls[0] > blow_up_at else 1.0)
            check_positive("var", var)          # what a model's predicted variance goes through
            return ((b[0] @ w - b[1]) ** 2).mean()

        def valid():
            seen.append(w.detach().clone())
            return float(((X @ w.detach() - y) ** 2).mean())

        hist = fit(loss, [w], (X, y), 8, lr=0.05, epochs=10, valid_every=4, valid_fn=valid, progress=False,
                   on_divergence=on_divergence)
        return w, hist, seen

    w, hist, seen = run("stop", blow_up_at=30)
    assert hist.stopped == "diverged" and "variances must be finite" in hist.diverged and "epoch 2" in hist.diverged
    assert hist.curve[-1]["step"] == 28 and hist.best_step == 28      # 30 steps ran, validated every 4
    best = int(np.argmin(hist.valid_loss))
    assert torch.equal(w.detach(), seen[best]) and bool(torch.isfinite(w).all())
    w_stop, ok, _ = run("stop", blow_up_at=10**6)                      # nothing diverges: nothing changes
    w_raise, same, _ = run("raise", blow_up_at=10**6)
    assert ok.stopped == "epochs" and ok.diverged is None and ok.steps[-1] == 120
    assert torch.equal(w_stop.detach(), w_raise.detach()) and ok.valid_loss == same.valid_loss
    assert [c["train"] for c in ok.curve] == [c["train"] for c in same.curve]
    with pytest.raises(ValueError, match=r"loss_fn: failed at epoch 2, batch 6 .*variances must be finite"):
        run("raise", blow_up_at=30)
    with pytest.raises(ValueError, match=r"loss_fn: failed at epoch 0, batch 0 .*variances must be finite"):
        run("stop", blow_up_at=0)                                       # at step 0: bad input, raised
    with pytest.raises(ValueError, match="^on_divergence"):
        run("ignore", blow_up_at=30)

    # a non-finite loss or gradient norm after the first step: the same stop
    w = torch.ones(3, dtype=DT, requires_grad=True)
    steps = [0]

    def nan_grad_later(b, g):
        steps[0] += 1
        base = ((b[0] @ w - b[1]) ** 2).mean()
        return base + (torch.sqrt(w - w.detach()).sum() if steps[0] > 5 else 0.0)

    hist = fit(nan_grad_later, [w], (X, y), 8, epochs=3, clip_norm=None, progress=False, on_divergence="stop")
    assert hist.stopped == "diverged" and "non-finite gradient norm" in hist.diverged and hist.curve == []
    assert bool(torch.isfinite(w).all())


def test_ctrl_c_restores_the_best_parameters_and_re_raises():
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    seen = {"batches": 0}
    valids = iter([1.0, 0.5, 2.0, 3.0])        # best after epoch 1

    def loss(b, g):
        seen["batches"] += 1
        if seen["batches"] == 3 * 12 + 5:         # Ctrl-C in the middle of epoch 3
            raise KeyboardInterrupt
        return _mse(w)(b, g)

    snap = {}

    def valid():
        v = next(valids)
        snap[len(snap)] = w.detach().clone()
        return v

    with pytest.raises(KeyboardInterrupt) as info:
        fit(loss, [w], (X, y), 8, epochs=10, valid_fn=valid, progress=False)
    assert torch.equal(w.detach(), snap[1])       # the parameters of the best validation
    hist = info.value.fit_history
    assert hist.stopped == "interrupted" and hist.best_epoch == 1 and hist.valid_loss == [1.0, 0.5, 2.0]


# ----------------------------------------------------------------------------- progress bar
def test_progress_bar_advances_per_batch(capsys):
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    fit(_mse(w), [w], (X, y), 32, epochs=2, progress=True)      # 3 batches per epoch
    err = capsys.readouterr().err
    assert "6/6" in err, err                                     # the bar counts batches, not epochs


# ----------------------------------------------------------------------------- valid_every and the curve
def test_valid_every_and_the_learning_curve():
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()                                            # 96 rows, batch 8: 12 steps per epoch
    calls = []
    values = [5.0, 4.0, 4.5, 4.6, 4.7, 4.8, 4.9]

    def valid():
        calls.append(1)
        return values[len(calls) - 1]

    losses = []

    def loss(b, g):
        value = _mse(w)(b, g)
        losses.append(float(value.detach()))
        return value

    hist = fit(loss, [w], (X, y), 8, epochs=3, valid_fn=valid, valid_every=5, patience=3, progress=False)
    # validations at steps 5, 10, 15, 20, 25: patience 3 runs out at the 5th (best was the 2nd)
    assert hist.valid_steps == [5, 10, 15, 20, 25] and len(calls) == 5
    assert hist.stopped == "patience" and hist.best_step == 10 and hist.best_epoch == 0
    assert [c["step"] for c in hist.curve] == [5, 10, 15, 20, 25]
    assert [c["epoch"] for c in hist.curve] == [0, 0, 1, 1, 2]
    assert [c["valid"] for c in hist.curve] == values[:5]
    for k, c in enumerate(hist.curve):                            # train = mean loss since the last validation
        assert c["train"] == pytest.approx(sum(losses[5 * k:5 * k + 5]) / 5, rel=1e-12)
        assert set(c) == {"step", "epoch", "cpu_s", "wall_s", "valid", "train", "lr"}
    assert all(a["cpu_s"] <= b["cpu_s"] and a["wall_s"] <= b["wall_s"] for a, b in zip(hist.curve, hist.curve[1:]))
    assert hist.steps == [12, 24, 25] and hist.epochs == 3 and hist.setup_cpu_s >= 0


def test_valid_every_validates_the_end_state_too():
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    hist = fit(_mse(w), [w], (X, y), 8, epochs=2, valid_fn=lambda: 1.0, valid_every=5, progress=False)
    assert hist.valid_steps == [5, 10, 15, 20, 24]
    with pytest.raises(ValueError, match="^valid_every"):
        fit(_mse(w), [w], (X, y), 8, epochs=2, valid_every=5, progress=False)


def test_curve_without_validation_has_one_entry_per_epoch():
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    hist = fit(_mse(w), [w], (X, y), 32, epochs=2, progress=False)
    assert [c["step"] for c in hist.curve] == [3, 6] and all(math.isnan(c["valid"]) for c in hist.curve)
    assert [c["train"] for c in hist.curve] == pytest.approx(hist.train_loss)


# ----------------------------------------------------------------------------- checkpoint and resume
def _net_fit(path, epochs, budget_s=None, **kw):
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1)).double()
    X, y = _problem()
    vals = iter(range(100, 0, -1))
    hist = fit(lambda b, g: ((net(b[0])[:, 0] - b[1]) ** 2).mean(), net, (X, y), 16, epochs, lr=1e-2,
               valid_fn=lambda: float(next(vals)), checkpoint=path, budget_s=budget_s, progress=False, **kw)
    return net, hist


def test_checkpoint_resume_equals_an_uninterrupted_run(tmp_path):
    straight, h1 = _net_fit(None, 5)
    path = tmp_path / "run" / "ckpt.pt"
    _net_fit(path, 2)
    assert path.exists()
    resumed, h2 = _net_fit(path, 5)
    assert h2.resumed_from_epoch == 2
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)
    assert h2.train_loss == h1.train_loss and h2.steps == h1.steps and h2.best_epoch == h1.best_epoch
    again, h3 = _net_fit(path, 5)                    # finished: nothing left to do
    assert h3.steps == h1.steps and torch.equal(again[0].weight, resumed[0].weight)


def test_checkpoint_carries_the_budget_used(tmp_path):
    path = tmp_path / "ckpt.pt"
    _, h1 = _net_fit(path, None, budget_s=0.2)
    assert h1.stopped == "budget"
    state = torch.load(path, weights_only=True)
    assert state["cpu_used"] >= 0.2
    _, h2 = _net_fit(path, None, budget_s=0.2)       # the budget is spent: no further step
    assert h2.steps == h1.steps and h2.stopped == "budget"


def test_checkpoint_of_other_parameters_is_an_error(tmp_path):
    path = tmp_path / "ckpt.pt"
    _net_fit(path, 1)
    w = torch.zeros(3, dtype=DT, requires_grad=True)
    X, y = _problem()
    with pytest.raises(ValueError, match="^checkpoint: .* other parameters"):
        fit(_mse(w), [w], (X, y), 8, epochs=2, checkpoint=path, progress=False)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="^checkpoint: .* cannot be read"):
        _net_fit(path, 2)


# ----------------------------------------------------------------------------- device
def test_device_argument_on_cpu_and_its_errors():
    net = nn.Linear(3, 1).double()
    X, y = _problem()
    hist = fit(lambda b, g: ((net(b[0])[:, 0] - b[1]) ** 2).mean(), net, (X, y), 32, 1, device="cpu", progress=False)
    assert isinstance(hist, FitHistory)
    with pytest.raises(ValueError, match="^device"):
        fit(lambda b, g: net(b[0]).sum(), net, (X, y), 32, 1, device="no such device", progress=False)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="^device: 'cuda' requested but CUDA is not available"):
            fit(lambda b, g: net(b[0]).sum(), net, (X, y), 32, 1, device="cuda", progress=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_device_cuda_trains_on_the_gpu():
    net = nn.Linear(3, 1).double()
    X, y = _problem()
    seen = []

    def loss(b, g):
        seen.append(b[0].device.type)
        return ((net(b[0])[:, 0] - b[1]) ** 2).mean()

    fit(loss, net, (X, y), 32, 2, device="auto", progress=False)
    assert set(seen) == {"cuda"} and next(net.parameters()).device.type == "cuda"


def test_plateau_schedule_halves_the_learning_rate_after_lr_patience_validations_without_improvement():
    """A validation loss that improves at validations 1, 2 and 5 only: with lr_patience 2 the
    learning rate is halved after validations 4, 7 and 9 (counting from 1), and never otherwise."""
    torch.manual_seed(0)
    w = torch.nn.Parameter(torch.zeros(3))
    losses = iter([5.0, 4.0, 4.5, 4.2, 3.0, 3.5, 3.1, 3.2, 3.3, 3.4])
    data = (torch.randn(8, 3),)
    hist = fit(lambda b, g: (b[0] @ w).square().mean(), [w], data, batch_size=8, epochs=10, lr=0.1,
               valid_fn=lambda: next(losses), lr_patience=2, keep_best=False)
    lrs = [c["lr"] for c in hist.curve]
    assert lrs == pytest.approx([0.1, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05, 0.025, 0.025, 0.0125])
    with pytest.raises(ValueError, match="lr_factor"):
        fit(lambda b, g: (b[0] @ w).sum(), [w], data, batch_size=8, epochs=1, valid_fn=lambda: 1.0, lr_factor=1.0)
    with pytest.raises(ValueError, match="lr_patience"):
        fit(lambda b, g: (b[0] @ w).sum(), [w], data, batch_size=8, epochs=1, lr_patience=3)


def test_plateau_schedule_stops_at_lr_min_and_the_optimizer_uses_the_floored_rate():
    """Never an improvement after the first validation, lr_patience 1, factor 0.5, floor 0.03:
    the optimizer's rate (recorded in the curve) goes 0.1 -> 0.05 -> 0.03 (clamped, not 0.025)
    and stays there. Without a floor the same run ends at 0.1 / 2**8."""
    data = (torch.randn(8, 3),)

    def run(**kw):
        w = torch.nn.Parameter(torch.zeros(3))
        return fit(lambda b, g: (b[0] @ w).square().mean(), [w], data, batch_size=8, epochs=10, lr=0.1,
                   valid_fn=lambda: 1.0, lr_patience=1, keep_best=False, **kw)

    floored = [c["lr"] for c in run(lr_min=0.03).curve]
    assert floored == pytest.approx([0.1, 0.1, 0.05, 0.03, 0.03, 0.03, 0.03, 0.03, 0.03, 0.03])
    free = [c["lr"] for c in run().curve]
    assert free[-1] == pytest.approx(0.1 / 2 ** 8)
    for bad in (-1e-3, 0.2):
        with pytest.raises(ValueError, match="lr_min"):
            run(lr_min=bad)

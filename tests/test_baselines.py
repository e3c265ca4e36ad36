"""Tests for the baseline world models: interface, causality, the feedback/memory rule, the FFNN
window, open-loop prediction that ignores future observations and stays finite for 10,000 steps,
the trivial references (repeat-last, training mean, linear ARX) against closed forms, and the
Transformer's ALiBi slopes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.baselines import (
    FFNNBaseline,
    GRUBaseline,
    LinearARX,
    LSTMBaseline,
    RepeatLast,
    RKNActionsAsObs,
    TrainingMean,
    alibi_causal_bias,
)
from pgm_wm.evaluation import multistep_predict

DT = torch.float64
BUILDERS = {
    "rkn": lambda: RKNActionsAsObs(2, 3, 4, num_basis=3, bandwidth=1, enc_hidden=(8,), dec_hidden=(8,)),
    "lstm": lambda: LSTMBaseline(2, 3, 8, (8,), (8,)),
    "gru": lambda: GRUBaseline(2, 3, 8, (8,), (8,)),
    "ffnn": lambda: FFNNBaseline(2, 3, window=3, hidden=(8, 8)),
}


def build(name):
    torch.manual_seed(0)
    return BUILDERS[name]().double()


def data(B=3, T=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, T, 2, generator=g, dtype=DT), torch.randn(B, T, 3, generator=g, dtype=DT),
            torch.rand(B, T, generator=g) < 0.6)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_shapes_positive_variance_and_causality(name):
    model = build(name)
    obs, act, mask = data()
    mean, var = model(obs, act, mask)
    assert mean.shape == var.shape == obs.shape
    assert bool((var > 0).all())
    t0 = 5
    obs2, act2 = obs.clone(), act.clone()
    obs2[:, t0 + 1:] += 3.0
    act2[:, t0 + 1:] -= 2.0
    obs2[~mask] = float("nan")  # masked values are never read
    mean2, var2 = model(obs2, act2, mask)
    torch.testing.assert_close(mean2[:, : t0 + 1], mean[:, : t0 + 1])
    torch.testing.assert_close(var2[:, : t0 + 1], var[:, : t0 + 1])
    act3 = act.clone()
    act3[:, t0] += 1.0  # a_t does influence the prediction of o_{t+1}
    assert not torch.allclose(model(obs, act3, mask)[0][:, t0], mean[:, t0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(BUILDERS))
def test_fast_loop_equals_the_step_by_step_reference(name, dtype):
    """forward (inputs known in advance applied before the loop, variances after it) equals
    forward_reference (step() at every step): values and parameter gradients."""
    torch.manual_seed(0)
    model = BUILDERS[name]().to(dtype)
    obs, act, mask = (x.to(dtype) if x.is_floating_point() else x for x in data(4, 12))
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-11, atol=1e-11)
    fast, ref = model(obs, act, mask), model.forward_reference(obs, act, mask)
    w = torch.randn_like(obs)
    params = list(model.parameters())
    g_fast = torch.autograd.grad(((fast[0] + fast[1]) * w).sum(), params, allow_unused=True)
    g_ref = torch.autograd.grad(((ref[0] + ref[1]) * w).sum(), params, allow_unused=True)
    for a, b in zip(fast + g_fast, ref + g_ref):
        if a is None or b is None:
            assert a is None and b is None
        else:
            torch.testing.assert_close(a, b, **tol)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_batch_equals_sequential(name):
    model = build(name)
    obs, act, mask = data(B=3)
    mean, _ = model(obs, act, mask)
    for b in range(3):
        torch.testing.assert_close(model(obs[b:b + 1], act[b:b + 1], mask[b:b + 1])[0][0], mean[b])


def test_ffnn_depends_only_on_its_window():
    model = build("ffnn")  # window 3
    obs, act, _ = data(B=2, T=10)
    mean, _ = model(obs, act)
    obs2 = obs.clone()
    obs2[:, :4] = torch.randn_like(obs2[:, :4])  # outputs at t >= 6 see inputs 4..t only
    act2 = act.clone()
    act2[:, :4] = 0.0
    mean2, _ = model(obs2, act2)
    torch.testing.assert_close(mean2[:, 6:], mean[:, 6:])
    assert not torch.allclose(mean2[:, 5], mean[:, 5])


@pytest.mark.parametrize("name", list(BUILDERS))
def test_multistep_ignores_future(name):
    model = build(name)
    obs, act, _ = data(B=2, T=20)
    ref = multistep_predict(model, obs, act, 6, 10)
    bad = obs.clone()
    bad[:, 6:] = float("nan")
    out = multistep_predict(model, bad, act, 6, 10)
    torch.testing.assert_close(out[0], ref[0])
    torch.testing.assert_close(out[1], ref[1])


def test_bad_inputs():
    model = build("lstm")
    obs, act, mask = data()
    with pytest.raises(ValueError, match="actions"):
        model(obs, act[..., :2], mask)
    with pytest.raises(ValueError, match="obs"):
        model(obs[..., :1], act, mask)
    with pytest.raises(ValueError, match="mask"):
        model(obs, act, mask[:, :3])
    with pytest.raises(ValueError, match="window"):
        FFNNBaseline(2, 3, window=0)
    with pytest.raises(ValueError, match="hidden"):
        LSTMBaseline(2, 3, hidden=0)


# ----------------------------------------------------------------------------- long open loop (issue 13)
LONG = 10_000


@pytest.mark.parametrize("name", ["lstm", "gru", "ffnn", "rkn", "repeat_last", "training_mean", "arx"])
def test_untrained_baselines_stay_finite_over_10000_open_loop_steps(name):
    torch.manual_seed(0)
    model = {"repeat_last": lambda: RepeatLast(2), "training_mean": lambda: TrainingMean([0.0, 1.0], [1.0, 2.0]),
             "arx": lambda: LinearARX(2, 3, 2)}.get(name, lambda: BUILDERS[name]())()
    obs, act, _ = (x.float() for x in data(B=1, T=LONG + 5, seed=3))  # float32, the default dtype
    with torch.no_grad():
        mean, var = multistep_predict(model, obs, act, 5)
    assert mean.shape == (1, LONG, 2)
    assert bool(torch.isfinite(mean).all()) and bool(torch.isfinite(var).all()) and bool((var > 0).all())
    # at most a linear drift (the ReLU FFNN grew geometrically, to 5e23 here and NaN in larger nets)
    assert float(mean.abs().max()) < 100 * LONG and float(var.max()) < 1e3 * LONG


# ----------------------------------------------------------------------------- trivial references
def _arx_system(n=4, T=200, seed=0):
    """o_{t+1} = A0 o_t + A1 o_{t-1} + B0 a_t + c, no noise (a stable AR(2) with inputs)."""
    g = torch.Generator().manual_seed(seed)
    A0 = torch.tensor([[0.5, 0.1], [-0.2, 0.4]], dtype=DT)
    A1 = torch.tensor([[0.2, 0.0], [0.05, -0.1]], dtype=DT)
    B0 = torch.tensor([[1.0, 0.0, -0.5], [0.3, 0.2, 0.0]], dtype=DT)
    c = torch.tensor([0.1, -0.3], dtype=DT)
    act = torch.randn(n, T, 3, generator=g, dtype=DT)
    obs = torch.zeros(n, T, 2, dtype=DT)
    obs[:, :2] = torch.randn(n, 2, 2, generator=g, dtype=DT)
    for t in range(1, T - 1):
        obs[:, t + 1] = obs[:, t] @ A0.T + obs[:, t - 1] @ A1.T + act[:, t] @ B0.T + c
    return obs, act, (A0, A1, B0, c)


def test_arx_fit_recovers_a_noiseless_system_and_equals_the_ridge_normal_equations():
    obs, act, (A0, A1, B0, c) = _arx_system()
    model = LinearARX.fit(obs, act, order=2, ridge=0.0)
    W = model.weight
    torch.testing.assert_close(W[:, :2], A0, atol=1e-8, rtol=0)
    torch.testing.assert_close(W[:, 2:4], A1, atol=1e-8, rtol=0)
    torch.testing.assert_close(W[:, 4:7], B0, atol=1e-8, rtol=0)
    torch.testing.assert_close(W[:, 7:], torch.zeros(2, 3, dtype=DT), atol=1e-8, rtol=0)
    torch.testing.assert_close(model.bias, c, atol=1e-8, rtol=0)
    # noisy data and a ridge: numpy's solution of the augmented least-squares problem
    g = np.random.default_rng(0)
    noisy = obs + torch.as_tensor(0.05 * g.normal(size=obs.shape))
    lam = 0.3
    m = LinearARX.fit(noisy, act, order=2, ridge=lam)
    o, a = noisy.numpy(), act.numpy()
    rows = [(np.concatenate([o[b, t], o[b, t - 1], a[b, t], a[b, t - 1], [1.0]]), o[b, t + 1])
            for b in range(o.shape[0]) for t in range(1, o.shape[1] - 1)]
    X, Y = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    P = np.sqrt(lam) * np.eye(X.shape[1])[:-1]  # no penalty on the bias
    sol = np.linalg.lstsq(np.vstack([X, P]), np.vstack([Y, np.zeros((P.shape[0], 2))]), rcond=None)[0]
    np.testing.assert_allclose(m.weight.numpy(), sol[:-1].T, atol=1e-9)
    np.testing.assert_allclose(m.bias.numpy(), sol[-1], atol=1e-9)
    np.testing.assert_allclose(m.var.numpy(), ((Y - X @ sol) ** 2).mean(0), rtol=1e-8)


def test_arx_predictions_one_step_and_open_loop_follow_the_recursion():
    obs, act, (A0, A1, B0, c) = _arx_system(n=2, T=40)
    model = LinearARX.fit(obs, act, order=2, ridge=0.0)
    mean, var = model(obs, act, None)
    want = obs[:, 1:-1] @ A0.T + obs[:, :-2] @ A1.T + act[:, 1:-1] @ B0.T + c
    torch.testing.assert_close(mean[:, 1:-1], want, atol=1e-8, rtol=0)
    # open loop from a context of 5: the noiseless system is reproduced exactly
    pm, _ = multistep_predict(model, obs, act, 5)
    torch.testing.assert_close(pm, obs[:, 5:], atol=1e-7, rtol=0)
    with pytest.raises(ValueError, match="order"):
        LinearARX(2, 3, 0)
    with pytest.raises(ValueError, match="valid"):
        LinearARX.fit(obs, act, 2, valid=torch.zeros(2, 40, dtype=torch.bool))


def test_repeat_last_and_training_mean_against_closed_forms():
    obs, act, mask = data(B=3, T=12, seed=5)
    rl = RepeatLast.fit(obs)
    d2 = ((obs[:, 1:] - obs[:, :-1]) ** 2).reshape(-1, 2).mean(0)
    torch.testing.assert_close(rl.step_var, d2)
    mean, var = rl(obs, act, mask)
    for b in range(3):
        last, age = None, 0
        for t in range(12):
            if mask[b, t]:
                last, age = obs[b, t], 0
            age += 1
            want = torch.zeros(2, dtype=DT) if last is None else last
            torch.testing.assert_close(mean[b, t], want)
            torch.testing.assert_close(var[b, t], age * d2)
    tm = TrainingMean.fit(obs, mask)
    x = obs[mask].numpy()
    np.testing.assert_allclose(tm.mean.numpy(), x.mean(0))
    np.testing.assert_allclose(tm.var.numpy(), x.var(0))
    m2, v2 = tm(obs, act, mask)
    assert m2.shape == obs.shape and torch.equal(m2[1, 3], tm.mean) and torch.equal(v2[2, 7], tm.var)
    with pytest.raises(ValueError, match="var"):
        TrainingMean([0.0], [0.0])
    with pytest.raises(ValueError, match="obs"):
        RepeatLast.fit(torch.full((1, 3, 2), float("nan"), dtype=DT))


# ----------------------------------------------------------------------------- Transformer: ALiBi slopes
@pytest.mark.parametrize("n_heads", [1, 2, 4, 8])
def test_alibi_slopes_and_causal_mask_against_their_closed_form(n_heads):
    T = 7
    bias = alibi_causal_bias(T, n_heads, torch.zeros((), dtype=DT))
    assert bias.shape == (n_heads, T, T)
    # closed form: a geometric sequence starting at 2^(-8/n) with the same ratio (n = 8: 1/2, ..., 1/256)
    r = 2.0 ** (-8.0 / n_heads)
    for h in range(n_heads):
        for i in range(T):
            for j in range(T):
                want = -(r ** (h + 1)) * (i - j) if j <= i else float("-inf")
                assert float(bias[h, i, j]) == pytest.approx(want, rel=1e-12, abs=0.0)
    if n_heads == 8:
        assert [float(-bias[h, 1, 0]) for h in range(8)] == [2.0 ** -(k + 1) for k in range(8)]

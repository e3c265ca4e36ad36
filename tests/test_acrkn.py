"""Tests for the action-conditional RKN (Chapter 4): control models, predict step, readout,
inverse dynamics. Oracles: the dense Kalman filter with a control input (pgm_wm.kalman), the
plain RKN, explicit recursions, and causality/perturbation properties."""

from __future__ import annotations

import pytest
import torch

from pgm_wm.acrkn import (
    AcRKN,
    DifferenceReadout,
    InverseDynamicsHead,
    LinearControl,
    LocallyLinearControl,
    MLPControl,
    ZeroControl,
    difference_scaling,
    inverse_dynamics,
    inverse_dynamics_loss,
)
from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder

from _helpers import linear_acrkn

DT = torch.float64


def make_model(m=4, do=3, da=2, control="mlp", num_basis=5, bandwidth=1, predict_differences=True, seed=0, **kw):
    torch.manual_seed(seed)
    ctrl = {
        "mlp": lambda: MLPControl(da, m, (16,)),
        "linear": lambda: LinearControl(da, m),
        "local": lambda: LocallyLinearControl(da, m, 3),
        "zero": lambda: ZeroControl(da, m),
    }[control]()
    model = AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, num_basis, bandwidth), ctrl,
                  BeliefDecoder(m, do, (16,), (16,)), predict_differences=predict_differences, **kw)
    return model.to(DT)


def data(B=3, T=12, do=3, da=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, T, do, generator=g, dtype=DT), torch.randn(B, T, da, generator=g, dtype=DT),
            torch.rand(B, T, generator=g) < 0.6)


def beliefs_equal(a, b, **tol):
    for f in ("mean", "var_upper", "var_lower", "cov_side"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), **tol)


# ----------------------------------------------------------------------------------- control models

def test_linear_control_is_matrix_product():
    c = LinearControl(2, 3).to(DT)
    a = torch.randn(5, 2, dtype=DT)
    torch.testing.assert_close(c(a, torch.zeros(5, 6, dtype=DT)), (c.B @ a.T).T)


def test_locally_linear_control_matches_loop_and_reduces_to_linear():
    c = LocallyLinearControl(2, 3, num_basis=4).to(DT)
    a, z = torch.randn(7, 2, dtype=DT), torch.randn(7, 6, dtype=DT)
    beta = c.coefficients(z)
    torch.testing.assert_close(beta.sum(-1), torch.ones(7, dtype=DT))
    assert bool((beta >= 0).all())
    want = torch.stack([sum(beta[i, k] * c.basis[k] @ a[i] for k in range(4)) for i in range(7)])
    torch.testing.assert_close(c(a, z), want)
    c1 = LocallyLinearControl(2, 3, num_basis=1).to(DT)
    torch.testing.assert_close(c1(a, z), a @ c1.basis[0].T)


def test_mlp_control_ignores_state_and_zero_control_is_zero():
    c = MLPControl(2, 3, (8,)).to(DT)
    a = torch.randn(4, 2, dtype=DT)
    torch.testing.assert_close(c(a, torch.randn(4, 6, dtype=DT)), c(a, torch.randn(4, 6, dtype=DT)))
    assert torch.equal(ZeroControl(2, 3)(a, torch.ones(4, 6, dtype=DT)), torch.zeros(4, 6, dtype=DT))


# ------------------------------------------------------------------------- reduction to the RKN

@pytest.mark.parametrize("control", ["zero", "mlp", "local"])
def test_dropping_the_control_cause_gives_the_rkn(control):
    """ac-RKN = RKN + [control cause]: filtering with the causes list minus its last entry is
    the Chapter-3 RKN exactly, for a known (MLP) and a state-dependent (locally linear) control."""
    model = make_model(control=control)
    obs, act, mask = data()
    causes = model.causes(act)
    assert len(causes) == 1
    w = model.rkn.encode(obs, mask)
    rkn_only = model.rkn.filter(w, mask=mask)
    dropped = model.rkn.filter(w, mask=mask, causes=causes[:-1])
    for name in ("prior", "posterior", "next_prior"):
        beliefs_equal(getattr(dropped, name), getattr(rkn_only, name), rtol=0, atol=0)
    full = model.filter(obs, act, mask)
    if control == "zero":  # b = 0: the control cause is a zero point mass
        beliefs_equal(full.next_prior, rkn_only.next_prior, rtol=0, atol=0)
    else:
        assert not torch.allclose(full.next_prior.mean, rkn_only.next_prior.mean)
    # no actions at all: the same RKN
    beliefs_equal(model.filter(obs, None, mask).next_prior, rkn_only.next_prior, rtol=0, atol=0)


def test_control_term_enters_first_predict_mean_exactly():
    model = make_model(control="local")
    obs, act, mask = data()
    out = model.filter(obs, act, mask)
    ref = model.filter(obs, None, mask)
    post0 = out.posterior.at(0)
    b0 = model.control(act[:, 0], post0.mean)
    torch.testing.assert_close(out.next_prior.mean[:, 0], ref.next_prior.mean[:, 0] + b0)


def test_linear_acrkn_equals_dense_kalman_filter_with_control():
    """Diagonal blocks (bandwidth 0), one basis matrix, identity encoder, linear control:
    the ac-RKN must be the dense Kalman filter with F = A, B u = B a (Eq. acrkn-predict)."""
    m, da, B, T = 3, 2, 2, 9
    model = linear_acrkn(m, da, seed=3)
    trans, ctrl, r = model.transition, model.control, model.encoder.var
    g = torch.Generator().manual_seed(0)
    y, u = torch.randn(B, T, m, generator=g, dtype=DT), torch.randn(B, T, da, generator=g, dtype=DT)
    mask = torch.rand(B, T, generator=g) < 0.5
    out = model.filter(y, u, mask)
    F = trans.dense_matrix(torch.zeros(2 * m, dtype=DT))
    H = torch.cat([torch.eye(m, dtype=DT), torch.zeros(m, m, dtype=DT)], 1)
    init = Gaussian(torch.zeros(2 * m, dtype=DT), 2.0 * torch.eye(2 * m, dtype=DT))
    kf = kalman_filter(y, init, F, H, torch.diag(trans.trans_var.detach()), torch.diag(r), mask,
                       B=ctrl.B.detach(), u=u)
    nxt = kf.next_prior
    dense = out.next_prior.to_dense()
    torch.testing.assert_close(dense.mean, nxt.mean, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(dense.cov, nxt.cov, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.posterior.to_dense().cov, kf.posterior.cov, rtol=1e-10, atol=1e-10)


# --------------------------------------------------------------- action affects only the mean

def test_action_changes_mean_not_covariance_constant_transition():
    model = make_model(num_basis=1)
    obs, act, mask = data()
    out1 = model.filter(obs, act, mask)
    out2 = model.filter(obs, act + 3.0 * torch.randn_like(act), mask)
    for f in ("var_upper", "var_lower", "cov_side"):
        assert torch.equal(getattr(out1.next_prior, f), getattr(out2.next_prior, f))
    assert not torch.allclose(out1.next_prior.mean, out2.next_prior.mean)
    _, v1 = model(obs, act, mask)
    _, v2 = model(obs, act * -2.0, mask)
    assert torch.equal(v1, v2)


def test_action_leaves_one_predict_step_covariance_unchanged_locally_linear():
    """With a state-dependent A the covariance of a *single* predict step from the same
    posterior must not depend on the action (later steps may, through A(z))."""
    model = make_model(num_basis=5, control="local")
    obs, act, mask = data()
    out1 = model.filter(obs, act, mask)
    out2 = model.filter(obs, act.flip(-1) + 1.0, mask)
    for f in ("var_upper", "var_lower", "cov_side"):
        assert torch.equal(getattr(out1.next_prior, f)[:, 0], getattr(out2.next_prior, f)[:, 0])
    assert not torch.allclose(out1.next_prior.mean[:, 0], out2.next_prior.mean[:, 0])


# --------------------------------------------------------------------------- readout / memory

def test_difference_readout_memory_rule_matches_recursion():
    shift, scale = torch.tensor([0.1, -0.2, 0.0], dtype=DT), torch.tensor([0.5, 2.0, 1.0], dtype=DT)
    model = make_model(diff_shift=shift, diff_scale=scale)
    obs, act, mask = data()
    mean, var = model(obs, act, mask)
    d_mean, d_var = model.decoder(model.filter(obs, act, mask).next_prior)
    B, T, _ = obs.shape
    for b in range(B):
        last = torch.zeros(3, dtype=DT)
        for t in range(T):
            mem = obs[b, t] if mask[b, t] else last
            want = mem + shift + scale * d_mean[b, t]
            torch.testing.assert_close(mean[b, t], want)
            torch.testing.assert_close(var[b, t], scale**2 * (d_var[b, t] + model.readout.var_floor))
            last = want


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_difference_readout_running_sum_equals_the_step_by_step_loop(dtype):
    """The vectorized readout (one running sum and a gather) against its loop, with a carried
    memory, leading masked steps, long unobserved stretches, and gradients."""
    g = torch.Generator().manual_seed(3)
    B, T, do = 4, 60, 3
    ro = DifferenceReadout(do, True, torch.tensor([0.1, -0.2, 0.0]), torch.tensor([0.5, 2.0, 1.0])).to(dtype)
    obs = torch.randn(B, T, do, generator=g, dtype=dtype)
    mask = torch.rand(B, T, generator=g) < 0.2
    mask[0] = False                      # never observed: the memory is `last` plus the running sum
    mask[1, :30] = False
    d_mean = torch.randn(B, T, do, generator=g, dtype=dtype, requires_grad=True)
    d_var = torch.rand(B, T, do, generator=g, dtype=dtype)
    last = torch.randn(B, do, generator=g, dtype=dtype, requires_grad=True)
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    for carried in (None, last):
        fast, ref = ro(obs, mask, d_mean, d_var, carried), ro.loop(obs, mask, d_mean, d_var, carried)
        for a, b in zip(fast, ref):
            torch.testing.assert_close(a, b, **tol)
        w = torch.randn(B, T, do, generator=g, dtype=dtype)
        leaves = [d_mean] + ([] if carried is None else [last])
        for a, b in zip(torch.autograd.grad((fast[0] * w).sum(), leaves), torch.autograd.grad((ref[0] * w).sum(), leaves)):
            torch.testing.assert_close(a, b, **tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("T", [1, 2, 7, 60])
def test_hybrid_readout_scan_equals_the_step_by_step_loop(dtype, T):
    """The hybrid readout's log-depth scan against its loop: values and gradients (decoder
    outputs, gate logit, carried memory), with leading masked steps, a never-observed sequence,
    long unobserved stretches, and sequence lengths that are and are not powers of two."""
    from pgm_wm.acrkn import HybridReadout

    g = torch.Generator().manual_seed(5)
    B, do = 4, 3
    ro = HybridReadout(do, torch.tensor([0.1, -0.2, 0.0]), torch.tensor([0.5, 2.0, 1.0])).to(dtype)
    with torch.no_grad():
        ro.gate_logit.copy_(torch.tensor([2.0, -0.5, 0.3]))
    obs = torch.randn(B, T, do, generator=g, dtype=dtype)
    mask = torch.rand(B, T, generator=g) < 0.3
    mask[0] = False
    mask[1, : T // 2] = False
    obs[~mask] = float("nan")            # masked values are never read
    d_mean = torch.randn(B, T, 2 * do, generator=g, dtype=dtype, requires_grad=True)
    d_var = torch.rand(B, T, 2 * do, generator=g, dtype=dtype, requires_grad=True)
    last = torch.randn(B, do, generator=g, dtype=dtype, requires_grad=True)
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    for carried in (None, last):
        fast, ref = ro(obs, mask, d_mean, d_var, carried), ro.loop(obs, mask, d_mean, d_var, carried)
        for a, b in zip(fast, ref):
            assert a.dtype == dtype and torch.isfinite(a).all()
            torch.testing.assert_close(a, b, **tol)
        w = torch.randn(B, T, do, generator=g, dtype=dtype)
        leaves = [d_mean, d_var, ro.gate_logit] + ([] if carried is None else [last])
        grads = [torch.autograd.grad(((out[0] + out[1]) * w).sum(), leaves) for out in (fast, ref)]
        for a, b in zip(*grads):
            torch.testing.assert_close(a, b, **tol)


def test_absolute_prediction_mode_is_the_decoder_output():
    model = make_model(predict_differences=False)
    obs, act, mask = data()
    mean, var = model(obs, act, mask)
    d_mean, d_var = model.decoder(model.filter(obs, act, mask).next_prior)
    torch.testing.assert_close(mean, d_mean)
    torch.testing.assert_close(var, d_var + model.readout.var_floor)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hybrid_readout_is_the_gated_mix_and_its_limits_are_the_two_readouts(dtype):
    """Eq. (acrkn-hybrid) against a hand-written loop; gate logits of +-40 reproduce the
    difference readout (first half of the decoder output) and the absolute one (second half)."""
    from pgm_wm.acrkn import DifferenceReadout, HybridReadout

    g = torch.Generator().manual_seed(3)
    B, T, do = 3, 7, 2
    obs = torch.randn(B, T, do, generator=g, dtype=dtype)
    mask = torch.rand(B, T, generator=g) < 0.5
    d_mean = torch.randn(B, T, 2 * do, generator=g, dtype=dtype)
    d_var = torch.rand(B, T, 2 * do, generator=g, dtype=dtype) + 0.1
    shift, scale = torch.tensor([0.1, -0.2]), torch.tensor([0.5, 2.0])
    hyb = HybridReadout(do, shift, scale)
    with torch.no_grad():
        hyb.gate_logit.copy_(torch.tensor([0.3, -1.1]))
    mean, var = hyb(obs, mask, d_mean, d_var)
    gate = torch.sigmoid(torch.tensor([0.3, -1.1], dtype=dtype))
    sh, sc, fl = shift.to(dtype), scale.to(dtype), hyb.var_floor
    for b in range(B):
        last = torch.zeros(do, dtype=dtype)
        for t in range(T):
            mem = obs[b, t] if mask[b, t] else last
            want = gate * (mem + sh + sc * d_mean[b, t, :do]) + (1 - gate) * d_mean[b, t, do:]
            want_var = gate**2 * sc**2 * (d_var[b, t, :do] + fl) + (1 - gate) ** 2 * (d_var[b, t, do:] + fl)
            torch.testing.assert_close(mean[b, t], want)
            torch.testing.assert_close(var[b, t], want_var)
            last = want
    assert mean.dtype == dtype
    for logit, ref, half in ((40.0, DifferenceReadout(do, True, shift, scale), slice(0, do)),
                             (-40.0, DifferenceReadout(do, False), slice(do, 2 * do))):
        with torch.no_grad():
            hyb.gate_logit.fill_(logit)
        got, ref_out = hyb(obs, mask, d_mean, d_var), ref(obs, mask, d_mean[..., half], d_var[..., half])
        torch.testing.assert_close(got[0], ref_out[0])
        torch.testing.assert_close(got[1], ref_out[1])
    with pytest.raises(ValueError, match="^delta_mean"):
        hyb.step(obs[:, 0], d_mean[:, 0, :do], d_var[:, 0, :do])


def test_hybrid_acrkn_builds_trains_and_checks_its_decoder_size():
    from pgm_wm.acrkn import AcRKN, HybridReadout
    from pgm_wm.builders import build_acrkn

    model = build_acrkn(3, 2, latent_obs_dim=4, hidden=8, num_basis=2, bandwidth=1, readout="hybrid")
    assert isinstance(model.readout, HybridReadout) and model.obs_dim == 3 and model.decoder.out_dim == 6
    obs, act, mask = torch.randn(2, 6, 3), torch.randn(2, 6, 2), torch.rand(2, 6) < 0.7
    mean, var = model(obs, act, mask)
    assert mean.shape == var.shape == (2, 6, 3) and bool((var > 0).all())
    (mean.square().mean() + var.mean()).backward()
    assert model.readout.gate_logit.grad is not None and bool(model.readout.gate_logit.grad.abs().sum() > 0)
    with pytest.raises(ValueError, match="^decoder"):
        AcRKN(model.encoder, model.transition, model.control, model.decoder, readout=HybridReadout(6))
    with pytest.raises(ValueError, match="^readout"):
        build_acrkn(3, 2, readout="sum")


def test_difference_scaling_from_stats():
    stats = {"obs_mean": torch.tensor([1.0, 2.0]), "obs_std": torch.tensor([2.0, 4.0]),
             "diff_mean": torch.tensor([0.2, -0.4]), "diff_std": torch.tensor([0.5, 1.0])}
    shift, scale = difference_scaling(stats)
    # a standardized difference d means o_{t+1} - o_t = diff_mean + diff_std d in original units
    d = torch.tensor([0.7, -1.3])
    o_t = torch.tensor([0.3, 5.0])
    o_next = o_t + stats["diff_mean"] + stats["diff_std"] * d
    norm = lambda x: (x - stats["obs_mean"]) / stats["obs_std"]  # noqa: E731
    torch.testing.assert_close(norm(o_t) + shift + scale * d, norm(o_next))
    with pytest.raises(ValueError, match="stats"):
        difference_scaling({"obs_std": torch.ones(2)})


# --------------------------------------------------------------------------- causality

def test_prediction_uses_no_future_or_masked_observation():
    model = make_model()
    obs, act, mask = data(T=10)
    mean, var = model(obs, act, mask)
    t0 = 4
    obs2 = obs.clone()
    obs2[:, t0 + 1:] = torch.randn_like(obs2[:, t0 + 1:]) * 10
    act2 = act.clone()
    act2[:, t0 + 1:] = 5.0
    obs2[~mask] = float("nan")  # masked values must be ignored, NaN included
    mean2, var2 = model(obs2, act2, mask)
    torch.testing.assert_close(mean2[:, : t0 + 1], mean[:, : t0 + 1])
    torch.testing.assert_close(var2[:, : t0 + 1], var[:, : t0 + 1])
    # the action a_t does influence the prediction of o_{t+1}
    act3 = act.clone()
    act3[:, t0] += 1.0
    mean3, _ = model(obs, act3, mask)
    torch.testing.assert_close(mean3[:, :t0], mean[:, :t0])
    assert not torch.allclose(mean3[:, t0], mean[:, t0])


def test_nan_at_masked_steps_gives_finite_gradients():
    model = make_model()
    obs, act, mask = data()
    obs = obs.clone()
    obs[~mask] = float("nan")
    mean, var = model(obs, act, mask)
    loss = (mean[:, :-1] - torch.nan_to_num(obs[:, 1:])).pow(2).mean() + var.mean()
    loss.backward()
    for p in model.parameters():
        if p.grad is not None:
            assert bool(torch.isfinite(p.grad).all())


def test_batch_equals_sequential():
    model = make_model()
    obs, act, mask = data(B=4)
    mean, var = model(obs, act, mask)
    for b in range(4):
        mb, vb = model(obs[b:b + 1], act[b:b + 1], mask[b:b + 1])
        torch.testing.assert_close(mb[0], mean[b])
        torch.testing.assert_close(vb[0], var[b])


# --------------------------------------------------------------------------- inverse dynamics

def test_inverse_dynamics_does_not_see_the_action_it_predicts():
    model = make_model()
    head = InverseDynamicsHead(4, 2, (8,)).to(DT)
    obs, act, _ = data(T=8)
    a_hat, _, _ = inverse_dynamics(model, head, obs, act, action_feedback=True)
    t0 = 3
    act2 = act.clone()
    act2[:, t0] += 2.0
    a_hat2, _, _ = inverse_dynamics(model, head, obs, act2, action_feedback=True)
    torch.testing.assert_close(a_hat2[:, : t0 + 1], a_hat[:, : t0 + 1])
    assert not torch.allclose(a_hat2[:, t0 + 1], a_hat[:, t0 + 1])  # fed back afterwards
    a_nf, _, _ = inverse_dynamics(model, head, obs, act, action_feedback=False)
    a_nf2, _, _ = inverse_dynamics(model, head, obs, act2, action_feedback=False)
    torch.testing.assert_close(a_nf, a_nf2)  # no feedback: actions never used


def test_inverse_dynamics_loss_value():
    model = make_model()
    head = InverseDynamicsHead(4, 2, (8,)).to(DT)
    obs, act, _ = data(T=8)
    a_hat, f_mean, _ = inverse_dynamics(model, head, obs, act)
    want = ((a_hat - act[:, :-1]) ** 2).mean() + 0.3 * ((f_mean[:, :-1] - obs[:, 1:]) ** 2).mean()
    torch.testing.assert_close(inverse_dynamics_loss(model, head, obs, act, lam=0.3), want)
    with pytest.raises(ValueError, match="lam"):
        inverse_dynamics_loss(model, head, obs, act, lam=-1.0)


# --------------------------------------------------------------------------- bad inputs

def test_bad_inputs_raise_value_error():
    model = make_model()
    obs, act, mask = data()
    with pytest.raises(ValueError, match="actions"):
        model(obs, act[:, :-1], mask)
    with pytest.raises(ValueError, match="mask"):
        model(obs, act, mask[:, :-1])
    with pytest.raises(ValueError, match="obs"):
        model(obs[..., :2], act, mask)
    with pytest.raises(ValueError, match="obs"):
        model(obs[0], act, mask)
    with pytest.raises(ValueError, match="action"):
        MLPControl(2, 4)(torch.zeros(3, 5), torch.zeros(3, 8))
    with pytest.raises(ValueError, match="mean"):
        LinearControl(2, 4)(torch.zeros(3, 2), torch.zeros(3, 7))
    with pytest.raises(ValueError, match="num_basis"):
        LocallyLinearControl(2, 4, num_basis=0)
    with pytest.raises(ValueError, match="scale"):
        DifferenceReadout(2, True, None, torch.tensor([1.0, -1.0]))
    with pytest.raises(ValueError, match="control"):
        AcRKN(ObservationEncoder(3, 4), LocallyLinearTransition(4), MLPControl(2, 5), BeliefDecoder(4, 3))
    with pytest.raises(ValueError, match="next_w"):
        InverseDynamicsHead(4, 2)(torch.zeros(3, 8), torch.zeros(3, 5))
    # issue 13.7 / 13.10: non-finite actions and observations, T = 0
    bad = act.clone()
    bad[0, 3, 1] = float("inf")
    with pytest.raises(ValueError, match="^actions: contains NaN"):
        model(obs, bad, mask)
    bad_obs = obs.clone()
    bad_obs[mask] = float("nan")
    with pytest.raises(ValueError, match="^obs: contains NaN"):
        model(bad_obs, act, mask)
    with pytest.raises(ValueError, match="^obs: need at least one time step"):
        model(obs[:, :0], act[:, :0], mask[:, :0])


# --------------------------------------------------------------------------- norm-bounded transition

def test_norm_bounded_transition_bounds_every_A_and_keeps_small_ones():
    from pgm_wm.acrkn import NormBoundedTransition

    torch.manual_seed(0)
    base = LocallyLinearTransition(4, num_basis=3, bandwidth=1).to(DT)
    with torch.no_grad():
        base.basis_11.add_(0.5 * torch.randn_like(base.basis_11))
    bounded = NormBoundedTransition(base, max_norm=0.95)
    z = 3.0 * torch.randn(50, 8, dtype=DT)
    assert float(torch.linalg.matrix_norm(base.dense_matrix(z).detach(), ord=2).max()) > 1.0  # the base is not
    assert float(torch.linalg.matrix_norm(bounded.dense_matrix(z).detach(), ord=2).max()) <= 0.95 + 1e-10
    # a transition that already satisfies the bound is left unchanged
    loose = NormBoundedTransition(base, max_norm=100.0)
    torch.testing.assert_close(loose.dense_matrix(z), base.dense_matrix(z))
    # its predict step equals the dense algebra with the bounded matrix (diagonal-block case exact)
    base0 = LocallyLinearTransition(3, num_basis=2, bandwidth=0).to(DT)
    b0 = NormBoundedTransition(base0, 0.9)
    from pgm_wm.factorized import FactorizedBelief
    post = FactorizedBelief(torch.randn(5, 6, dtype=DT), torch.rand(5, 3, dtype=DT) + 0.5,
                            torch.rand(5, 3, dtype=DT) + 0.5, 0.1 * torch.rand(5, 3, dtype=DT))
    prior = b0(post)
    A = b0.dense_matrix(post.mean)
    dense = post.to_dense()
    torch.testing.assert_close(prior.mean, (A @ dense.mean[..., None])[..., 0])
    want_cov = A @ dense.cov @ A.transpose(-1, -2) + torch.diag(base0.trans_var.detach())
    torch.testing.assert_close(prior.to_dense().cov, want_cov)
    with pytest.raises(ValueError, match="max_norm"):
        NormBoundedTransition(base, 0.0)


def test_norm_bounded_acrkn_latent_stays_bounded_open_loop():
    from pgm_wm.acrkn import NormBoundedTransition

    model = make_model(num_basis=3, control="zero")
    with torch.no_grad():  # make the base transition expansive
        model.rkn.transition.basis_11.fill_(0.0)
        model.rkn.transition.basis_11.add_(0.3 * torch.eye(4, dtype=DT))
    obs, act, _ = data(T=60)
    mask = torch.zeros(3, 60, dtype=torch.bool)
    mask[:, :5] = True
    grow = model.filter(obs, act, mask).next_prior.mean.norm(dim=-1)
    model.rkn.transition = NormBoundedTransition(model.rkn.transition, 1.0)
    keep = model.filter(obs, act, mask).next_prior.mean.norm(dim=-1)
    assert bool((grow[:, -1] > 100 * grow[:, 5]).all())
    assert bool((keep[:, 4:].diff(dim=-1) <= 1e-9).all())  # non-expansive without inputs (b = 0)

"""The compiled locally linear factorized filter (pgm_wm.locally_linear_jit) against autograd of
the readable reference loop (filter_loop with LocallyLinearTransition.predictor): values and
gradients of every input and parameter, float32 and float64, with and without masks, causes,
the diagonal-only ablation, one basis matrix, and the norm-bounded transition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pgm_wm.acrkn import NormBoundedTransition
from pgm_wm.beliefs import DiagGaussian, FactorizedBelief
from pgm_wm._backends.locally_linear_jit import band_pairs
from pgm_wm.rkn import LocallyLinearTransition, locally_linear_filter

TOL = {torch.float64: dict(rtol=1e-9, atol=1e-10), torch.float32: dict(rtol=2e-3, atol=2e-4)}


def _problem(dtype, B=5, T=7, m=4, K=3, bandwidth=1, masked=True, causes=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    tr = LocallyLinearTransition(m, K, bandwidth).double()
    with torch.no_grad():                                   # random parameters, not the symmetric init
        for p in tr.parameters():
            p.add_(0.3 * r(*p.shape))
    tr = tr.to(dtype)
    prior = FactorizedBelief(r(B, 2 * m), 1 + r(B, m).abs(), 2 + r(B, m).abs(), 0.3 * torch.tanh(r(B, m)))
    obs = DiagGaussian(r(B, T, m), 0.1 + r(B, T, m).abs())
    mask = (torch.rand(B, T, generator=g) < 0.6) if masked else None
    inputs = None
    if causes:
        inputs = FactorizedBelief(r(B, T, 2 * m), 0.1 * r(B, T, m).abs(), 0.2 * r(B, T, m).abs(),
                                  0.01 * r(B, T, m))
    cast = lambda b: None if b is None else b.map(lambda x: x.to(dtype).requires_grad_())  # noqa: E731
    return tr, cast(prior), cast(obs), mask, cast(inputs)


def _run(backend, tr, prior, obs, mask, inputs, diagonal_only=False):
    out = locally_linear_filter(prior, tr, obs, mask, inputs, diagonal_only=diagonal_only, backend=backend)
    beliefs = (out.prior, out.posterior, out.next_prior)
    # a loss that reads every output field with its own weights
    g = torch.Generator().manual_seed(1)
    loss = 0.0
    values = []
    for b in beliefs:
        for x in (b.mean, b.var_upper, b.var_lower, b.cov_side):
            values.append(x)
            loss = loss + (torch.randn(x.shape, generator=g, dtype=torch.float64).to(x.dtype) * x).sum()
    leaves = [p for p in tr.parameters() if p.requires_grad]
    for b in (prior, obs, inputs):
        if b is not None:
            leaves += [getattr(b, f) for f in b._event_dims]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    return values, grads


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("masked,causes,diagonal_only,K", [
    (True, True, False, 3), (False, False, False, 3), (True, False, True, 3), (True, True, False, 1),
    (False, True, True, 1)])
def test_compiled_equals_reference(dtype, masked, causes, diagonal_only, K):
    tr, prior, obs, mask, inputs = _problem(dtype, K=K, masked=masked, causes=causes)
    ref_v, ref_g = _run("reference", tr, prior, obs, mask, inputs, diagonal_only)
    fast_v, fast_g = _run("compiled", tr, prior, obs, mask, inputs, diagonal_only)
    for a, b in zip(ref_v, fast_v):
        torch.testing.assert_close(b, a, **TOL[dtype])
    for a, b in zip(ref_g, fast_g):
        if a is None:
            assert b is None or float(b.abs().max()) == 0.0
        else:
            torch.testing.assert_close(b, a, **TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_norm_bounded_transition(dtype):
    tr, prior, obs, mask, inputs = _problem(dtype, m=3, K=2, bandwidth=2)
    nb = NormBoundedTransition(tr, max_norm=0.9)
    ref_v, ref_g = _run("reference", nb, prior, obs, mask, inputs)
    fast_v, fast_g = _run("compiled", nb, prior, obs, mask, inputs)
    for a, b in zip(ref_v + list(ref_g), fast_v + list(fast_g)):
        torch.testing.assert_close(b, a, **TOL[dtype])


def test_band_pairs_cover_the_band_mask():
    from pgm_wm.rkn import band_mask
    for m, bw in [(1, 0), (5, 0), (5, 2), (4, 7)]:
        bi, bj = band_pairs(m, bw)
        dense = np.zeros((m, m), dtype=bool)
        dense[bi, bj] = True
        assert (dense == band_mask(m, bw).numpy()).all() and len(bi) == dense.sum()


def test_backend_argument_is_checked():
    tr, prior, obs, mask, inputs = _problem(torch.float64)
    with pytest.raises(ValueError, match="backend"):
        locally_linear_filter(prior, tr, obs, mask, inputs, backend="fast!")


@pytest.mark.parametrize("diagonal_only", [False, True])
def test_the_readable_twin_equals_the_compiled_loop(diagonal_only):
    """packed_reference (tensor operations on the kernel's own packed arguments) equals the
    compiled forward pass to rounding (float64)."""
    from pgm_wm._backends.locally_linear_jit import locally_linear_filter_jit, packed_reference

    g = torch.Generator().manual_seed(3)
    T, m, N, K, bw = 6, 3, 4, 2, 1
    bi, bj = band_pairs(m, bw)
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    x0 = torch.cat([r(2 * m, N), 1 + r(m, N).abs(), 0.1 * r(m, N), 2 + r(m, N).abs()])
    args = (x0, r(T, m, N), 0.2 + r(T, m, N).abs(), (torch.rand(T, N, generator=g) < 0.6).double(),
            torch.cat([r(T, 2 * m, N), 0.1 * r(T, m, N).abs(), torch.zeros(T, m, N, dtype=torch.float64),
                       0.1 * r(T, m, N).abs()], 1),
            0.3 * r(4, K, len(bi)), r(K, 2 * m), r(K), torch.as_tensor(bi == bj, dtype=torch.float64))
    X1, P1 = locally_linear_filter_jit(*args, bi, bj, diagonal_only)
    X2, P2 = packed_reference(*args, bi, bj, diagonal_only)
    torch.testing.assert_close(X1, X2, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(P1, P2, rtol=1e-12, atol=1e-12)


def test_second_derivatives_through_the_compiled_loop_equal_the_reference():
    """A gradient penalty (create_graph=True): its gradient with respect to every parameter is
    the same through the compiled loop (whose backward recomputes by the readable twin) and
    through the book's loop."""
    tr, prior, obs, mask, inputs = _problem(torch.float64, K=3)
    params = [p for p in tr.parameters() if p.requires_grad]

    def penalty(backend):
        out = locally_linear_filter(prior, tr, obs, mask, inputs, backend=backend)
        loss = out.next_prior.mean.square().sum() + out.next_prior.var_upper.log().sum()
        grads = torch.autograd.grad(loss, params + [obs.mean], create_graph=True)
        return torch.autograd.grad(sum(gr.square().sum() for gr in grads), params)

    for a, b in zip(penalty("compiled"), penalty("reference")):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


def test_the_table_routes_the_locally_linear_filter():
    from pgm_wm._backends import Call, choose, use_compiled

    op = "locally_linear_factorized_filter"
    assert choose(op, Call(needs_grad=True)) == "compiled"
    assert choose(op, Call(device="cuda")) == "reference"
    assert choose(op, Call(transformed=True)) == "reference"
    with use_compiled(False):
        assert choose(op, Call()) == "reference"
        with pytest.raises(ValueError, match="backend"):
            choose(op, Call(), "compiled")
    with pytest.raises(ValueError, match="backend"):
        choose(op, Call(), "tensor")

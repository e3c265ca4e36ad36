r"""Compiled loop of :func:`pgm_wm.factorized.diagonal_factorized_filter` with its hand-written
backward pass (Chapter 6: the MTS3 fast level, trained through this loop).

With diagonal blocks every latent dimension ("lane") :math:`i` of every sequence is its own
two-state filter, so the compiled loop (:mod:`pgm_wm._backends.compiler`) runs the update (Eq. rkn-update,
product form) and the predict (Eq. rkn-predict) lane by lane; per lane and step, with the prior
:math:`(z^u, z^l, \sigma^u, \sigma^s, \sigma^l)`, the observation :math:`(w, r)` and the mask
:math:`\mu\in\{0, 1\}`:

.. math:: \begin{aligned}
          g &= \mu/(\sigma^u + r),\quad e = w - z^u,\quad \rho = 1 - \mu + rg,\\
          z^{u+} &= z^u + \sigma^u g e,\quad z^{l+} = z^l + \sigma^s g e,\quad
          \sigma^{u+} = \sigma^u\rho,\quad \sigma^{s+} = \sigma^s\rho,\quad
          \sigma^{l+} = \sigma^l - (\sigma^s)^2 g,\\
          z' &= A_{\text{lane}}\,z^+ + b,\qquad s' = C_{\text{lane}}^\top s^+ + q
          \end{aligned}

(:math:`A_{\text{lane}}` the lane's 2×2 transition, :math:`C_{\text{lane}}` the 3×3 map of
Eq. rkn-predict on :math:`(\sigma^u, \sigma^s, \sigma^l)`). The backward pass is reverse-mode
differentiation of the same loop (adjoints :math:`\bar x = \partial\ell/\partial x`), from the
last step to the first:

.. math:: \begin{aligned}
          \bar e &= g(\bar z^{u+}\sigma^u + \bar z^{l+}\sigma^s),\quad
          \bar\rho = \bar\sigma^{u+}\sigma^u + \bar\sigma^{s+}\sigma^s,\quad
          \bar g = e(\bar z^{u+}\sigma^u + \bar z^{l+}\sigma^s) + r\bar\rho - (\sigma^s)^2\bar\sigma^{l+},\\
          \bar d &= -\bar g\,g/(\sigma^u + r),\quad \bar w = \bar e,\quad \bar r = g\bar\rho + \bar d,\quad
          \bar z^u = \bar z^{u+} - \bar e,\quad \bar z^l = \bar z^{l+},\\
          \bar\sigma^u &= ge\,\bar z^{u+} + \rho\,\bar\sigma^{u+} + \bar d,\quad
          \bar\sigma^s = ge\,\bar z^{l+} + \rho\,\bar\sigma^{s+} - 2\sigma^sg\,\bar\sigma^{l+},\quad
          \bar\sigma^l = \bar\sigma^{l+},
          \end{aligned}

and the transition's gradients are one matrix product each after the loop:
:math:`\bar A = \sum_{t}\bar z'^{\top}_t z^+_t`, :math:`\bar C = \sum_t s^{+\top}_t\bar s'_t`.
Values and gradients are tested equal to the reference loop (autograd through
:func:`pgm_wm.factorized.factorized_filter`) in float32 and float64.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .compiler import as_array, kernel
from .factorized_fast import diagonal_steps


@kernel
def _forward(z0, s0, w, r, mu, has_mask, in_z, a, c, in_s, Z, S, Zp, Sp, z_last, s_last):
    """Forward loop, batch first: ``w, r, mu: (N, T, m)``, ``in_z: (N, T, 2m)``,
    ``in_s: (N, T, 3m)``, ``a: (4, m)`` = lane diagonals of :math:`A_{11}, A_{12}, A_{21}, A_{22}`,
    ``c: (3, 3, m)`` with ``c[k, l]`` the coefficient of :math:`s^+_k` in :math:`s'_l`. Writes
    the priors ``Z, S``, posteriors ``Zp, Sp`` (``(N, T, 2m)``, ``(N, T, 3m)``) and the last
    prediction ``z_last, s_last``. The loop over lanes is innermost (vector instructions)."""
    N, T, m = w.shape
    zu, zl = np.empty(m), np.empty(m)
    su, ss, sl = np.empty(m), np.empty(m), np.empty(m)
    for b in range(N):
        for i in range(m):
            zu[i], zl[i] = z0[b, i], z0[b, m + i]
            su[i], ss[i], sl[i] = s0[b, i], s0[b, m + i], s0[b, 2 * m + i]
        for t in range(T):
            for i in range(m):
                Z[b, t, i], Z[b, t, m + i] = zu[i], zl[i]
                S[b, t, i], S[b, t, m + i], S[b, t, 2 * m + i] = su[i], ss[i], sl[i]
                mt = mu[b, t, i] if has_mask else 1.0
                rt = r[b, t, i]
                g = mt / (su[i] + rt)
                ge = g * (w[b, t, i] - zu[i])
                rho = (1.0 - mt) + rt * g
                pu, pl = zu[i] + su[i] * ge, zl[i] + ss[i] * ge
                qu, qs, ql = su[i] * rho, ss[i] * rho, sl[i] - ss[i] * ss[i] * g
                Zp[b, t, i], Zp[b, t, m + i] = pu, pl
                Sp[b, t, i], Sp[b, t, m + i], Sp[b, t, 2 * m + i] = qu, qs, ql
                zu[i] = a[0, i] * pu + a[1, i] * pl + in_z[b, t, i]
                zl[i] = a[2, i] * pu + a[3, i] * pl + in_z[b, t, m + i]
                su[i] = c[0, 0, i] * qu + c[1, 0, i] * qs + c[2, 0, i] * ql + in_s[b, t, i]
                ss[i] = c[0, 1, i] * qu + c[1, 1, i] * qs + c[2, 1, i] * ql + in_s[b, t, m + i]
                sl[i] = c[0, 2, i] * qu + c[1, 2, i] * qs + c[2, 2, i] * ql + in_s[b, t, 2 * m + i]
        for i in range(m):
            z_last[b, i], z_last[b, m + i] = zu[i], zl[i]
            s_last[b, i], s_last[b, m + i], s_last[b, 2 * m + i] = su[i], ss[i], sl[i]


@kernel
def _backward(Z, S, w, r, mu, has_mask, a, c, dZ, dS, dZp, dSp, dz_last, ds_last,
              g_w, g_r, g_in_z, g_in_s, g_z0, g_s0):
    """Backward loop (module docstring): from the saved priors ``Z, S`` and the gradients of the
    six outputs, the gradients of ``w, r``, the input means ``in_z`` and variances ``in_s`` (the
    adjoints of the predictions) and of the first prior ``z0, s0``."""
    N, T, m = w.shape
    lu, ll = np.empty(m), np.empty(m)                       # adjoint of z'
    ku, ks, kl = np.empty(m), np.empty(m), np.empty(m)      # adjoint of s'
    for b in range(N):
        for i in range(m):
            lu[i], ll[i] = dz_last[b, i], dz_last[b, m + i]
            ku[i], ks[i], kl[i] = ds_last[b, i], ds_last[b, m + i], ds_last[b, 2 * m + i]
        for t in range(T - 1, -1, -1):
            for i in range(m):
                g_in_z[b, t, i], g_in_z[b, t, m + i] = lu[i], ll[i]
                g_in_s[b, t, i], g_in_s[b, t, m + i], g_in_s[b, t, 2 * m + i] = ku[i], ks[i], kl[i]
                # predict backward: adjoints of the posterior
                bpu = a[0, i] * lu[i] + a[2, i] * ll[i] + dZp[b, t, i]
                bpl = a[1, i] * lu[i] + a[3, i] * ll[i] + dZp[b, t, m + i]
                bqu = c[0, 0, i] * ku[i] + c[0, 1, i] * ks[i] + c[0, 2, i] * kl[i] + dSp[b, t, i]
                bqs = c[1, 0, i] * ku[i] + c[1, 1, i] * ks[i] + c[1, 2, i] * kl[i] + dSp[b, t, m + i]
                bql = c[2, 0, i] * ku[i] + c[2, 1, i] * ks[i] + c[2, 2, i] * kl[i] + dSp[b, t, 2 * m + i]
                # update backward, from the saved prior
                zu, su, ss = Z[b, t, i], S[b, t, i], S[b, t, m + i]
                mt = mu[b, t, i] if has_mask else 1.0
                rt = r[b, t, i]
                d = su + rt
                g = mt / d
                e = w[b, t, i] - zu
                rho = (1.0 - mt) + rt * g
                sz = bpu * su + bpl * ss
                be = g * sz
                brho = bqu * su + bqs * ss
                bg = e * sz + rt * brho - ss * ss * bql
                bd = -bg * g / d
                g_w[b, t, i] = be
                g_r[b, t, i] = g * brho + bd
                lu[i] = bpu - be + dZ[b, t, i]
                ll[i] = bpl + dZ[b, t, m + i]
                ku[i] = g * e * bpu + rho * bqu + bd + dS[b, t, i]
                ks[i] = g * e * bpl + rho * bqs - 2.0 * ss * g * bql + dS[b, t, m + i]
                kl[i] = bql + dS[b, t, 2 * m + i]
        for i in range(m):
            g_z0[b, i], g_z0[b, m + i] = lu[i], ll[i]
            g_s0[b, i], g_s0[b, m + i], g_s0[b, 2 * m + i] = ku[i], ks[i], kl[i]


class _DiagonalFilter(torch.autograd.Function):
    """Autograd wrapper: forward by :func:`_forward`, backward by :func:`_backward` plus one
    matrix product for the gradient of ``A`` and one sum for that of ``coef``.

    A backward pass that must itself be differentiable (``create_graph=True``, e.g. a gradient
    penalty: autograd then runs the backward with gradient mode on) is not what the compiled
    loop computes: it is then recomputed from the saved inputs by the tensor path
    (:func:`pgm_wm._backends.factorized_fast.diagonal_steps`) and differentiated by autograd,
    so second derivatives are those of the tensor path (tested)."""

    @staticmethod
    def forward(ctx, z0, s0, w, r, mu, in_z, in_s, A, coef):  # noqa: D102
        N, T, m = w.shape
        a = torch.stack([torch.diagonal(A[:m, :m]), torch.diagonal(A[:m, m:]),
                         torch.diagonal(A[m:, :m]), torch.diagonal(A[m:, m:])])
        opts = dict(dtype=w.dtype, device=w.device)
        Z, Zp = torch.empty(N, T, 2 * m, **opts), torch.empty(N, T, 2 * m, **opts)
        S, Sp = torch.empty(N, T, 3 * m, **opts), torch.empty(N, T, 3 * m, **opts)
        z_last, s_last = torch.empty(N, 2 * m, **opts), torch.empty(N, 3 * m, **opts)
        has_mask = mu is not None
        mu_arr = arr(mu) if has_mask else arr(w[:1, :1])
        _forward(arr(z0), arr(s0), arr(w), arr(r), mu_arr, has_mask, arr(in_z), arr(a), arr(coef), arr(in_s),
                 Z.numpy(), S.numpy(), Zp.numpy(), Sp.numpy(), z_last.numpy(), s_last.numpy())
        ctx.save_for_backward(Z, S, Zp, Sp, a, z0, s0, w, r, mu, in_z, in_s, A, coef)
        return Z, S, Zp, Sp, z_last, s_last

    @staticmethod
    def backward(ctx, dZ, dS, dZp, dSp, dz_last, ds_last):  # noqa: D102
        Z, S, Zp, Sp, a, *inputs = ctx.saved_tensors
        if torch.is_grad_enabled():          # create_graph=True: differentiate the tensor path instead
            return _differentiable_backward(ctx, inputs, (dZ, dS, dZp, dSp, dz_last, ds_last))
        z0, s0, w, r, mu, in_z, in_s, A, coef = inputs
        N, T, m = w.shape
        grad = lambda x, like: arr(torch.zeros_like(like) if x is None else x)  # noqa: E731
        g_w, g_r = torch.empty_like(w), torch.empty_like(r)
        g_in_z, g_in_s = torch.empty_like(Z), torch.empty_like(S)
        g_z0, g_s0 = torch.empty(N, 2 * m, dtype=w.dtype), torch.empty(N, 3 * m, dtype=w.dtype)
        has_mask = mu is not None
        _backward(arr(Z), arr(S), arr(w), arr(r), arr(mu) if has_mask else arr(w[:1, :1]), has_mask, arr(a),
                  arr(coef), grad(dZ, Z), grad(dS, S), grad(dZp, Zp), grad(dSp, Sp), grad(dz_last, g_z0),
                  grad(ds_last, g_s0), g_w.numpy(), g_r.numpy(), g_in_z.numpy(), g_in_s.numpy(), g_z0.numpy(),
                  g_s0.numpy())
        # z' = z⁺ Aᵀ + in_z (as the tensor-operation path computes it: every entry of A gets
        # its gradient) and s'_l = Σ_k coef[k, l] s⁺_k + in_s per lane
        g_A = g_in_z.reshape(N * T, 2 * m).T @ Zp.reshape(N * T, 2 * m) if ctx.needs_input_grad[7] else None
        g_coef = torch.einsum("nkm,nlm->klm", Sp.reshape(N * T, 3, m), g_in_s.reshape(N * T, 3, m)) \
            if ctx.needs_input_grad[8] else None
        return g_z0, g_s0, g_w, g_r, None, g_in_z, g_in_s, g_A, g_coef


def _differentiable_backward(ctx, inputs: list, grad_outputs: tuple) -> tuple:
    """The gradients of the inputs as a differentiable function of the inputs and of
    ``grad_outputs``: autograd through the tensor path (the class docstring)."""
    wanted = [i for i, x in enumerate(inputs) if x is not None and ctx.needs_input_grad[i]]
    # a node of its own per input: the partial derivatives, not total ones (coef is computed
    # from A before the call, and the gradient of A must not pass through coef twice)
    xs = [x.view_as(x) if i in wanted else x for i, x in enumerate(inputs)]
    outs = diagonal_steps(*xs)
    pairs = [(o, g) for o, g in zip(outs, grad_outputs) if g is not None and o.requires_grad]
    grads = torch.autograd.grad([o for o, _ in pairs], [xs[i] for i in wanted], [g for _, g in pairs],
                                create_graph=True, allow_unused=True) if pairs and wanted else ()
    out: list = [None] * len(inputs)
    for i, g in zip(wanted, grads):
        out[i] = torch.zeros_like(inputs[i]) if g is None else g
    return tuple(out)


def arr(x: Tensor) -> np.ndarray:
    """A C-contiguous NumPy array of a CPU tensor (no copy where it is contiguous)."""
    return np.ascontiguousarray(as_array(x))


def diagonal_filter_jit(z0: Tensor, s0: Tensor, w: Tensor, r: Tensor, mu: Tensor | None, in_z: Tensor,
                        in_s: Tensor, A: Tensor, coef: Tensor) -> tuple[Tensor, ...]:
    """The diagonal factorized filter on packed, batch-flattened states (see
    :func:`pgm_wm.factorized.diagonal_factorized_filter`): ``z0: (N, 2m)``, ``s0: (N, 3m)``,
    ``w, r: (N, T, m)``, ``mu: (N, T, m)`` 0/1 or ``None``, ``in_z: (N, T, 2m)``,
    ``in_s: (N, T, 3m)`` (input variances plus the transition noise), ``A: (2m, 2m)`` with
    diagonal blocks, ``coef: (3, 3, m)`` the predict map of the variances per lane
    (``coef[k, l]``: coefficient of :math:`s^+_k` in :math:`s'_l`). Returns
    ``(Z, S, Zp, Sp, z_last, s_last)``: priors, posteriors and the last prediction,
    differentiable in every input but ``mu`` (to any order: see :class:`_DiagonalFilter`).
    Not under ``torch.func`` transforms (the backend table sends those calls to the tensor
    path; called directly, it raises ``ValueError``)."""
    active = getattr(torch._C, "_are_functorch_transforms_active", None)
    if active is not None and active():
        raise ValueError("backend: the compiled diagonal factorized filter cannot run under torch.func "
                         "transforms (vmap, grad, jacrev, ...); use backend='tensor'")
    return _DiagonalFilter.apply(z0, s0, w, r, mu, in_z, in_s, A, coef)

r"""Compiled loop of the RKN's locally linear factorized filter with its hand-written backward
pass (Chapters 3–5: the RKN, the ac-RKN and the HiP-RSSM train through this loop).

The readable reference is the book's loop (:func:`pgm_wm.filtering.filter_loop`) with the
update of Eq. (rkn-update) and the predict of Eq. (rkn-predict) with the locally linear
transition of Eq. (rkn-transition). Run as tensor operations it launches about fifty small
operations per time step, forward and again backward, and a training step of the ac-RKN spends
most of its time on those launches. Here one step of all sequences is a few compiled loops.

**Band storage.** Every block :math:`A_{xy}` (:math:`xy \in \{11, 12, 21, 22\}`) of a basis matrix
is a band matrix of half-width :math:`b`; the four blocks share one pattern, the ``nb`` pairs
:math:`(i_p, j_p)` with :math:`|i_p - j_p| \le b`. A basis is stored as ``(4, K, nb)`` values,
the mixed transition of a sequence as ``(4, nb)`` values. With :math:`\alpha = \mathrm{softmax}(W
z^+ + c)` (Eq. rkn-transition) and :math:`\iota_p = 1` on the diagonal when the identity is added,

.. math:: A_{xy,p} = \iota_p [xy \in \{11, 22\}] + \sum_k \alpha_k B_{xy,k,p}.

**Predict by band entries.** Row :math:`i` of the mean and the three variance vectors of
Eq. (rkn-predict) are sums over the band entries :math:`p` with :math:`i_p = i` (column
:math:`j = j_p`), with the posterior :math:`(z^{u+}, z^{l+}, \sigma^{u+}, \sigma^{s+}, \sigma^{l+})`:

.. math:: \begin{aligned}
          z^{u-}_i &= \textstyle\sum_p A_{11,p} z^{u+}_j + A_{12,p} z^{l+}_j, \qquad
          z^{l-}_i = \textstyle\sum_p A_{21,p} z^{u+}_j + A_{22,p} z^{l+}_j,\\
          \sigma^{u-}_i &= \textstyle\sum_p A_{11,p}^2\sigma^{u+}_j + 2A_{11,p}A_{12,p}\sigma^{s+}_j
                           + A_{12,p}^2\sigma^{l+}_j + q^u_i,\\
          \sigma^{l-}_i &= \textstyle\sum_p A_{21,p}^2\sigma^{u+}_j + 2A_{21,p}A_{22,p}\sigma^{s+}_j
                           + A_{22,p}^2\sigma^{l+}_j + q^l_i,\\
          \sigma^{s-}_i &= \textstyle\sum_p A_{21,p}A_{11,p}\sigma^{u+}_j
                           + (A_{22,p}A_{11,p} + A_{21,p}A_{12,p})\sigma^{s+}_j + A_{22,p}A_{12,p}\sigma^{l+}_j,
          \end{aligned}

plus the known causes of the step (``in_z``, ``in_s``: an action term, a task cause); the
transition noise :math:`q` is folded into ``in_s`` by the caller. ``diag_only`` zeroes
:math:`\sigma^{s-}` after every predict (Chapter 3's diagonal ablation).

**Backward pass** (adjoints :math:`\bar x = \partial\ell/\partial x`, from the last step to the
first). With :math:`\bar z^{\pm}, \bar\sigma^{\pm}` the adjoints of the step's prediction (the
carry from the later steps plus the gradients of the outputs), per band entry

.. math:: \begin{aligned}
          \bar A_{11} &= 2\bar\sigma^{u-}_i(A_{11}\sigma^{u+}_j + A_{12}\sigma^{s+}_j)
                         + \bar\sigma^{s-}_i(A_{21}\sigma^{u+}_j + A_{22}\sigma^{s+}_j) + \bar z^{u-}_i z^{u+}_j,\\
          \bar A_{12} &= 2\bar\sigma^{u-}_i(A_{11}\sigma^{s+}_j + A_{12}\sigma^{l+}_j)
                         + \bar\sigma^{s-}_i(A_{21}\sigma^{s+}_j + A_{22}\sigma^{l+}_j) + \bar z^{u-}_i z^{l+}_j,
          \end{aligned}

(:math:`\bar A_{21}, \bar A_{22}` likewise with :math:`\bar\sigma^{l-}` and :math:`\bar z^{l-}`); the
posterior's adjoints collect the transposed products (e.g. :math:`\bar z^{u+}_j \mathrel{+}=
A_{11}\bar z^{u-}_i + A_{21}\bar z^{l-}_i`); the mixture gives :math:`\bar\alpha_k = \sum_{xy,p}
\bar A_{xy,p} B_{xy,k,p}` and :math:`\bar B_{xy,k,p} \mathrel{+}= \alpha_k \bar A_{xy,p}`; the softmax
:math:`\bar\ell_k = \alpha_k(\bar\alpha_k - \sum_{k'}\alpha_{k'}\bar\alpha_{k'})`, then
:math:`\bar W \mathrel{+}= \bar\ell\, z^{+\top}`, :math:`\bar c \mathrel{+}= \bar\ell` and
:math:`\bar z^+ \mathrel{+}= W^\top\bar\ell`. The update's adjoints are those of
:mod:`pgm_wm.factorized_jit` (the same product form of Eq. rkn-update).

Arrays are batch-last (``(..., N)``): the loops over the sequences are innermost and run as
vector instructions. Values and gradients are tested equal to autograd of the reference loop
in float32 and float64 (``tests/test_locally_linear_jit.py``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ._jit import as_array, jit

__all__ = ["band_pairs", "locally_linear_filter_jit"]


def band_pairs(m: int, bandwidth: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``nb`` index pairs ``(i_p, j_p)`` of an ``m x m`` band of half-width ``bandwidth``,
    row by row: two int64 arrays."""
    rows, cols = [], []
    for i in range(m):
        for j in range(max(0, i - bandwidth), min(m, i + bandwidth + 1)):
            rows.append(i)
            cols.append(j)
    return np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)


@jit
def _forward(z0, s0, w, r, mu, has_mask, in_z, in_s, basis, ident, bi, bj, Wc, bc, has_coef, diag_only,
             Z, S, Zp, Sp, z_last, s_last, alpha, Aval):
    """Forward loop, batch last: ``z0: (2m, N)``, ``s0: (3m, N)`` = ``[σ^u, σ^s, σ^l]``,
    ``w, r: (T, m, N)``, ``mu: (T, N)`` 1/0, ``in_z: (T, 2m, N)``, ``in_s: (T, 3m, N)``,
    ``basis: (4, K, nb)``, ``ident: (nb,)``, ``Wc: (K, 2m)``, ``bc: (K,)``. Writes the priors
    ``Z, S``, posteriors ``Zp, Sp``, the last prediction and, for the backward pass, the mixing
    weights ``alpha: (T, K, N)`` and the mixed band values ``Aval: (T, 4, nb, N)``."""
    T, m, N = w.shape
    K, nb = basis.shape[1], bi.shape[0]
    z, s = z0.copy(), s0.copy()
    zp, sp = np.empty_like(z), np.empty_like(s)
    logit = np.empty((K, N), dtype=z.dtype)
    for t in range(T):
        Z[t] = z
        S[t] = s
        # update, Eq. (rkn-update) in product form
        for i in range(m):
            for n in range(N):
                mt = mu[t, n] if has_mask else 1.0
                rt = r[t, i, n]
                su, ss, sl = s[i, n], s[m + i, n], s[2 * m + i, n]
                g = mt / (su + rt)
                ge = g * (w[t, i, n] - z[i, n])
                rho = (1.0 - mt) + rt * g
                zp[i, n] = z[i, n] + su * ge
                zp[m + i, n] = z[m + i, n] + ss * ge
                sp[i, n] = su * rho
                sp[m + i, n] = ss * rho
                sp[2 * m + i, n] = sl - ss * ss * g
        Zp[t] = zp
        Sp[t] = sp
        # mixing weights α = softmax(W z⁺ + c)
        if has_coef:
            for k in range(K):
                for n in range(N):
                    logit[k, n] = bc[k]
                for c in range(2 * m):
                    wkc = Wc[k, c]
                    for n in range(N):
                        logit[k, n] += wkc * zp[c, n]
            for n in range(N):
                mx = logit[0, n]
                for k in range(1, K):
                    mx = max(mx, logit[k, n])
                tot = 0.0
                for k in range(K):
                    e = np.exp(logit[k, n] - mx)
                    logit[k, n] = e
                    tot += e
                for k in range(K):
                    alpha[t, k, n] = logit[k, n] / tot
        else:
            for k in range(K):
                for n in range(N):
                    alpha[t, k, n] = 1.0
        # A_t = ι + Σ_k α_k B_k on the band entries
        for x in range(4):
            on_diag = x == 0 or x == 3
            for p in range(nb):
                base = ident[p] if on_diag else 0.0
                for n in range(N):
                    Aval[t, x, p, n] = base
                for k in range(K):
                    bkp = basis[x, k, p]
                    for n in range(N):
                        Aval[t, x, p, n] += alpha[t, k, n] * bkp
        # predict, Eq. (rkn-predict), plus the known causes
        z[:] = in_z[t]
        s[:] = in_s[t]
        for p in range(nb):
            i, j = bi[p], bj[p]
            for n in range(N):
                a11, a12, a21, a22 = Aval[t, 0, p, n], Aval[t, 1, p, n], Aval[t, 2, p, n], Aval[t, 3, p, n]
                pu, pl = zp[j, n], zp[m + j, n]
                qu, qs, ql = sp[j, n], sp[m + j, n], sp[2 * m + j, n]
                z[i, n] += a11 * pu + a12 * pl
                z[m + i, n] += a21 * pu + a22 * pl
                s[i, n] += a11 * a11 * qu + 2.0 * a11 * a12 * qs + a12 * a12 * ql
                s[m + i, n] += a21 * a11 * qu + (a22 * a11 + a21 * a12) * qs + a22 * a12 * ql
                s[2 * m + i, n] += a21 * a21 * qu + 2.0 * a21 * a22 * qs + a22 * a22 * ql
        if diag_only:
            s[m:2 * m] = 0.0
    z_last[:] = z
    s_last[:] = s


@jit
def _backward(Z, S, Zp, Sp, w, r, mu, has_mask, basis, bi, bj, Wc, has_coef, diag_only, alpha, Aval,
              dZ, dS, dZp, dSp, dz_last, ds_last,
              g_w, g_r, g_in_z, g_in_s, g_z0, g_s0, g_A, g_logit):
    """Backward loop (module docstring): from the saved beliefs, ``alpha`` and ``Aval`` and the
    gradients of the six outputs, the gradients of the inputs (batch last as in
    :func:`_forward`) and, per step and sequence, the adjoints of the mixed band values
    ``g_A: (T, 4, nb, N)`` and of the logits ``g_logit: (T, K, N)``. The parameter gradients are
    sums of their products over steps and sequences, one matrix product each after the loop
    (reductions inside the loop would not run as vector instructions)."""
    T, m, N = w.shape
    K, nb = basis.shape[1], bi.shape[0]
    lz, ls = dz_last.copy(), ds_last.copy()              # adjoints of the prediction of step t
    bz, bs = np.empty_like(lz), np.empty_like(ls)        # adjoints of the posterior of step t
    if diag_only:
        ls[m:2 * m] = 0.0
    for t in range(T - 1, -1, -1):
        g_in_z[t] = lz
        g_in_s[t] = ls
        bz[:] = dZp[t]
        bs[:] = dSp[t]
        dA = g_A[t]
        dal = g_logit[t]
        # predict backward
        for p in range(nb):
            i, j = bi[p], bj[p]
            for n in range(N):
                a11, a12, a21, a22 = Aval[t, 0, p, n], Aval[t, 1, p, n], Aval[t, 2, p, n], Aval[t, 3, p, n]
                pu, pl = Zp[t, j, n], Zp[t, m + j, n]
                qu, qs, ql = Sp[t, j, n], Sp[t, m + j, n], Sp[t, 2 * m + j, n]
                lu, ll = lz[i, n], lz[m + i, n]
                ku, ks, kl = ls[i, n], ls[m + i, n], ls[2 * m + i, n]
                u1, u2 = a11 * qu + a12 * qs, a11 * qs + a12 * ql
                v1, v2 = a21 * qu + a22 * qs, a21 * qs + a22 * ql
                dA[0, p, n] = 2.0 * ku * u1 + ks * v1 + lu * pu
                dA[1, p, n] = 2.0 * ku * u2 + ks * v2 + lu * pl
                dA[2, p, n] = 2.0 * kl * v1 + ks * u1 + ll * pu
                dA[3, p, n] = 2.0 * kl * v2 + ks * u2 + ll * pl
                bz[j, n] += a11 * lu + a21 * ll
                bz[m + j, n] += a12 * lu + a22 * ll
                bs[j, n] += a11 * a11 * ku + a21 * a11 * ks + a21 * a21 * kl
                bs[m + j, n] += 2.0 * a11 * a12 * ku + (a22 * a11 + a21 * a12) * ks + 2.0 * a21 * a22 * kl
                bs[2 * m + j, n] += a12 * a12 * ku + a22 * a12 * ks + a22 * a22 * kl
        # mixture backward: ᾱ_k = Σ_{xy,p} Ā_{xy,p} B_{xy,k,p}
        if has_coef:
            dal[:] = 0.0
            for x in range(4):
                for p in range(nb):
                    for k in range(K):
                        bkp = basis[x, k, p]
                        for n in range(N):
                            dal[k, n] += dA[x, p, n] * bkp
            # softmax backward: dal becomes the adjoint of the logits; then z̄⁺ += Wᵀ ℓ̄
            dot = np.zeros(N, dtype=lz.dtype)
            for k in range(K):
                for n in range(N):
                    dot[n] += alpha[t, k, n] * dal[k, n]
            for k in range(K):
                for n in range(N):
                    dal[k, n] = alpha[t, k, n] * (dal[k, n] - dot[n])
                for c in range(2 * m):
                    wkc = Wc[k, c]
                    for n in range(N):
                        bz[c, n] += wkc * dal[k, n]
        # update backward, from the saved prior (as in factorized_jit)
        for i in range(m):
            for n in range(N):
                zu, su, ss = Z[t, i, n], S[t, i, n], S[t, m + i, n]
                mt = mu[t, n] if has_mask else 1.0
                rt = r[t, i, n]
                d = su + rt
                g = mt / d
                e = w[t, i, n] - zu
                rho = (1.0 - mt) + rt * g
                bpu, bpl = bz[i, n], bz[m + i, n]
                bqu, bqs, bql = bs[i, n], bs[m + i, n], bs[2 * m + i, n]
                sz = bpu * su + bpl * ss
                be = g * sz
                brho = bqu * su + bqs * ss
                bg = e * sz + rt * brho - ss * ss * bql
                bd = -bg * g / d
                g_w[t, i, n] = be
                g_r[t, i, n] = g * brho + bd
                lz[i, n] = bpu - be + dZ[t, i, n]
                lz[m + i, n] = bpl + dZ[t, m + i, n]
                ls[i, n] = g * e * bpu + rho * bqu + bd + dS[t, i, n]
                ls[m + i, n] = g * e * bpl + rho * bqs - 2.0 * ss * g * bql + dS[t, m + i, n]
                ls[2 * m + i, n] = bql + dS[t, 2 * m + i, n]
        if diag_only:
            ls[m:2 * m] = 0.0     # the prior's side covariance is a constant zero
    g_z0[:] = lz
    g_s0[:] = ls


def _arr(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(as_array(x))


class _LocallyLinearFilter(torch.autograd.Function):
    """Autograd wrapper of :func:`_forward` / :func:`_backward` (batch-last tensors)."""

    @staticmethod
    def forward(ctx, z0, s0, w, r, mu, in_z, in_s, basis, Wc, bc, ident, bi, bj, diag_only):  # noqa: D102
        T, m, N = w.shape
        K = basis.shape[1]
        opts = dict(dtype=w.dtype, device=w.device)
        Z, Zp = torch.empty(T, 2 * m, N, **opts), torch.empty(T, 2 * m, N, **opts)
        S, Sp = torch.empty(T, 3 * m, N, **opts), torch.empty(T, 3 * m, N, **opts)
        z_last, s_last = torch.empty(2 * m, N, **opts), torch.empty(3 * m, N, **opts)
        alpha = torch.empty(T, K, N, **opts)
        Aval = torch.empty(T, 4, bi.shape[0], N, **opts)
        has_mask, has_coef = mu is not None, Wc is not None
        dummy = np.zeros((1, 1), dtype=_arr(w).dtype)
        _forward(_arr(z0), _arr(s0), _arr(w), _arr(r), _arr(mu) if has_mask else dummy, has_mask, _arr(in_z),
                 _arr(in_s), _arr(basis), _arr(ident), bi, bj, _arr(Wc) if has_coef else dummy,
                 _arr(bc) if has_coef else dummy[0], has_coef, diag_only,
                 Z.numpy(), S.numpy(), Zp.numpy(), Sp.numpy(), z_last.numpy(), s_last.numpy(), alpha.numpy(),
                 Aval.numpy())
        ctx.save_for_backward(Z, S, Zp, Sp, w, r, mu, basis, Wc, alpha, Aval)
        ctx.bi, ctx.bj, ctx.diag_only = bi, bj, diag_only
        return Z, S, Zp, Sp, z_last, s_last

    @staticmethod
    def backward(ctx, dZ, dS, dZp, dSp, dz_last, ds_last):  # noqa: D102
        Z, S, Zp, Sp, w, r, mu, basis, Wc, alpha, Aval = ctx.saved_tensors
        T, m, N = w.shape
        grad = lambda x, like: _arr(torch.zeros_like(like) if x is None else x)  # noqa: E731
        g_w, g_r = torch.empty_like(w), torch.empty_like(r)
        g_in_z, g_in_s = torch.empty_like(Z), torch.empty_like(S)
        g_z0, g_s0 = torch.empty(2 * m, N, dtype=w.dtype), torch.empty(3 * m, N, dtype=w.dtype)
        has_mask, has_coef = mu is not None, Wc is not None
        dummy = np.zeros((1, 1), dtype=_arr(w).dtype)
        g_A, g_logit = torch.empty_like(Aval), torch.zeros_like(alpha)
        _backward(_arr(Z), _arr(S), _arr(Zp), _arr(Sp), _arr(w), _arr(r), _arr(mu) if has_mask else dummy, has_mask,
                  _arr(basis), ctx.bi, ctx.bj, _arr(Wc) if has_coef else dummy, has_coef, ctx.diag_only, _arr(alpha),
                  _arr(Aval), grad(dZ, Z), grad(dS, S), grad(dZp, Zp), grad(dSp, Sp), grad(dz_last, g_z0),
                  grad(ds_last, g_s0), g_w.numpy(), g_r.numpy(), g_in_z.numpy(), g_in_s.numpy(), g_z0.numpy(),
                  g_s0.numpy(), g_A.numpy(), g_logit.numpy())
        # B̄_{xy,k,p} = Σ_{t,n} α_{t,k,n} Ā_{t,xy,p,n};  W̄ = Σ_{t,n} ℓ̄ z⁺ᵀ;  c̄ = Σ_{t,n} ℓ̄
        K = alpha.shape[1]
        nb4 = g_A.shape[1] * g_A.shape[2]
        g_basis = (torch.bmm(alpha, g_A.reshape(T, nb4, N).transpose(1, 2)).sum(0)      # (K, 4 nb)
                   .reshape(K, 4, -1).transpose(0, 1) if ctx.needs_input_grad[7] else None)
        g_Wc = g_bc = None
        if has_coef:
            g_Wc = torch.bmm(g_logit, Zp.transpose(1, 2)).sum(0) if ctx.needs_input_grad[8] else None
            g_bc = g_logit.sum((0, 2)) if ctx.needs_input_grad[9] else None
        return (g_z0, g_s0, g_w, g_r, None, g_in_z, g_in_s, g_basis, g_Wc, g_bc, None, None, None, None)


def locally_linear_filter_jit(z0: Tensor, s0: Tensor, w: Tensor, r: Tensor, mu: Tensor | None, in_z: Tensor,
                              in_s: Tensor, basis: Tensor, Wc: Tensor | None, bc: Tensor | None, ident: Tensor,
                              bi: np.ndarray, bj: np.ndarray, diag_only: bool = False) -> tuple[Tensor, ...]:
    """The locally linear factorized filter on batch-last tensors (module docstring):
    ``z0: (2m, N)``, ``s0: (3m, N)`` (``[σ^u, σ^s, σ^l]``), ``w, r: (T, m, N)``, ``mu: (T, N)``
    1/0 or ``None``, ``in_z: (T, 2m, N)``, ``in_s: (T, 3m, N)`` (cause variances plus the
    transition noise), ``basis: (4, K, nb)`` band values of the blocks 11, 12, 21, 22 at the pairs
    ``(bi, bj)`` (:func:`band_pairs`), ``Wc: (K, 2m)`` and ``bc: (K,)`` the coefficient net
    (``None``: one basis matrix, :math:`\\alpha = 1`), ``ident: (nb,)`` what is added to the
    diagonal blocks (1 on the diagonal when the identity is added). Returns the priors
    ``Z: (T, 2m, N)``, ``S: (T, 3m, N)``, the posteriors ``Zp, Sp`` and the last prediction
    ``z_last: (2m, N)``, ``s_last: (3m, N)``; differentiable in every input but ``mu``,
    ``ident`` and the index arrays."""
    return _LocallyLinearFilter.apply(z0, s0, w, r, mu, in_z, in_s, basis, Wc, bc, ident, bi, bj, bool(diag_only))

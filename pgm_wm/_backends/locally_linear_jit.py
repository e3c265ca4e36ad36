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
vector instructions. A belief is one packed array of ``5m`` rows, :math:`[z^u; z^l; \sigma^u;
\sigma^s; \sigma^l]` (:data:`FIELDS`), so that every loop reads and writes few distinct arrays;
the small matrix products of a step (logits, mixture, and their adjoints) are loops over the
sequences (:func:`_matmul`). Values and gradients are tested equal to autograd of the reference loop
in float32 and float64 (``tests/test_locally_linear_jit.py``), and so is
:func:`packed_reference`, the same loop as tensor operations, which also serves the second
derivatives (``create_graph=True``) the hand-written backward pass does not compute.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .compiler import as_array, kernel

__all__ = ["FIELDS", "band_pairs", "locally_linear_filter_jit", "packed_reference"]

FIELDS = ("mean_upper", "mean_lower", "var_upper", "cov_side", "var_lower")
"""The five ``m``-row blocks of a packed belief, in order."""


def band_pairs(m: int, bandwidth: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``nb`` index pairs ``(i_p, j_p)`` of an ``m x m`` band of half-width ``bandwidth``,
    row by row: two int64 arrays."""
    rows, cols = [], []
    for i in range(m):
        for j in range(max(0, i - bandwidth), min(m, i + bandwidth + 1)):
            rows.append(i)
            cols.append(j)
    return np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)


@kernel
def _matmul(a, b, out, accumulate):
    """``out (+)= a @ b`` for C-contiguous ``a: (I, K)``, ``b: (K, N)``: the loop over ``N`` (the
    sequences) innermost, so it runs as vector instructions. Written out instead of ``np.dot``:
    these products are small, and a multi-threaded BLAS (OpenBLAS starts threads from about
    N = 128) can be a hundred times slower on a machine whose cores are busy."""
    rows, K = a.shape
    N = b.shape[1]
    for i in range(rows):
        row = out[i]
        if not accumulate:
            row[:] = 0
        for k in range(K):
            aik = a[i, k]
            bk = b[k]
            for n in range(N):
                row[n] += aik * bk[n]


@kernel
def _forward(x0, w, r, mu, inp, basis_t, ident, bi, bj, Wc, bc, has_coef, diag_only, one, X, P, alpha, Aval):
    """Forward loop, batch last: ``x0: (5m, N)`` the first prior (packed), ``w, r: (T, m, N)``,
    ``mu: (T, N)`` 1/0, ``inp: (T, 5m, N)`` the known causes (means, then variances plus the
    transition noise), ``basis_t: (4 nb, K)`` (the basis values, blocks 11, 12, 21, 22 one
    after the other), ``ident: (nb,)``, ``Wc: (K, 2m)``, ``bc: (K,)``, ``one`` the number 1 in
    the arrays' dtype (so that no arithmetic is promoted to float64). Writes the priors
    ``X: (T + 1, 5m, N)`` (``X[T]`` the prediction after the last step), the posteriors
    ``P: (T, 5m, N)`` and, for the backward pass, the mixing weights ``alpha: (T, K, N)`` and the
    mixed band values ``Aval: (T, 4 nb, N)``."""
    T, m, N = w.shape
    K, nb = basis_t.shape[1], bi.shape[0]
    two, zero = one + one, one - one
    u, lo, su, ss, sl = 0, m, 2 * m, 3 * m, 4 * m       # row offsets of the packed fields
    logit = np.empty((K, N), dtype=x0.dtype)
    X[0] = x0
    for t in range(T):
        x, post, wt, rt_, A = X[t], P[t], w[t], r[t], Aval[t]
        # update, Eq. (rkn-update) in product form
        for i in range(m):
            for n in range(N):
                mt, rt = mu[t, n], rt_[i, n]
                vu, vs, vl = x[su + i, n], x[ss + i, n], x[sl + i, n]
                g = mt / (vu + rt)
                ge = g * (wt[i, n] - x[u + i, n])
                rho = (one - mt) + rt * g
                post[u + i, n] = x[u + i, n] + vu * ge
                post[lo + i, n] = x[lo + i, n] + vs * ge
                post[su + i, n] = vu * rho
                post[ss + i, n] = vs * rho
                post[sl + i, n] = vl - vs * vs * g
        # mixing weights α = softmax(W z⁺ + c)
        if has_coef:
            _matmul(Wc, post[:2 * m], logit, False)
            for n in range(N):
                mx = logit[0, n] + bc[0]
                for k in range(1, K):
                    mx = max(mx, logit[k, n] + bc[k])
                tot = zero
                for k in range(K):
                    e = np.exp(logit[k, n] + bc[k] - mx)
                    logit[k, n] = e
                    tot += e
                for k in range(K):
                    alpha[t, k, n] = logit[k, n] / tot
        else:
            alpha[t] = one
        # A_t = ι + Σ_k α_k B_k on the band entries: one matrix product (4 nb, K) x (K, N)
        _matmul(basis_t, alpha[t], A, False)
        for p in range(nb):
            for n in range(N):
                A[p, n] += ident[p]
                A[3 * nb + p, n] += ident[p]
        # predict, Eq. (rkn-predict), plus the known causes
        nxt = X[t + 1]
        nxt[:] = inp[t]
        for p in range(nb):
            i, j = bi[p], bj[p]
            for n in range(N):
                a11, a12, a21, a22 = A[p, n], A[nb + p, n], A[2 * nb + p, n], A[3 * nb + p, n]
                pu, pl = post[u + j, n], post[lo + j, n]
                qu, qs, ql = post[su + j, n], post[ss + j, n], post[sl + j, n]
                nxt[u + i, n] += a11 * pu + a12 * pl
                nxt[lo + i, n] += a21 * pu + a22 * pl
                nxt[su + i, n] += a11 * (a11 * qu + two * a12 * qs) + a12 * a12 * ql
                nxt[ss + i, n] += a21 * a11 * qu + (a22 * a11 + a21 * a12) * qs + a22 * a12 * ql
                nxt[sl + i, n] += a21 * (a21 * qu + two * a22 * qs) + a22 * a22 * ql
        if diag_only:
            nxt[ss:ss + m] = zero


@kernel
def _backward(X, P, w, r, mu, basis, bi, bj, WcT, has_coef, diag_only, one, alpha, Aval, dX, dP,
              g_w, g_r, g_inp, g_A, g_logit):
    """Backward loop (module docstring): from the saved beliefs ``X, P``, ``alpha`` and ``Aval``
    and the gradients ``dX, dP`` of the outputs, the gradients of ``w, r`` and of the causes
    ``g_inp: (T, 5m, N)``, and, per step and sequence, the adjoints of the mixed band values
    ``g_A: (T, 4 nb, N)`` and of the logits ``g_logit: (T, K, N)`` (``basis: (K, 4 nb)``,
    ``WcT: (2m, K)``). The gradient of the first prior is left in ``dX[0]``. The parameter
    gradients are sums of products over steps and sequences, one matrix product each after the
    loop (reductions inside the loop would not run as vector instructions)."""
    T, m, N = w.shape
    K, nb = basis.shape[0], bi.shape[0]
    two, zero = one + one, one - one
    u, lo, su, ss, sl = 0, m, 2 * m, 3 * m, 4 * m
    dot = np.empty(N, dtype=X.dtype)
    bp = np.empty((5 * m, N), dtype=X.dtype)            # adjoint of the posterior of step t
    for t in range(T - 1, -1, -1):
        lam = dX[t + 1]                                  # adjoint of the prediction of step t
        if diag_only:
            lam[ss:ss + m] = zero                        # that side covariance is a constant zero
        g_inp[t] = lam
        bp[:] = dP[t]
        x, post, A, dA = X[t], P[t], Aval[t], g_A[t]
        # predict backward
        for p in range(nb):
            i, j = bi[p], bj[p]
            for n in range(N):
                a11, a12, a21, a22 = A[p, n], A[nb + p, n], A[2 * nb + p, n], A[3 * nb + p, n]
                pu, pl = post[u + j, n], post[lo + j, n]
                qu, qs, ql = post[su + j, n], post[ss + j, n], post[sl + j, n]
                lu, ll = lam[u + i, n], lam[lo + i, n]
                ku, ks, kl = lam[su + i, n], lam[ss + i, n], lam[sl + i, n]
                u1, u2 = a11 * qu + a12 * qs, a11 * qs + a12 * ql
                v1, v2 = a21 * qu + a22 * qs, a21 * qs + a22 * ql
                dA[p, n] = two * ku * u1 + ks * v1 + lu * pu
                dA[nb + p, n] = two * ku * u2 + ks * v2 + lu * pl
                dA[2 * nb + p, n] = two * kl * v1 + ks * u1 + ll * pu
                dA[3 * nb + p, n] = two * kl * v2 + ks * u2 + ll * pl
                bp[u + j, n] += a11 * lu + a21 * ll
                bp[lo + j, n] += a12 * lu + a22 * ll
                bp[su + j, n] += a11 * (a11 * ku + a21 * ks) + a21 * a21 * kl
                bp[ss + j, n] += two * (a11 * a12 * ku + a21 * a22 * kl) + (a22 * a11 + a21 * a12) * ks
                bp[sl + j, n] += a12 * (a12 * ku + a22 * ks) + a22 * a22 * kl
        if has_coef:
            # mixture backward, ᾱ = B Ā (one matrix product (K, 4 nb) x (4 nb, N)), then the
            # softmax: ℓ̄_k = α_k (ᾱ_k - Σ_k' α_k' ᾱ_k'), and z̄⁺ += Wᵀ ℓ̄
            dal = g_logit[t]
            _matmul(basis, dA, dal, False)
            dot[:] = zero
            for k in range(K):
                for n in range(N):
                    dot[n] += alpha[t, k, n] * dal[k, n]
            for k in range(K):
                for n in range(N):
                    dal[k, n] = alpha[t, k, n] * (dal[k, n] - dot[n])
            _matmul(WcT, dal, bp[:2 * m], True)
        # update backward, from the saved prior (as in factorized_jit); adds into dX[t]
        lam, wt, rt_ = dX[t], w[t], r[t]
        for i in range(m):
            for n in range(N):
                zu, vu, vs = x[u + i, n], x[su + i, n], x[ss + i, n]
                mt, rt = mu[t, n], rt_[i, n]
                d = vu + rt
                g = mt / d
                e = wt[i, n] - zu
                rho = (one - mt) + rt * g
                bpu, bpl = bp[u + i, n], bp[lo + i, n]
                bqu, bqs, bql = bp[su + i, n], bp[ss + i, n], bp[sl + i, n]
                sz = bpu * vu + bpl * vs
                be = g * sz
                brho = bqu * vu + bqs * vs
                bg = e * sz + rt * brho - vs * vs * bql
                bd = -bg * g / d
                g_w[t, i, n] = be
                g_r[t, i, n] = g * brho + bd
                lam[u + i, n] += bpu - be
                lam[lo + i, n] += bpl
                lam[su + i, n] += g * e * bpu + rho * bqu + bd
                lam[ss + i, n] += g * e * bpl + rho * bqs - two * vs * g * bql
                lam[sl + i, n] += bql
    if diag_only:
        dX[0, ss:ss + m] = zero


def _arr(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(as_array(x))


def packed_reference(x0: Tensor, w: Tensor, r: Tensor, mu: Tensor | None, inp: Tensor, basis: Tensor,
                     Wc: Tensor | None, bc: Tensor | None, ident: Tensor, bi: np.ndarray, bj: np.ndarray,
                     diag_only: bool = False) -> tuple[Tensor, Tensor]:
    """:func:`locally_linear_filter_jit` as tensor operations, step by step, on the same packed,
    batch-last arguments: the compiled loop's readable twin (tested equal to it, and to the
    book's loop). Differentiable to any order; the compiled backward pass recomputes through it
    when a gradient of a gradient is asked for. Returns ``(X, P)``."""
    T, m, N = w.shape
    ii, jj = torch.as_tensor(bi), torch.as_tensor(bj)
    x, Xs, Ps = x0, [x0], []
    for t in range(T):
        zu, zl, vu, vs, vl = x.split(m)
        mt = torch.ones_like(w[t, :1]) if mu is None else mu[t][None]
        g = mt / (vu + r[t])
        ge = g * (w[t] - zu)
        rho = (1.0 - mt) + r[t] * g
        post = torch.cat([zu + vu * ge, zl + vs * ge, vu * rho, vs * rho, vl - vs * vs * g])
        Ps.append(post)
        zp = post[:2 * m]
        alpha = torch.ones_like(zp[:1]) if Wc is None else torch.softmax(Wc @ zp + bc[:, None], dim=0)
        A = torch.einsum("xkp,kn->xpn", basis, alpha)                          # (4, nb, N)
        a11, a12, a21, a22 = A[0] + ident[:, None], A[1], A[2], A[3] + ident[:, None]
        pu, pl, qu, qs, ql = (post[k * m + jj] for k in range(5))
        rows = [a11 * pu + a12 * pl, a21 * pu + a22 * pl,
                a11 * (a11 * qu + 2 * a12 * qs) + a12 * a12 * ql,
                a21 * a11 * qu + (a22 * a11 + a21 * a12) * qs + a22 * a12 * ql,
                a21 * (a21 * qu + 2 * a22 * qs) + a22 * a22 * ql]
        nxt = inp[t] + torch.cat([torch.zeros_like(zu).index_add(0, ii, row) for row in rows])
        if diag_only:
            nxt = torch.cat([nxt[:3 * m], torch.zeros_like(nxt[3 * m:4 * m]), nxt[4 * m:]])
        Xs.append(nxt)
        x = nxt
    return torch.stack(Xs), torch.stack(Ps)


class _LocallyLinearFilter(torch.autograd.Function):
    """Autograd wrapper of :func:`_forward` / :func:`_backward` (batch-last tensors)."""

    @staticmethod
    def forward(ctx, x0, w, r, mu, inp, basis, Wc, bc, ident, bi, bj, diag_only):  # noqa: D102
        T, m, N = w.shape
        K, nb = basis.shape[1], bi.shape[0]
        opts = dict(dtype=w.dtype, device=w.device)
        X, P = torch.empty(T + 1, 5 * m, N, **opts), torch.empty(T, 5 * m, N, **opts)
        alpha, Aval = torch.empty(T, K, N, **opts), torch.empty(T, 4 * nb, N, **opts)
        mu = torch.ones(T, N, **opts) if mu is None else mu
        has_coef = Wc is not None
        one = _arr(w).dtype.type(1.0)
        Wc_, bc_ = (Wc, bc) if has_coef else (torch.zeros(1, 2 * m, **opts), torch.zeros(1, **opts))
        basis_k = basis.detach().permute(1, 0, 2).reshape(K, 4 * nb)          # (K, 4 nb)
        _forward(_arr(x0), _arr(w), _arr(r), _arr(mu), _arr(inp), _arr(basis_k.T), _arr(ident), bi, bj, _arr(Wc_),
                 _arr(bc_), has_coef, diag_only, one, X.numpy(), P.numpy(), alpha.numpy(), Aval.numpy())
        ctx.save_for_backward(X, P, w, r, mu, basis_k, Wc_, alpha, Aval, x0, inp, basis, Wc, bc, ident)
        ctx.bi, ctx.bj, ctx.diag_only, ctx.has_coef = bi, bj, diag_only, has_coef
        return X, P

    @staticmethod
    def backward(ctx, dX, dP):  # noqa: D102
        X, P, w, r, mu, basis_k, Wc_, alpha, Aval, *inputs = ctx.saved_tensors
        if torch.is_grad_enabled():      # create_graph=True: differentiate the readable twin instead
            return _differentiable_backward(ctx, w, r, mu, inputs, dX, dP)
        K = basis_k.shape[0]
        dX = torch.zeros_like(X) if dX is None else dX.clone(memory_format=torch.contiguous_format)
        dP = torch.zeros_like(P) if dP is None else dP
        g_w, g_r, g_inp = torch.empty_like(w), torch.empty_like(r), torch.empty_like(P)
        g_A, g_logit = torch.empty_like(Aval), torch.zeros_like(alpha)
        _backward(X.numpy(), P.numpy(), _arr(w), _arr(r), _arr(mu), _arr(basis_k), ctx.bi, ctx.bj, _arr(Wc_.T),
                  ctx.has_coef, ctx.diag_only, _arr(w).dtype.type(1.0), alpha.numpy(), Aval.numpy(), dX.numpy(),
                  _arr(dP), g_w.numpy(), g_r.numpy(), g_inp.numpy(), g_A.numpy(), g_logit.numpy())
        # B̄_{xy,k,p} = Σ_{t,n} α_{t,k,n} Ā_{t,xy,p,n};  W̄ = Σ_{t,n} ℓ̄ z⁺ᵀ;  c̄ = Σ_{t,n} ℓ̄
        g_basis = (torch.bmm(alpha, g_A.transpose(1, 2)).sum(0).reshape(K, 4, -1).transpose(0, 1)
                   if ctx.needs_input_grad[5] else None)
        g_Wc = g_bc = None
        if ctx.has_coef:
            m2 = ctx.saved_tensors[6].shape[1]
            g_Wc = torch.bmm(g_logit, P[:, :m2].transpose(1, 2)).sum(0) if ctx.needs_input_grad[6] else None
            g_bc = g_logit.sum((0, 2)) if ctx.needs_input_grad[7] else None
        return dX[0], g_w, g_r, None, g_inp, g_basis, g_Wc, g_bc, None, None, None, None


def _differentiable_backward(ctx, w: Tensor, r: Tensor, mu: Tensor | None, inputs: list, dX: Tensor | None,
                             dP: Tensor | None) -> tuple:
    """The gradients of every input as a differentiable function of the inputs and of the
    output gradients: autograd through :func:`packed_reference` (second derivatives exact)."""
    x0, inp, basis, Wc, bc, ident = inputs
    args = {1: x0, 2: w, 3: r, 5: inp, 6: basis, 7: Wc, 8: bc}          # position in forward's arguments
    wanted = [i for i, x in args.items() if x is not None and ctx.needs_input_grad[i - 1]]
    xs = {i: (x.view_as(x) if i in wanted else x) for i, x in args.items()}
    X, P = packed_reference(xs[1], xs[2], xs[3], mu, xs[5], xs[6], xs[7], xs[8], ident, ctx.bi, ctx.bj,
                            ctx.diag_only)
    outs = [(o, g) for o, g in ((X, dX), (P, dP)) if g is not None]
    grads = torch.autograd.grad([o for o, _ in outs], [xs[i] for i in wanted], [g for _, g in outs],
                                create_graph=True, allow_unused=True) if outs and wanted else ()
    result: list = [None] * 12
    for i, g in zip(wanted, grads):
        result[i - 1] = torch.zeros_like(args[i]) if g is None else g
    return tuple(result)


def locally_linear_filter_jit(x0: Tensor, w: Tensor, r: Tensor, mu: Tensor | None, inp: Tensor, basis: Tensor,
                              Wc: Tensor | None, bc: Tensor | None, ident: Tensor, bi: np.ndarray, bj: np.ndarray,
                              diag_only: bool = False) -> tuple[Tensor, Tensor]:
    """The locally linear factorized filter on batch-last, packed tensors (module docstring):
    ``x0: (5m, N)`` the first prior, rows :data:`FIELDS`; ``w, r: (T, m, N)``; ``mu: (T, N)``
    1/0 or ``None``; ``inp: (T, 5m, N)`` the known causes of each step, packed like a belief
    (their means, their variances plus the transition noise); ``basis: (4, K, nb)`` band values
    of the blocks 11, 12, 21, 22 at the pairs ``(bi, bj)`` (:func:`band_pairs`); ``Wc: (K, 2m)``
    and ``bc: (K,)`` the coefficient net (``None``: one basis matrix, :math:`\alpha = 1`);
    ``ident: (nb,)`` what is added to the diagonal blocks (1 on the diagonal when the identity is
    added). Returns ``X: (T + 1, 5m, N)`` (the priors ``X[:T]`` and the predictions ``X[1:]``)
    and the posteriors ``P: (T, 5m, N)``; differentiable in every input but ``mu``, ``ident``
    and the index arrays."""
    return _LocallyLinearFilter.apply(x0, w, r, mu, inp, basis, Wc, bc, ident, bi, bj, bool(diag_only))

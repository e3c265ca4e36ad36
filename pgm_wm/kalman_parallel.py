r"""Parallel-in-time Kalman filtering and RTS smoothing by associative scan (Chapter 1).

Särkkä and García-Fernández (2021) observed that the filter's recursion is the prefix
"product" of one element per step under an associative operator, so it can be computed with
:math:`O(\log T)` sequential depth (an associative scan) instead of :math:`T` dependent steps.
Every element and the operator follow from the chapter's own identities:

* **Element of step t** (:math:`t \ge 2`): the step's contribution
  :math:`p(z_t \mid z_{t-1}, y_t) \propto p(y_t\mid z_t)\,p(z_t\mid z_{t-1})` is a linear-Gaussian
  map of :math:`z_{t-1}`, by the update Eq. (kf-update) of the "prior"
  :math:`\mathcal N(Fz_{t-1} + c_{t-1}, Q)`: with :math:`S = HQH^\top + R`, :math:`K = QH^\top S^{-1}`,

  .. math:: \begin{aligned}
            p(z_t\mid z_{t-1}, y_t) &= \mathcal N\big(A_t z_{t-1} + b_t,\; C_t\big),\quad
            A_t = (I - KH)F,\\
            b_t &= c_{t-1} + K(y_t - Hc_{t-1}),\quad C_t = (I-KH)Q(I-KH)^\top + KRK^\top,
            \end{aligned}

  and the evidence :math:`p(y_t \mid z_{t-1}) \propto \exp(-\tfrac12 z_{t-1}^\top J_t z_{t-1} +
  \eta_t^\top z_{t-1})` (Eq. gauss-evidence read as a function of :math:`z_{t-1}`) with
  :math:`J_t = F^\top H^\top S^{-1}HF`, :math:`\eta_t = F^\top H^\top S^{-1}(y_t - Hc_{t-1})`.
  A missing observation gives :math:`(F, c_{t-1}, Q, 0, 0)`; step 1 is the posterior of
  ``init`` itself, :math:`(0, \mu^+_1, \Sigma^+_1, 0, 0)`.
* **Operator** :math:`(A_i, b_i, C_i, \eta_i, J_i) \otimes (A_j, b_j, C_j, \eta_j, J_j)`
  (:math:`i` before :math:`j`): marginalize the middle state (Eq. gauss-marginal) after
  conditioning it on the later evidence (Eq. gauss-condition); with :math:`M = (I + C_iJ_j)^{-1}`,

  .. math:: A = A_jMA_i,\ b = A_jM(b_i + C_i\eta_j) + b_j,\ C = A_jMC_iA_j^\top + C_j,\
            \eta = A_i^\top M^\top(\eta_j - J_jb_i) + \eta_i,\ J = A_i^\top M^\top J_jA_i + J_i .

  The prefix product up to step :math:`t` has :math:`A = 0` and is the filtered posterior
  :math:`\mathcal N(b, C) = p(z_t\mid y_{\le t})`.
* **Smoother elements** :math:`(E_t, g_t, L_t)` with the RTS gain :math:`E_t = G_t` and
  :math:`p(z_t\mid z_{t+1}, y_{\le t}) = \mathcal N(E_tz_{t+1} + g_t, L_t)` (Eq. rts before
  averaging); the operator composes two such linear-Gaussian maps (Eq. gauss-marginal):
  :math:`(E_iE_j,\ E_ig_j + g_i,\ E_iL_jE_i^\top + L_i)`, scanned from the end.

The priors, one-step predictions and the exact log-likelihood (Eq. kf-loglik) then follow for
all steps at once from the filtered beliefs. :func:`associative_scan` is generic (any tuple of
tensors with time first, any associative ``fn``), for other linear-Gaussian chains with a
state-independent transition too.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
from torch import Tensor

from .filtering import FilterResult
from ._linalg import LOG_2PI, symmetrize
from .gaussian import Gaussian
from ._backends.kalman_fast import smoothing_precision
from .kalman import check_filter_inputs, check_smoother_inputs, smoother_gains

__all__ = ["associative_scan", "parallel_kalman_filter", "parallel_rts_smoother", "scan_filter"]

Elems = tuple[Tensor, ...]


def associative_scan(fn: Callable[[Elems, Elems], Elems], elems: Sequence[Tensor], reverse: bool = False) -> Elems:
    """Inclusive scan ``out[t] = e[0] ⊗ e[1] ⊗ … ⊗ e[t]`` (``reverse``: ``e[t] ⊗ … ⊗ e[T-1]``)
    of a tuple of tensors with time on axis 0, for an associative ``fn(earlier, later)`` that
    combines batches of elements elementwise along axis 0.

    The odd–even recursion (Blelloch; Ladner–Fischer): combine neighbouring pairs, scan the
    half-length sequence recursively, then fill in the even positions; ``2⌈log₂T⌉`` calls of
    ``fn``, each on up to ``T/2`` elements at once, so the sequential depth is ``O(log T)``
    and the total work ``O(T)``. Differentiable (no in-place writes).
    """
    elems = tuple(elems)
    if len(elems) == 0:
        raise ValueError("elems: need at least one tensor")
    T = elems[0].shape[0]
    if any(e.shape[0] != T for e in elems):
        raise ValueError("elems: every tensor needs the same length on axis 0")
    if reverse:
        flipped = tuple(e.flip(0) for e in elems)
        out = _prefix(lambda a, b: fn(b, a), flipped)
        return tuple(o.flip(0) for o in out)
    return _prefix(fn, elems)


def _prefix(fn: Callable[[Elems, Elems], Elems], elems: Elems) -> Elems:
    T = elems[0].shape[0]
    if T < 2:
        return elems
    pairs = fn(tuple(e[0:-1:2] for e in elems), tuple(e[1::2] for e in elems))     # T // 2 elements
    odd = _prefix(fn, pairs)                                                          # prefixes at 1, 3, 5, …
    rest = tuple(e[2::2] for e in elems)
    left = odd if T % 2 == 1 else tuple(o[:-1] for o in odd)
    even = fn(left, rest) if rest[0].shape[0] > 0 else rest                          # prefixes at 2, 4, …
    even = tuple(torch.cat([e[:1], ev]) for e, ev in zip(elems, even))
    return tuple(_interleave(ev, od) for ev, od in zip(even, odd))


def _interleave(even: Tensor, odd: Tensor) -> Tensor:
    """``[even[0], odd[0], even[1], odd[1], …]`` (``len(even) - len(odd)`` is 0 or 1)."""
    k = odd.shape[0]
    both = torch.stack([even[:k], odd], 1).reshape(2 * k, *odd.shape[1:])
    return both if even.shape[0] == k else torch.cat([both, even[k:]])


def _mv(A: Tensor, x: Tensor) -> Tensor:
    return (A @ x.unsqueeze(-1)).squeeze(-1)


def _filter_op(a: Elems, b: Elems) -> Elems:
    """The filtering operator of the module docstring, on batches of elements."""
    A_i, b_i, C_i, eta_i, J_i = a
    A_j, b_j, C_j, eta_j, J_j = b
    n = A_i.shape[-1]
    eye = torch.eye(n, dtype=A_i.dtype, device=A_i.device)
    lu = torch.linalg.lu_factor(eye + C_i @ J_j)                       # I + C_i J_j
    rhs = torch.cat([A_i, (b_i + _mv(C_i, eta_j)).unsqueeze(-1), C_i], -1)
    X = torch.linalg.lu_solve(*lu, rhs)                                # M [A_i, b_i + C_i η_j, C_i]
    MA, Mb, MC = X[..., :n], X[..., n], X[..., n + 1:]
    rhs_t = torch.cat([(eta_j - _mv(J_j, b_i)).unsqueeze(-1), J_j @ A_i], -1)
    Y = torch.linalg.lu_solve(*lu, rhs_t, adjoint=True)                # Mᵀ [η_j − J_j b_i, J_j A_i]
    A_it = A_i.transpose(-1, -2)
    return (
        A_j @ MA,
        _mv(A_j, Mb) + b_j,
        symmetrize(A_j @ MC @ A_j.transpose(-1, -2)) + C_j,
        _mv(A_it, Y[..., 0]) + eta_i,
        symmetrize(A_it @ Y[..., 1:]) + J_i,
    )


def _smoother_op(a: Elems, b: Elems) -> Elems:
    """The smoothing operator (``a`` the earlier step, ``b`` the later one)."""
    E_i, g_i, L_i = a
    E_j, g_j, L_j = b
    return E_i @ E_j, _mv(E_i, g_j) + g_i, symmetrize(E_i @ L_j @ E_i.transpose(-1, -2)) + L_i


def scan_filter(y: Tensor, w: Tensor, c: Tensor, m0: Tensor, P0: Tensor, F: Tensor, H: Tensor, Q: Tensor,
                R: Tensor) -> tuple[Tensor, ...]:
    r"""The filter of :func:`parallel_kalman_filter` on validated, time-major inputs, with noise
    covariances that may change with time: ``y: (T, N, m)``, ``w: (T, N)`` 1 = observed,
    ``c: (T, N, n)`` the known inputs of the predict after step ``t``, ``m0: (N, n)``,
    ``P0: (N, n, n)``, ``F: (1, N, n, n)``, ``H: (1, N, m, n)``, ``Q: (T or 1, N, n, n)`` the
    noise of the predict after step ``t``, ``R: (T or 1, N, m, m)`` that of observation ``t``.
    Returns ``(m_prior, P_prior, m_post, P_post, m_next, P_next, ll)``, time-major, with
    ``ll: (T, N)``. Used by :func:`pgm_wm.factorized.parallel_factorized_filter` too."""
    T, N, m = y.shape
    n = m0.shape[-1]
    dt, dev = y.dtype, y.device
    eye = torch.eye(n, dtype=dt, device=dev)
    Q_prev = Q[:-1] if Q.shape[0] == T else Q          # noise entering step t = 2..T
    R0, R_rest = R[0], (R[1:] if R.shape[0] == T else R)
    H0 = H[0]
    # Step 1: the posterior of init given y_1 (Eqs. kf-update, kf-joseph).
    S0 = H0 @ P0 @ H0.transpose(-1, -2) + R0
    K0 = P0 @ H0.transpose(-1, -2) @ torch.linalg.inv(S0) * w[0, :, None, None]
    A0 = eye - K0 @ H0
    b1 = m0 + _mv(K0, y[0] - _mv(H0, m0))
    C1 = symmetrize(A0 @ P0 @ A0.transpose(-1, -2) + K0 @ R0 @ K0.transpose(-1, -2))
    # Steps 2..T: elements (A, b, C, η, J) from the update of N(F z + c, Q) with y_t.
    S = H @ Q_prev @ H.transpose(-1, -2) + R_rest
    HtSinv = torch.linalg.solve(S, H.expand(S.shape[0], N, m, n)).transpose(-1, -2) * w[1:, :, None, None]
    K = Q_prev @ HtSinv                                                      # (T-1, N, n, m)
    IKH = eye - K @ H
    resid = y[1:] - _mv(H, c[:-1])
    A = IKH @ F
    b = c[:-1] + _mv(K, resid)
    C = symmetrize(IKH @ Q_prev @ IKH.transpose(-1, -2) + K @ R_rest @ K.transpose(-1, -2))
    FtHtSinv = F.transpose(-1, -2) @ HtSinv
    eta = _mv(FtHtSinv, resid)
    J = symmetrize(FtHtSinv @ H @ F)
    zeros_nn = torch.zeros(1, N, n, n, dtype=dt, device=dev)
    elems = (
        torch.cat([zeros_nn, A.expand(T - 1, N, n, n)]), torch.cat([b1[None], b]), torch.cat([C1[None], C]),
        torch.cat([torch.zeros(1, N, n, dtype=dt, device=dev), eta]), torch.cat([zeros_nn, J]),
    )
    _, m_post, P_post, _, _ = associative_scan(_filter_op, elems)           # (T, N, n), (T, N, n, n)

    # Predictions and the exact log-likelihood for all steps at once (Eqs. kf-predict, kf-loglik).
    m_next = _mv(F, m_post) + c
    P_next = symmetrize(F @ P_post @ F.transpose(-1, -2)) + Q
    m_prior = torch.cat([m0[None], m_next[:-1]])
    P_prior = torch.cat([P0[None], P_next[:-1]])
    S_all = symmetrize(H @ P_prior @ H.transpose(-1, -2)) + R
    chol, _ = torch.linalg.cholesky_ex(S_all)
    innov = y - _mv(H, m_prior)
    sol = torch.linalg.solve_triangular(chol, innov.unsqueeze(-1), upper=False).squeeze(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    ll = -0.5 * (sol.square().sum(-1) + logdet + m * LOG_2PI)
    ll = torch.where(w > 0, ll, torch.zeros((), dtype=dt))
    return m_prior, P_prior, m_post, P_post, m_next, P_next, ll


def parallel_kalman_filter(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None = None, B: Tensor | None = None, u: Tensor | None = None,
    *, validate: bool = True,
) -> FilterResult[Gaussian]:
    """The Kalman filter by associative scan, :math:`O(\\log T)` sequential depth; same
    signature, checks and result as :func:`pgm_wm.kalman.kalman_filter` (exact, not an
    approximation: tested equal to the sequential filter to 1e-10 in float64)."""
    y, mask, offsets, batch = check_filter_inputs(y, init, F, H, Q, R, mask, B, u, validate)
    T, n = y.shape[-2], init.dim
    N = math.prod(batch)
    dt, dev = y.dtype, y.device

    def tm(x: Tensor, k: int) -> Tensor:
        """(*batch, T, *event) -> (T, N, *event)."""
        event = x.shape[x.ndim - k:]
        return x.expand(*batch, T, *event).reshape(N, T, *event).transpose(0, 1)

    def per(x: Tensor, k: int) -> Tensor:
        """A parameter (*b, *event) -> (N, *event)."""
        event = x.shape[x.ndim - k:]
        return x.expand(*batch, *event).reshape(N, *event)

    Fb, Hb, Qb, Rb = per(F, 2), per(H, 2), per(Q, 2), per(R, 2)
    y_t = tm(y, 1)                                                           # (T, N, m)
    w = torch.ones(T, N, dtype=dt, device=dev) if mask is None else tm(mask, 0).to(dt)
    c = torch.zeros(T, N, n, dtype=dt, device=dev) if offsets is None else tm(offsets, 1)
    m_prior, P_prior, m_post, P_post, m_next, P_next, ll = scan_filter(
        y_t, w, c, per(init.mean, 1), per(init.cov, 2), *(x.unsqueeze(0) for x in (Fb, Hb, Qb, Rb)))
    ll = ll.T.reshape(*batch, T)

    def belief(mean: Tensor, cov: Tensor) -> Gaussian:
        return Gaussian(mean.transpose(0, 1).reshape(*batch, T, n), cov.transpose(0, 1).reshape(*batch, T, n, n))

    return FilterResult(belief(m_prior, P_prior), belief(m_post, P_post), belief(m_next, P_next), ll)


def parallel_rts_smoother(result: FilterResult, F: Tensor, Q: Tensor) -> Gaussian:
    """The RTS smoother by associative scan from the end, :math:`O(\\log T)` sequential depth;
    same arguments and result as :func:`pgm_wm.kalman.rts_smoother` (elements in the module
    docstring; the conditional covariances in the Joseph form)."""
    post, nxt = check_smoother_inputs(result, F, Q)
    dtype = F.dtype
    m_f, P_f, m_n, P_n, F, Q = smoothing_precision(post, nxt, F, Q)     # float32: run in float64
    post, nxt = Gaussian(m_f, P_f), Gaussian(m_n, P_n)
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    mean = post.mean.expand(*batch, T, n)
    if T == 1:
        return Gaussian(mean, post.cov.expand(*batch, T, n, n)).to(dtype)
    G, L = smoother_gains(post, nxt, F, Q)                                  # (..., T-1, n, n)
    G = G.expand(*batch, T - 1, n, n)
    L = L.expand(*batch, T - 1, n, n)
    g = mean[..., :-1, :] - _mv(G, nxt.mean.expand(*batch, T, n)[..., :-1, :])   # μ⁺ − G μ⁻_{t+1}
    last_cov = post.cov.expand(*batch, T, n, n)[..., -1:, :, :]
    E = torch.cat([G, torch.zeros_like(last_cov)], -3)
    g = torch.cat([g, mean[..., -1:, :]], -2)
    Lall = torch.cat([L, last_cov], -3)
    k = len(batch)
    _, m_s, P_s = associative_scan(
        _smoother_op, (E.movedim(k, 0), g.movedim(k, 0), Lall.movedim(k, 0)), reverse=True)
    return Gaussian(m_s.movedim(0, k), P_s.movedim(0, k)).to(dtype)

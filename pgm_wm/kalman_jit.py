r"""Compiled per-sequence loops of the Kalman filter and the RTS smoother (Chapter 1).

The fast backend (:mod:`pgm_wm.kalman_fast`) hands these loops the case in which every sequence
has its own covariances (a mask per sequence) and the parameters ``F, H, Q, R`` are shared:
there the covariance recursion cannot be computed once for the batch, and a step of tensor
operations costs more in launches than in arithmetic. Compiled (:mod:`pgm_wm._jit`), a step is
the book's equations on one sequence's small matrices:

* update, Eqs. (kf-update) and (kf-joseph): :math:`S = H\Sigma^-H^\top + R = LL^\top` (Cholesky),
  :math:`K = \Sigma^-H^\top S^{-1}`, :math:`\mu^+ = \mu^- + K(y - H\mu^-)`,
  :math:`\Sigma^+ = (I - KH)\Sigma^-(I - KH)^\top + KRK^\top` (then symmetrized); a missing step
  keeps the prior and adds 0 to the log-likelihood;
* log-likelihood, Eq. (kf-loglik): :math:`-\tfrac12(\lVert L^{-1}e\rVert^2 + 2\sum_i\log L_{ii}
  + m\log 2\pi)`;
* predict, Eq. (kf-predict): :math:`\mu^-_{t+1} = F\mu^+ + Bu_t`, :math:`\Sigma^-_{t+1} = F\Sigma^+F^\top + Q`;
* smoother, Eq. (rts): :math:`G_t = \Sigma^+_tF^\top(\Sigma^-_{t+1})^{-1}` by a Cholesky solve,
  :math:`\mu^s_t = \mu^+_t + G_t(\mu^s_{t+1} - \mu^-_{t+1})`,
  :math:`\Sigma^s_t = (I - G_tF)\Sigma^+_t(I - G_tF)^\top + G_tQG_t^\top + G_t\Sigma^s_{t+1}G_t^\top`.

Every array is stored batch-last (``(T, n, n, N)``: each matrix entry a contiguous vector over
the ``N`` sequences), and every loop over the batch is innermost, so the compiler turns it into
vector instructions: all sequences advance one step together. Tested equal to
:func:`pgm_wm.kalman.kalman_filter_reference` and
:func:`pgm_wm.kalman.rts_smoother_reference` in float32 and float64.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit

_LOG_2PI = math.log(2.0 * math.pi)


@jit
def _cholesky(S, L):
    """Lower Cholesky factors of batch-last SPD matrices ``S: (k, k, N)`` into ``L``
    (upper part untouched); a factor that is not positive definite gets NaN."""
    k, _, N = S.shape
    for j in range(k):
        for b in range(N):
            d = S[j, j, b]
            for p in range(j):
                d -= L[j, p, b] * L[j, p, b]
            L[j, j, b] = math.sqrt(d) if d > 0.0 else np.nan
        for i in range(j + 1, k):
            for b in range(N):
                v = S[i, j, b]
                for p in range(j):
                    v -= L[i, p, b] * L[j, p, b]
                L[i, j, b] = v / L[j, j, b]


@jit
def _cholesky_solve(L, X):
    r"""Overwrite batch-last ``X: (k, r, N)`` by :math:`(LL^\top)^{-1}X` (``L`` from :func:`_cholesky`)."""
    k, r, N = X.shape
    for c in range(r):
        for i in range(k):                               # L z = x
            for p in range(i):
                for b in range(N):
                    X[i, c, b] -= L[i, p, b] * X[p, c, b]
            for b in range(N):
                X[i, c, b] /= L[i, i, b]
        for i in range(k - 1, -1, -1):                   # Lᵀ x = z
            for p in range(i + 1, k):
                for b in range(N):
                    X[i, c, b] -= L[p, i, b] * X[p, c, b]
            for b in range(N):
                X[i, c, b] /= L[i, i, b]


@jit
def filter_loop(y, w, off, F, H, Q, R, M, P, Mp, Pp, ll):
    r"""The masked Kalman filter of every sequence (module docstring), batch-last, in place.

    ``y: (T, m, N)``, ``w: (T, N)`` 1 = observed / 0 = missing (``y`` is then ignored, NaN
    allowed), ``off: (T, n, N)`` the known inputs :math:`Bu_t`, ``F, Q: (n, n)``, ``H: (m, n)``,
    ``R: (m, m)``. ``M[0]: (n, N)`` and ``P[0]: (n, n, N)`` hold the first prior on entry.
    Outputs: priors ``M: (T+1, n, N)``, ``P: (T+1, n, n, N)`` (index ``T`` the last
    prediction), posteriors ``Mp: (T, n, N)``, ``Pp: (T, n, n, N)``, log-likelihoods
    ``ll: (T, N)`` (NaN where an innovation matrix is not positive definite)."""
    T, m, N = y.shape
    n = F.shape[0]
    dt = y.dtype
    PHt = np.empty((n, m, N), dt)
    S = np.empty((m, m, N), dt)
    L = np.empty((m, m, N), dt)
    Kt = np.empty((m, n, N), dt)                     # Kᵀ = S⁻¹ H Σ⁻ (solved in place)
    A = np.empty((n, n, N), dt)                      # I − K H
    AP = np.empty((n, n, N), dt)
    KR = np.empty((n, m, N), dt)
    FP = np.empty((n, n, N), dt)
    e = np.empty((m, N), dt)
    z = np.empty((m, N), dt)
    acc = np.empty(N, dt)
    c0 = -0.5 * m * _LOG_2PI
    for t in range(T):
        Pt, Mt, Pu, mu = P[t], M[t], Pp[t], Mp[t]
        wt = w[t]
        for i in range(n):                               # Σ⁻ Hᵀ
            for k in range(m):
                for b in range(N):
                    acc[b] = 0.0
                for j in range(n):
                    h = H[k, j]
                    for b in range(N):
                        acc[b] += Pt[i, j, b] * h
                PHt[i, k] = acc
        for k in range(m):                               # S = H Σ⁻ Hᵀ + R
            for k2 in range(m):
                for b in range(N):
                    acc[b] = R[k, k2]
                for j in range(n):
                    h = H[k, j]
                    for b in range(N):
                        acc[b] += h * PHt[j, k2, b]
                S[k, k2] = acc
        for k in range(m):                               # e = y − H μ⁻ (0 where missing)
            for b in range(N):
                acc[b] = y[t, k, b]
            for j in range(n):
                h = H[k, j]
                for b in range(N):
                    acc[b] -= h * Mt[j, b]
            for b in range(N):
                e[k, b] = acc[b] if wt[b] != 0.0 else 0.0
        _cholesky(S, L)
        for b in range(N):                               # log-likelihood, Eq. (kf-loglik)
            acc[b] = 0.0
        for k in range(m):
            for b in range(N):
                v = e[k, b]
                for p in range(k):
                    v -= L[k, p, b] * z[p, b]
                v /= L[k, k, b]
                z[k, b] = v
                acc[b] += v * v + 2.0 * math.log(L[k, k, b])
        for b in range(N):
            ll[t, b] = c0 - 0.5 * acc[b] if wt[b] != 0.0 else 0.0
        for k in range(m):                               # Kᵀ = S⁻¹ (Σ⁻Hᵀ)ᵀ, 0 where missing
            for i in range(n):
                for b in range(N):
                    Kt[k, i, b] = PHt[i, k, b]
        _cholesky_solve(L, Kt)
        for k in range(m):
            for i in range(n):
                for b in range(N):
                    Kt[k, i, b] = Kt[k, i, b] if wt[b] != 0.0 else 0.0
        for i in range(n):                               # μ⁺ = μ⁻ + K e
            for b in range(N):
                acc[b] = Mt[i, b]
            for k in range(m):
                for b in range(N):
                    acc[b] += Kt[k, i, b] * e[k, b]
            mu[i] = acc
        for i in range(n):                               # A = I − K H, K R
            for j in range(n):
                for b in range(N):
                    acc[b] = 1.0 if i == j else 0.0
                for k in range(m):
                    h = H[k, j]
                    for b in range(N):
                        acc[b] -= Kt[k, i, b] * h
                A[i, j] = acc
            for k2 in range(m):
                for b in range(N):
                    acc[b] = 0.0
                for k in range(m):
                    r = R[k, k2]
                    for b in range(N):
                        acc[b] += Kt[k, i, b] * r
                KR[i, k2] = acc
        for i in range(n):                               # A Σ⁻
            for j in range(n):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    for b in range(N):
                        acc[b] += A[i, p, b] * Pt[p, j, b]
                AP[i, j] = acc
        for i in range(n):                               # Σ⁺ = A Σ⁻ Aᵀ + K R Kᵀ (Joseph form)
            for j in range(i + 1):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    for b in range(N):
                        acc[b] += AP[i, p, b] * A[j, p, b]
                for k2 in range(m):
                    for b in range(N):
                        acc[b] += KR[i, k2, b] * Kt[k2, j, b]
                Pu[i, j] = acc
                Pu[j, i] = acc
        for i in range(n):                               # μ⁻_{t+1} = F μ⁺ + B u
            for b in range(N):
                acc[b] = off[t, i, b]
            for j in range(n):
                f = F[i, j]
                for b in range(N):
                    acc[b] += f * mu[j, b]
            M[t + 1, i] = acc
        for i in range(n):                               # Σ⁻_{t+1} = F Σ⁺ Fᵀ + Q
            for j in range(n):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    f = F[i, p]
                    for b in range(N):
                        acc[b] += f * Pu[p, j, b]
                FP[i, j] = acc
        for i in range(n):
            for j in range(i + 1):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    f = F[j, p]
                    for b in range(N):
                        acc[b] += FP[i, p, b] * f
                for b in range(N):
                    P[t + 1, i, j, b] = acc[b] + Q[i, j]
                    P[t + 1, j, i, b] = acc[b] + Q[j, i]


@jit
def smoother_loop(mf, Pf, mp, Pn, F, Q, Ms, Cs):
    r"""The RTS smoother of every sequence (module docstring), batch-last: ``Ms: (T, n, N)``,
    ``Cs: (T, n, n, N)`` from the filter's posteriors ``mf, Pf`` and next-step priors ``mp, Pn``
    (index ``t``: :math:`p(z_{t+1}\mid y_{\le t})`). Returns False if a predicted covariance is
    not positive definite."""
    T, n, N = mf.shape
    dt = mf.dtype
    Sp = np.empty((n, n, N), dt)
    L = np.empty((n, n, N), dt)
    Gt = np.empty((n, n, N), dt)                     # Gᵀ = (Σ⁻)⁻¹ F Σ⁺ (solved in place)
    A = np.empty((n, n, N), dt)                      # I − G F
    AP = np.empty((n, n, N), dt)
    GQC = np.empty((n, n, N), dt)                    # G (Q + Σˢ_{t+1})
    d = np.empty((n, N), dt)
    acc = np.empty(N, dt)
    Ms[T - 1] = mf[T - 1]
    Cs[T - 1] = Pf[T - 1]
    for t in range(T - 2, -1, -1):
        for i in range(n):
            for j in range(n):
                for b in range(N):
                    Sp[i, j, b] = 0.5 * (Pn[t, i, j, b] + Pn[t, j, i, b])
        _cholesky(Sp, L)
        for i in range(n):
            for b in range(N):
                if not L[i, i, b] > 0.0:
                    return False
        for i in range(n):                               # F Σ⁺
            for j in range(n):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    f = F[i, p]
                    for b in range(N):
                        acc[b] += f * Pf[t, p, j, b]
                Gt[i, j] = acc
        _cholesky_solve(L, Gt)
        for i in range(n):                               # A = I − G F
            for j in range(n):
                for b in range(N):
                    acc[b] = 1.0 if i == j else 0.0
                for p in range(n):
                    f = F[p, j]
                    for b in range(N):
                        acc[b] -= Gt[p, i, b] * f
                A[i, j] = acc
        for i in range(n):                               # A Σ⁺ and G (Q + Σˢ_{t+1})
            for j in range(n):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    for b in range(N):
                        acc[b] += A[i, p, b] * Pf[t, p, j, b]
                AP[i, j] = acc
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    q = Q[p, j]
                    for b in range(N):
                        acc[b] += Gt[p, i, b] * (q + Cs[t + 1, p, j, b])
                GQC[i, j] = acc
        for i in range(n):                               # μˢ = μ⁺ + G (μˢ_{t+1} − μ⁻_{t+1})
            for b in range(N):
                d[i, b] = Ms[t + 1, i, b] - mp[t, i, b]
        for i in range(n):
            for b in range(N):
                acc[b] = mf[t, i, b]
            for p in range(n):
                for b in range(N):
                    acc[b] += Gt[p, i, b] * d[p, b]
            Ms[t, i] = acc
        for i in range(n):                               # Σˢ = A Σ⁺ Aᵀ + G (Q + Σˢ_{t+1}) Gᵀ
            for j in range(i + 1):
                for b in range(N):
                    acc[b] = 0.0
                for p in range(n):
                    for b in range(N):
                        acc[b] += AP[i, p, b] * A[j, p, b] + GQC[i, p, b] * Gt[p, j, b]
                Cs[t, i, j] = acc
                Cs[t, j, i] = acc
    return True

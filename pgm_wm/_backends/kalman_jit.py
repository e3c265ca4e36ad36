r"""Compiled loops of the Kalman filter and the RTS smoother (Chapter 1), the ``"compiled"``
backend of :func:`pgm_wm.kalman.kalman_filter` and :func:`pgm_wm.kalman.rts_smoother`.

A step of tensor operations costs more in launches than in arithmetic for these small
matrices; compiled (:mod:`pgm_wm._backends.compiler`), a step is the book's equations on the
small matrices of the sequences, for parameters ``F, H, Q, R`` shared by the batch:

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

The covariances, gains and smoother gains do not depend on the observed values. So the loops
take ``C`` covariance sequences: ``C = N``, one per sequence (a mask per sequence, or a batched
initial covariance), or ``C = 1``, one for the whole batch (no mask, or the same mask for every
sequence): the Riccati recursion then runs once, and only the means are per sequence. Every
array is stored batch-last (``(T, n, n, C)``, ``(T, n, N)``: each matrix entry a contiguous
vector over the sequences), and every loop over the batch is innermost, so the compiler turns
it into vector instructions: all sequences advance one step together. Tested equal to
:func:`pgm_wm.kalman.kalman_filter_reference` and
:func:`pgm_wm.kalman.rts_smoother_reference` in float32 and float64.
"""

from __future__ import annotations

import math

import numpy as np

from .compiler import kernel

_LOG_2PI = math.log(2.0 * math.pi)


@kernel
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


@kernel
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


@kernel
def _same(a, b):
    """Whether the batch-last matrices ``a, b: (k, l, C)`` are equal bitwise (NaN never is)."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            for c in range(a.shape[2]):
                if a[i, j, c] != b[i, j, c]:
                    return False
    return True


@kernel
def filter_loop(y, w, off, F, H, Q, R, M, P, Mp, Pp, ll):
    r"""The masked Kalman filter of every sequence (module docstring), batch-last, in place.

    ``y: (T, m, N)``, ``w: (T, N)`` 1 = observed / 0 = missing (``y`` is then ignored, NaN
    allowed), ``off: (T, n, N)`` the known inputs :math:`Bu_t` (``w``, ``off`` with a first
    axis of length 1: the same at every step, e.g. all observed, no input), ``F, Q: (n, n)``, ``H: (m, n)``,
    ``R: (m, m)``. ``M[0]: (n, N)`` and ``P[0]: (n, n, C)`` hold the first prior on entry, with
    ``C = N`` covariances (one per sequence) or ``C = 1`` (shared by the batch; the mask must
    then be the same for every sequence: column 0 of ``w`` drives the covariances).
    Outputs: priors ``M: (T+1, n, N)``, ``P: (T+1, n, n, C)`` (index ``T`` the last
    prediction), posteriors ``Mp: (T, n, N)``, ``Pp: (T, n, n, C)``, log-likelihoods
    ``ll: (T, N)`` (NaN where an innovation matrix is not positive definite)."""
    T, m, N = y.shape
    n = F.shape[0]
    C = P.shape[3]
    dt = y.dtype
    PHt = np.empty((n, m, C), dt)
    S = np.empty((m, m, C), dt)
    Lc = np.empty((m, m, C), dt)
    Ktc = np.empty((m, n, C), dt)                    # Kᵀ = S⁻¹ H Σ⁻ (solved in place)
    A = np.empty((n, n, C), dt)                      # I − K H
    AP = np.empty((n, n, C), dt)
    KR = np.empty((n, m, C), dt)
    FP = np.empty((n, n, C), dt)
    ac = np.empty(C, dt)
    # the gains and Cholesky factors per sequence (copies of the shared ones when C = 1)
    ldc = np.empty(C, dt)                            # log det S
    Kt = Ktc if C == N else np.empty((m, n, N), dt)
    L = Lc if C == N else np.empty((m, m, N), dt)
    ld = ldc if C == N else np.empty(N, dt)
    e = np.empty((m, N), dt)
    z = np.empty((m, N), dt)
    acc = np.empty(N, dt)
    c0 = -0.5 * m * _LOG_2PI
    steady = False
    for t in range(T):
        Pt, Mt, Pu, mu = P[t], M[t], Pp[t], Mp[t]
        wt = w[t] if w.shape[0] == T else w[0]
        ot = off[t] if off.shape[0] == T else off[0]
        if steady:                                       # the covariances repeat: copy them
            for i in range(n):
                for j in range(n):
                    for c in range(C):
                        Pu[i, j, c] = Pp[t - 1, i, j, c]
                        P[t + 1, i, j, c] = Pt[i, j, c]
        else:
            # ---- covariances (C of them): Eqs. (kf-update), (kf-joseph), (kf-predict)
            for i in range(n):                               # Σ⁻ Hᵀ
                for k in range(m):
                    for c in range(C):
                        ac[c] = 0.0
                    for j in range(n):
                        h = H[k, j]
                        for c in range(C):
                            ac[c] += Pt[i, j, c] * h
                    for c in range(C):
                        PHt[i, k, c] = ac[c]
            for k in range(m):                               # S = H Σ⁻ Hᵀ + R
                for k2 in range(m):
                    for c in range(C):
                        ac[c] = R[k, k2]
                    for j in range(n):
                        h = H[k, j]
                        for c in range(C):
                            ac[c] += h * PHt[j, k2, c]
                    for c in range(C):
                        S[k, k2, c] = ac[c]
            _cholesky(S, Lc)
            for c in range(C):
                ac[c] = 0.0
            for k in range(m):
                for c in range(C):
                    ac[c] += 2.0 * math.log(Lc[k, k, c])
            for c in range(C):
                ldc[c] = ac[c]
            for k in range(m):                               # Kᵀ = S⁻¹ (Σ⁻Hᵀ)ᵀ, 0 where missing
                for i in range(n):
                    for c in range(C):
                        Ktc[k, i, c] = PHt[i, k, c]
            _cholesky_solve(Lc, Ktc)
            for k in range(m):
                for i in range(n):
                    for c in range(C):
                        Ktc[k, i, c] = Ktc[k, i, c] if wt[c] != 0.0 else 0.0
            for i in range(n):                               # A = I − K H, K R
                for j in range(n):
                    for c in range(C):
                        ac[c] = 1.0 if i == j else 0.0
                    for k in range(m):
                        h = H[k, j]
                        for c in range(C):
                            ac[c] -= Ktc[k, i, c] * h
                    for c in range(C):
                        A[i, j, c] = ac[c]
                for k2 in range(m):
                    for c in range(C):
                        ac[c] = 0.0
                    for k in range(m):
                        r = R[k, k2]
                        for c in range(C):
                            ac[c] += Ktc[k, i, c] * r
                    for c in range(C):
                        KR[i, k2, c] = ac[c]
            for i in range(n):                               # A Σ⁻
                for j in range(n):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        for c in range(C):
                            ac[c] += A[i, p, c] * Pt[p, j, c]
                    for c in range(C):
                        AP[i, j, c] = ac[c]
            for i in range(n):                               # Σ⁺ = A Σ⁻ Aᵀ + K R Kᵀ (Joseph form)
                for j in range(i + 1):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        for c in range(C):
                            ac[c] += AP[i, p, c] * A[j, p, c]
                    for k2 in range(m):
                        for c in range(C):
                            ac[c] += KR[i, k2, c] * Ktc[k2, j, c]
                    for c in range(C):
                        Pu[i, j, c] = ac[c]
                    for c in range(C):
                        Pu[j, i, c] = ac[c]
            for i in range(n):                               # Σ⁻_{t+1} = F Σ⁺ Fᵀ + Q
                for j in range(n):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        f = F[i, p]
                        for c in range(C):
                            ac[c] += f * Pu[p, j, c]
                    for c in range(C):
                        FP[i, j, c] = ac[c]
            for i in range(n):
                for j in range(i + 1):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        f = F[j, p]
                        for c in range(C):
                            ac[c] += FP[i, p, c] * f
                    for c in range(C):
                        P[t + 1, i, j, c] = ac[c] + Q[i, j]
                        P[t + 1, j, i, c] = ac[c] + Q[j, i]
            if C != N:                                       # shared: the same gain for every sequence
                for k in range(m):
                    for i in range(n):
                        g = Ktc[k, i, 0]
                        for b in range(N):
                            Kt[k, i, b] = g
                    for k2 in range(m):
                        g = Lc[k, k2, 0]
                        for b in range(N):
                            L[k, k2, b] = g
                g = ldc[0]
                for b in range(N):
                    ld[b] = g
            # without a mask, once Σ⁻_{t+1} = Σ⁻_t bitwise every later step repeats this one
            steady = w.shape[0] == 1 and _same(P[t + 1], Pt)
        # ---- means (N of them)
        for k in range(m):                               # e = y − H μ⁻ (0 where missing)
            for b in range(N):
                acc[b] = y[t, k, b]
            for j in range(n):
                h = H[k, j]
                for b in range(N):
                    acc[b] -= h * Mt[j, b]
            for b in range(N):
                e[k, b] = acc[b] if wt[b] != 0.0 else 0.0
        for b in range(N):                               # log-likelihood, Eq. (kf-loglik)
            acc[b] = ld[b]
        for k in range(m):
            for b in range(N):
                v = e[k, b]
                for p in range(k):
                    v -= L[k, p, b] * z[p, b]
                v /= L[k, k, b]
                z[k, b] = v
                acc[b] += v * v
        for b in range(N):
            ll[t, b] = c0 - 0.5 * acc[b] if wt[b] != 0.0 else 0.0
        for i in range(n):                               # μ⁺ = μ⁻ + K e
            for b in range(N):
                acc[b] = Mt[i, b]
            for k in range(m):
                for b in range(N):
                    acc[b] += Kt[k, i, b] * e[k, b]
            for b in range(N):
                mu[i, b] = acc[b]
        for i in range(n):                               # μ⁻_{t+1} = F μ⁺ + B u
            for b in range(N):
                acc[b] = ot[i, b]
            for j in range(n):
                f = F[i, j]
                for b in range(N):
                    acc[b] += f * mu[j, b]
            for b in range(N):
                M[t + 1, i, b] = acc[b]


@kernel
def smoother_loop(mf, Pf, mp, Pn, F, Q, Ms, Cs):
    r"""The RTS smoother of every sequence (module docstring), batch-last: ``Ms: (T, n, N)``,
    ``Cs: (T, n, n, C)`` from the filter's posteriors ``mf: (T, n, N)``, ``Pf: (T, n, n, C)``
    and next-step priors ``mp, Pn`` (index ``t``: :math:`p(z_{t+1}\mid y_{\le t})`), with
    ``C = N`` covariance sequences or ``C = 1`` shared by the batch. Returns False if a
    predicted covariance is not positive definite."""
    T, n, N = mf.shape
    C = Pf.shape[3]
    dt = mf.dtype
    Sp = np.empty((n, n, C), dt)
    Lc = np.empty((n, n, C), dt)
    Gtc = np.empty((n, n, C), dt)                    # Gᵀ = (Σ⁻)⁻¹ F Σ⁺ (solved in place)
    A = np.empty((n, n, C), dt)                      # I − G F
    AP = np.empty((n, n, C), dt)
    GQC = np.empty((n, n, C), dt)                    # G (Q + Σˢ_{t+1})
    ac = np.empty(C, dt)
    Gt = Gtc if C == N else np.empty((n, n, N), dt)  # the gains per sequence (copies when C = 1)
    d = np.empty((n, N), dt)
    acc = np.empty(N, dt)
    Ms[T - 1] = mf[T - 1]
    Cs[T - 1] = Pf[T - 1]
    cs_repeats = False                               # Σˢ_{t+1} = Σˢ_{t+2} bitwise
    for t in range(T - 2, -1, -1):
        # ---- covariances (C of them). Where the filter's covariances of step t equal those of
        # step t + 1 bitwise (its steady state), the gains of step t + 1 are reused, and so is
        # Σˢ_{t+1} once the smoothed covariances repeat too: the same numbers, computed once.
        same_inputs = t < T - 2 and _same(Pf[t], Pf[t + 1]) and _same(Pn[t], Pn[t + 1])
        if not same_inputs:
            for i in range(n):
                for j in range(n):
                    for c in range(C):
                        Sp[i, j, c] = 0.5 * (Pn[t, i, j, c] + Pn[t, j, i, c])
            _cholesky(Sp, Lc)
            for i in range(n):
                for c in range(C):
                    if not Lc[i, i, c] > 0.0:
                        return False
            for i in range(n):                           # F Σ⁺
                for j in range(n):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        f = F[i, p]
                        for c in range(C):
                            ac[c] += f * Pf[t, p, j, c]
                    for c in range(C):
                        Gtc[i, j, c] = ac[c]
            _cholesky_solve(Lc, Gtc)
            for i in range(n):                           # A = I − G F
                for j in range(n):
                    for c in range(C):
                        ac[c] = 1.0 if i == j else 0.0
                    for p in range(n):
                        f = F[p, j]
                        for c in range(C):
                            ac[c] -= Gtc[p, i, c] * f
                    for c in range(C):
                        A[i, j, c] = ac[c]
            for i in range(n):                           # A Σ⁺
                for j in range(n):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        for c in range(C):
                            ac[c] += A[i, p, c] * Pf[t, p, j, c]
                    for c in range(C):
                        AP[i, j, c] = ac[c]
            if C != N:
                for i in range(n):
                    for j in range(n):
                        g = Gtc[i, j, 0]
                        for b in range(N):
                            Gt[i, j, b] = g
        if same_inputs and cs_repeats:
            for i in range(n):
                for j in range(n):
                    for c in range(C):
                        Cs[t, i, j, c] = Cs[t + 1, i, j, c]
        else:
            for i in range(n):                           # G (Q + Σˢ_{t+1})
                for j in range(n):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        q = Q[p, j]
                        for c in range(C):
                            ac[c] += Gtc[p, i, c] * (q + Cs[t + 1, p, j, c])
                    for c in range(C):
                        GQC[i, j, c] = ac[c]
            for i in range(n):                           # Σˢ = A Σ⁺ Aᵀ + G (Q + Σˢ_{t+1}) Gᵀ
                for j in range(i + 1):
                    for c in range(C):
                        ac[c] = 0.0
                    for p in range(n):
                        for c in range(C):
                            ac[c] += AP[i, p, c] * A[j, p, c] + GQC[i, p, c] * Gtc[p, j, c]
                    for c in range(C):
                        Cs[t, i, j, c] = ac[c]
                    for c in range(C):
                        Cs[t, j, i, c] = ac[c]
            cs_repeats = _same(Cs[t], Cs[t + 1])
        # ---- means (N of them): μˢ = μ⁺ + G (μˢ_{t+1} − μ⁻_{t+1})
        for i in range(n):
            for b in range(N):
                d[i, b] = Ms[t + 1, i, b] - mp[t, i, b]
        for i in range(n):
            for b in range(N):
                acc[b] = mf[t, i, b]
            for p in range(n):
                for b in range(N):
                    acc[b] += Gt[p, i, b] * d[p, b]
            for b in range(N):
                Ms[t, i, b] = acc[b]
    return True

r"""The ``"tensor"`` and ``"compiled"`` backends of :func:`pgm_wm.kalman.kalman_filter` and of
:func:`pgm_wm.kalman.rts_smoother` (Chapter 1): the same numbers as the book's reference loops
(tested in float32 and float64), with fewer operations per step. Which one serves a call is
decided by the backend table (:mod:`pgm_wm._backends`).

* Shared covariances: with unbatched parameters and the same mask (or none) for every sequence,
  one covariance sequence (Eqs. kf-update, kf-joseph, kf-predict) serves the whole batch: the
  covariances, gains and smoother gains do not depend on the observed values.
* ``"compiled"`` (unbatched ``F, H, Q, R``, no gradient, CPU): the loops of
  :mod:`pgm_wm._backends.kalman_jit` (numba; all sequences advance together, batch-last), for
  the filter and the RTS smoother, with one covariance sequence for the batch where it is shared
  and one per sequence otherwise.
* ``"tensor"``, shared covariances: the Riccati recursion once (without a mask and a gradient it
  stops at its bitwise steady state); the means are then the linear recursion
  :math:`\mu^-_{t+1} = F(I - K_tH)\mu^-_t + FK_ty_t + Bu_t`, one small GEMM per step, and
  posteriors and log-likelihoods (Eq. kf-loglik) follow for all steps at once.
* ``"tensor"``, a covariance per sequence: batch-last storage ("structure of arrays"), every map
  linear in the covariance one GEMM with a constant matrix, closed-form 2×2 inverses,
  preallocated outputs (the path with a gradient, on other devices, or with ``PGM_WM_JIT=0``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..filtering import FilterResult
from .._linalg import LOG_2PI, predict_cov, sandwich_operator, symmetrize
from ..gaussian import Gaussian
from .compiler import as_array, contiguous_array, empty
from .kalman_jit import filter_loop, smoother_loop

def _spd_inverse(S: Tensor) -> tuple[Tensor, Tensor]:
    """``(S⁻¹, log det S)`` of small SPD matrices ``(..., m, m)``: closed formulas on the whole
    batch for ``m ≤ 2`` (a handful of elementwise operations instead of one LAPACK call per
    matrix), Cholesky otherwise. Not positive definite → NaN in the log-determinant."""
    m = S.shape[-1]
    if m == 1:
        return S.reciprocal(), torch.log(S[..., 0, 0])
    if m == 2:
        a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        det = a * d - b * b
        logdet = torch.where(a > 0, torch.log(det), torch.full_like(det, float("nan")))
        inv = torch.stack([d, -b, -b, a], -1).reshape(S.shape) / det[..., None, None]
        return inv, logdet
    chol, info = torch.linalg.cholesky_ex(S)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    logdet = torch.where(info == 0, logdet, torch.full_like(logdet, float("nan")))
    return torch.cholesky_inverse(chol), logdet


def _joseph_step(P: Tensor, H: Tensor, R: Tensor, w: Tensor | None, eye: Tensor) -> tuple[Tensor, ...]:
    """One covariance update, Eqs. (kf-update) and (kf-joseph), on a batch of priors ``P``
    (``(..., n, n)``, parameters broadcast). Returns ``(Σ⁺, K, S⁻¹, log det S)``."""
    PHt = P @ H.transpose(-1, -2)                                  # (..., n, m)
    S_inv, logdet = _spd_inverse(H @ PHt + R)
    K = PHt @ S_inv
    if w is not None:
        K = K * w[..., None, None]
    A = eye - K @ H
    return symmetrize(A @ P @ A.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)), K, S_inv, logdet


def filter_fast(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None, offsets: Tensor | None, batch: torch.Size, compiled: bool,
) -> FilterResult[Gaussian]:
    """The ``"compiled"`` (``compiled=True``: unbatched ``F, H, Q, R``, no gradient, CPU) or
    ``"tensor"`` backend (module docstring) on validated inputs; see :func:`kalman_filter`."""
    T, m, n = y.shape[-2], y.shape[-1], init.dim
    N = math.prod(batch)
    dt, dev = y.dtype, y.device
    eye = torch.eye(n, dtype=dt, device=dev)
    needs_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (y, init.mean, init.cov, F, H, Q, R) + (() if offsets is None else (offsets,)))

    def flat(x: Tensor, k: int) -> Tensor:
        """(*b, *event) with k event dims -> (N, *event)."""
        event = x.shape[x.ndim - k:]
        return x.expand(*batch, *event).reshape(N, *event)

    y_tm = flat(y, 2).transpose(0, 1)                                          # (T, N, m)
    off_tm = None if offsets is None else flat(offsets, 2).transpose(0, 1)    # (T, N, n)
    flat_mask = None if mask is None else flat(mask, 1)                        # (N, T)
    params_2d = all(x.ndim == 2 for x in (F, H, Q, R, init.cov))
    shared = params_2d and (flat_mask is None or bool((flat_mask == flat_mask[:1]).all()))
    w_all = None if flat_mask is None else flat_mask.to(dt)

    if compiled:
        return filter_compiled(flat(y, 2), w_all, None if offsets is None else flat(offsets, 2), F, H, Q, R,
                               flat(init.mean, 1), init.cov if shared else flat(init.cov, 2), batch)
    if shared:
        # One covariance sequence for the whole batch (Riccati recursion, Eqs. kf-update/kf-predict).
        w = None if w_all is None else w_all[0]
        op_F = sandwich_operator(F)
        steady_ok = mask is None and not needs_grad
        P, Ps, Ks, Sinvs, logdets, Pps = init.cov, [], [], [], [], []
        t_steady = T                           # first step from which everything repeats
        for t in range(T):
            Ps.append(P)
            step = _joseph_step(P, H, R, None if w is None else w[t], eye)
            nxt = predict_cov(step[0], F, Q, op_F)
            for lst, x in zip((Pps, Ks, Sinvs, logdets), step):
                lst.append(x)
            if steady_ok and torch.equal(nxt, P):
                t_steady = t
                break
            P = nxt
        Ps.append(nxt)
        rest = T - len(Pps)                     # steps after the steady state: views of the last one

        def seq(xs: list[Tensor]) -> Tensor:
            out = torch.stack(xs)
            return out if rest == 0 else torch.cat([out, out[-1:].expand(rest, *out.shape[1:])])

        P_all, Pp_all = seq(Ps), seq(Pps)                                       # (T+1, n, n), (T, n, n)
        K_all, Sinv_all, logdet_all = seq(Ks), seq(Sinvs), seq(logdets)
        # Means: μ⁻_{t+1} = A_t μ⁻_t + c_t with A_t = F(I − K_t H), c_t = F K_t y_t + B u_t.
        FK = F @ K_all                                                          # (T, n, m)
        A_t = (F - FK @ H).transpose(-1, -2)                                    # (T, n, n), transposed
        ts = min(t_steady, T)
        y_bt = flat(y, 2)                                                        # (N, T, m)
        c = torch.bmm(y_tm[:ts], FK[:ts].transpose(-1, -2))                     # transient: per step
        if ts < T:                                                              # steady: one GEMM
            c = torch.cat([c, (y_bt[:, ts:] @ FK[ts].T).transpose(0, 1)])
        if off_tm is not None:
            c = c + off_tm
        mean0 = flat(init.mean, 1)
        if needs_grad:
            means = [mean0]
            for t in range(T):
                means.append(torch.addmm(c[t], means[-1], A_t[t]))
            M = torch.stack(means)
        else:
            M = torch.empty(T + 1, N, n, dtype=dt, device=dev)
            M[0] = mean0
            for t in range(T):
                torch.addmm(c[t], M[t], A_t[t], out=M[t + 1])
        innov = y_tm - M[:T] @ H.transpose(-1, -2)                               # (T, N, m)
        gain_term = torch.bmm(innov[:ts], K_all[:ts].transpose(-1, -2))
        if ts < T:
            gain_term = torch.cat([gain_term, innov[ts:] @ K_all[ts].T])
        M_post = M[:T] + gain_term
        S_inv_tm, logdet_tm = Sinv_all.unsqueeze(1), logdet_all.unsqueeze(1)
        cov_prior = P_all[:T].unsqueeze(1)
        cov_post = Pp_all.unsqueeze(1)
        cov_next = P_all[1:].unsqueeze(1)
    else:
        # A covariance per sequence (a mask per sequence or batched parameters), outputs
        # written into preallocated tensors (lists when a gradient is needed).
        if needs_grad:
            lists: dict[str, list[Tensor]] = {k: [] for k in ("P", "Pp", "M", "Mp", "Sinv", "ld", "e")}
            bufs: dict[str, Tensor] = {}
        else:
            # "structure of arrays": the batch is the last, contiguous axis of every slot
            sizes = dict(P=(T + 1, n, n, N), Pp=(T, n, n, N), M=(T + 1, n, N), Mp=(T, n, N),
                         Sinv=(T, m, m, N), ld=(T, N), e=(T, m, N))
            bufs = {k: torch.empty(v, dtype=dt, device=dev) for k, v in sizes.items()}

        def out(name: str, t: int) -> Tensor | None:
            """The slot of step t of an output (None: let the op allocate, for autograd)."""
            return None if needs_grad else bufs[name][t]

        def put(name: str, t: int, x: Tensor, soa: bool = True) -> None:
            """Store x (batch last if soa, else batch first) as slot t of an output."""
            if not soa:
                x = x.movedim(0, -1)
            if needs_grad:
                lists[name].append(x)
            elif x.data_ptr() != bufs[name][t].data_ptr():
                bufs[name][t].copy_(x)

        step = _SequenceStep(F, H, Q, R, n, m, N) if params_2d else None
        P, mean = flat(init.cov, 2), flat(init.mean, 1)
        if step is not None:
            P, mean = P.permute(1, 2, 0).contiguous(), mean.T.contiguous()
            y_soa = y_tm.permute(0, 2, 1).contiguous()                             # (T, m, N)
            u_soa = None if off_tm is None else off_tm.permute(0, 2, 1).contiguous()
        put("P", 0, P, soa=step is not None)
        put("M", 0, mean, soa=step is not None)
        for t in range(T):
            w = None if w_all is None else w_all[:, t]
            if step is not None:
                P, mean = step(P, mean, y_soa[t], w, None if u_soa is None else u_soa[t], t, out)
                for name in ("Pp", "Mp", "Sinv", "ld", "e"):
                    put(name, t, getattr(step, name))
                put("P", t + 1, P)
                put("M", t + 1, mean)
            else:   # batched parameters: plain batched matrix products
                prior = Gaussian(mean, P)
                Pp, K, S_inv, logdet = _joseph_step(P, flat(H, 2) if H.ndim > 2 else H,
                                                    flat(R, 2) if R.ndim > 2 else R, w, eye)
                Fb = flat(F, 2) if F.ndim > 2 else F
                e = y_tm[t] - (prior.mean.unsqueeze(-2) @ (flat(H, 2) if H.ndim > 2 else H).transpose(-1, -2)).squeeze(-2)
                mean_p = mean + (K @ e.unsqueeze(-1)).squeeze(-1)
                P = symmetrize(Fb @ Pp @ Fb.transpose(-1, -2)) + (flat(Q, 2) if Q.ndim > 2 else Q)
                mean = (Fb @ mean_p.unsqueeze(-1)).squeeze(-1)
                if off_tm is not None:
                    mean = mean + off_tm[t]
                for name, x in (("Pp", Pp), ("Mp", mean_p), ("Sinv", S_inv), ("ld", logdet.expand(N)),
                                ("e", e)):
                    put(name, t, x, soa=False)
                put("P", t + 1, P, soa=False)
                put("M", t + 1, mean, soa=False)
        if needs_grad:
            bufs = {k: torch.stack([x.expand_as(v[-1]) for x in v]) for k, v in lists.items()}
        aos = {k: v.movedim(-1, 1) for k, v in bufs.items()}          # batch back to axis 1 (views)
        M, M_post, innov = aos["M"], aos["Mp"], aos["e"]
        S_inv_tm, logdet_tm = aos["Sinv"], bufs["ld"]
        cov_prior, cov_post, cov_next = aos["P"][:T], aos["Pp"], aos["P"][1:]

    # Eq. (kf-loglik) for all steps at once: log N(e_t | 0, S_t).
    quad = (innov.unsqueeze(-1) * innov.unsqueeze(-2) * S_inv_tm).flatten(-2).sum(-1)   # (T, N)
    ll = -0.5 * (quad + logdet_tm + m * LOG_2PI)
    if w_all is not None:
        ll = torch.where(w_all.T > 0, ll, torch.zeros((), dtype=dt))
    ll = ll.T.reshape(*batch, T)

    def belief(mean_tm: Tensor, cov_tm: Tensor) -> Gaussian:
        mean = mean_tm.reshape(T, *batch, n).movedim(0, -2)
        cov = cov_tm.expand(T, N, n, n).reshape(T, *batch, n, n).movedim(0, -3) if cov_tm.shape[1] == N \
            else cov_tm.reshape(T, *([1] * len(batch)), n, n).movedim(0, -3).expand(*batch, T, n, n)
        return Gaussian(mean, cov)

    return FilterResult(belief(M[:T], cov_prior), belief(M_post, cov_post), belief(M[1:], cov_next), ll)


def filter_compiled(y: Tensor, w: Tensor | None, offsets: Tensor | None, F: Tensor, H: Tensor, Q: Tensor,
                    R: Tensor, mean0: Tensor, cov0: Tensor, batch: torch.Size) -> FilterResult[Gaussian]:
    """The ``"compiled"`` filter (:func:`pgm_wm._backends.kalman_jit.filter_loop`, batch-last):
    ``y: (N, T, m)``, ``w: (N, T)`` 1/0 or ``None``, ``offsets: (N, T, n)`` or ``None``,
    ``mean0: (N, n)``, ``cov0: (n, n)`` (one covariance sequence for the batch; the mask, if
    any, must be the same for every sequence) or ``(N, n, n)`` (one per sequence). The results
    are batch-first views of the batch-last buffers (shared covariances: broadcast views)."""
    N, T, m = y.shape
    n = F.shape[-1]
    C = 1 if cov0.ndim == 2 else N
    dt = y.dtype
    w = torch.ones(1, N, dtype=dt) if w is None else w.T            # (T or 1, N)
    off = torch.zeros(1, n, N, dtype=dt) if offsets is None else offsets.permute(1, 2, 0)
    M, P = empty(T + 1, n, N, dtype=dt), empty(T + 1, n, n, C, dtype=dt)
    Mp, Pp, ll = empty(T, n, N, dtype=dt), empty(T, n, n, C, dtype=dt), empty(T, N, dtype=dt)
    M[0], P[0] = mean0.T, cov0.unsqueeze(-1) if C == 1 else cov0.permute(1, 2, 0)
    arr = contiguous_array
    filter_loop(as_array(y.permute(1, 2, 0)), arr(w), arr(off), arr(F), arr(H), arr(Q), arr(R),
                M.numpy(), P.numpy(), Mp.numpy(), Pp.numpy(), ll.numpy())
    return FilterResult(_batch_first(M[:T], P[:T], batch), _batch_first(Mp, Pp, batch),
                        _batch_first(M[1:], P[1:], batch), ll.T.reshape(*batch, T))


def _batch_first(mean: Tensor, cov: Tensor, batch: torch.Size) -> Gaussian:
    """A belief from batch-last buffers ``mean: (T, n, N)``, ``cov: (T, n, n, C)`` (``C = 1``:
    shared by the batch, returned as a broadcast view)."""
    T, n = mean.shape[:2]
    m = mean.permute(2, 0, 1).reshape(*batch, T, n)
    if cov.shape[-1] == 1 and mean.shape[-1] != 1:
        c = cov[..., 0].reshape(*([1] * len(batch)), T, n, n).expand(*batch, T, n, n)
    else:
        c = cov.permute(3, 0, 1, 2).reshape(*batch, T, n, n)
    return Gaussian(m, c)


class _SequenceStep:
    r"""One step of the per-sequence fast path for unbatched ``F, H, Q, R`` on ``N``
    covariances stored "structure of arrays" (``Σ: (n, n, N)``, ``μ: (n, N)``): every map that
    is linear in :math:`\Sigma` or :math:`K` is one GEMM with a constant matrix, products of two
    per-sequence matrices are broadcast multiply-and-sum over the contiguous batch axis, the
    innovation matrices are inverted by closed formulas (``m ≤ 2``), and results go straight
    into their output slots (``out``). Eqs. (kf-update), (kf-joseph), (kf-predict)."""

    def __init__(self, F: Tensor, H: Tensor, Q: Tensor, R: Tensor, n: int, m: int, N: int) -> None:
        dt, dev = F.dtype, F.device
        eye_n = torch.eye(n, dtype=dt, device=dev)
        # vec(Σ) -> [vec(Σ Hᵀ), vec(H Σ Hᵀ) + vec(R)], vec(K) -> vec(K H), vec(K R)
        to_PHt = torch.einsum("ab,kj->akbj", eye_n, H).reshape(n * m, n * n)        # [i k, i j] = H_kj
        to_S = torch.einsum("ki,lj->klij", H, H).reshape(m * m, n * n)
        self.lin = torch.cat([to_PHt, to_S], 0).contiguous()
        self.lin_bias = torch.cat([torch.zeros(n * m, dtype=dt, device=dev), R.reshape(m * m)])[:, None]
        self.to_KH = torch.einsum("ab,kj->ajbk", eye_n, H).reshape(n * n, n * m)     # [i j, i k] = H_kj
        self.to_KR = torch.einsum("ab,kj->ajbk", eye_n, R).reshape(n * m, n * m)     # [i j, i k] = R_kj
        self.to_FPF = torch.einsum("ki,lj->klij", F, F).reshape(n * n, n * n)
        self.eye_vec = eye_n.reshape(n * n, 1)
        self.Qv = Q.reshape(n * n, 1)
        self.H, self.F = H, F
        self.n, self.m, self.N = n, m, N

    def __call__(self, P: Tensor, mean: Tensor, y_t: Tensor, w: Tensor | None, u_t: Tensor | None, t: int, out):
        n, m, N = self.n, self.m, self.N
        lin = torch.addmm(self.lin_bias, self.lin, P.view(n * n, N))                # (n m + m², N)
        PHt = lin[: n * m].view(n, m, N)
        S = lin[n * m:].view(m, m, N)
        S_inv, logdet = _spd_inverse_soa(S, w)                                       # weight 0: K = 0
        K = _mm(PHt, S_inv)                                                           # (n, m, N)
        A = torch.addmm(self.eye_vec, self.to_KH, K.view(n * m, N), alpha=-1).view(n, n, N)   # I − K H
        KR = (self.to_KR @ K.view(n * m, N)).view(n, m, N)
        # Joseph form (kf-joseph): Σ⁺ = A Σ Aᵀ + K R Kᵀ
        Pp = torch.add(_mm_t(_mm(A, P), A), _mm_t(KR, K), out=out("Pp", t))
        e = torch.addmm(y_t, self.H, mean, alpha=-1, out=out("e", t))                # y − H μ⁻
        Mp = torch.add(mean, (K * e.unsqueeze(0)).sum(1), out=out("Mp", t))
        slot = out("P", t + 1)
        P_next = torch.addmm(self.Qv, self.to_FPF, Pp.view(n * n, N),
                             out=None if slot is None else slot.view(n * n, N)).view(n, n, N)
        mean_next = torch.addmm(u_t, self.F, Mp, out=out("M", t + 1)) if u_t is not None \
            else torch.mm(self.F, Mp, out=out("M", t + 1))
        self.Pp, self.Mp, self.Sinv, self.ld, self.e = Pp, Mp, S_inv, logdet, e
        return P_next, mean_next


def _mm(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` for batch-last matrices ``A: (i, k, N)``, ``B: (k, j, N)`` -> ``(i, j, N)``."""
    return (A.unsqueeze(2) * B.unsqueeze(0)).sum(1)


def _mm_t(A: Tensor, B: Tensor) -> Tensor:
    """``A @ Bᵀ`` for batch-last matrices ``A: (i, k, N)``, ``B: (j, k, N)`` -> ``(i, j, N)``."""
    return (A.unsqueeze(1) * B.unsqueeze(0)).sum(2)


def _spd_inverse_soa(S: Tensor, w: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(w · S⁻¹, log det S)`` for batch-last SPD matrices ``S: (m, m, N)``; closed formulas for
    ``m ≤ 2``, Cholesky otherwise (see :func:`_spd_inverse`)."""
    m = S.shape[0]
    if m == 2:
        a, b, d = S[0, 0], S[0, 1], S[1, 1]
        det = torch.addcmul(a * d, b, b, value=-1)
        scale = det.reciprocal() if w is None else w / det
        nb = -b
        inv = torch.stack([d, nb, nb, a]).view(2, 2, -1) * scale
        return inv, torch.log(det)
    inv, logdet = _spd_inverse(S.movedim(-1, 0))
    inv = inv.movedim(0, -1)
    return (inv if w is None else inv * w), logdet


def rts_compiled(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> Gaussian:
    """The ``"compiled"`` RTS smoother (:func:`pgm_wm._backends.kalman_jit.smoother_loop`,
    batch-last) for unbatched ``F, Q`` without a gradient: one covariance sequence where the
    filter's covariances are shared by the batch (broadcast views), one per sequence otherwise.
    The views that :func:`filter_compiled` returns are read without a copy."""
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    N = math.prod(batch)
    dt = F.dtype
    Pf, Pn = compact(post.cov, 3), compact(nxt.cov, 3)
    C = 1 if Pf.shape[:-3].numel() == 1 and Pn.shape[:-3].numel() == 1 else N

    def soa(x: Tensor, k: int, cols: int) -> np.ndarray:       # (*batch, T, *event) -> (T, *event, cols)
        event = x.shape[x.ndim - k:]
        x = x.reshape(T, *event, 1) if cols == 1 else \
            x.expand(*batch, T, *event).reshape(N, T, *event).movedim(0, -1)
        return contiguous_array(x)

    M, Cs = empty(T, n, N, dtype=dt), empty(T, n, n, C, dtype=dt)
    if not smoother_loop(soa(post.mean, 1, N), soa(Pf, 2, C), soa(nxt.mean, 1, N), soa(Pn, 2, C),
                         contiguous_array(F), contiguous_array(Q), M.numpy(), Cs.numpy()):
        raise ValueError("result: a predicted covariance is not positive definite (Q too small?)")
    return _batch_first(M, Cs, batch)


def smoothing_precision(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> tuple[Tensor, ...]:
    r"""The filter's beliefs and ``F, Q`` in the dtype the RTS recursion runs in: float64 for
    float32 inputs (broadcast covariances stay broadcast views). Why: the backward recursion
    :math:`\Sigma^s_t = L_t + G_t\Sigma^s_{t+1}G_t^\top` multiplies the rounding errors of
    :math:`\Sigma^s_{t+1}` by :math:`G_t` twice per step, and with a process noise far below
    the filtered variance (``Q`` ~ 1e-12, ``R`` ~ 1e12) :math:`G_t \approx F^{-1}` is expanding:
    in float32 the smoothed variances came out negative (issue 24); in float64 they do not,
    and the result is rounded to float32 once. Returns ``(post.mean, post.cov, nxt.mean,
    nxt.cov, F, Q)``."""
    if F.dtype != torch.float32:
        return post.mean, post.cov, nxt.mean, nxt.cov, F, Q
    up = lambda x, k: compact(x, k).double().expand(x.shape)  # noqa: E731
    return up(post.mean, 2), up(post.cov, 3), up(nxt.mean, 2), up(nxt.cov, 3), F.double(), Q.double()


def compact(x: Tensor, k: int) -> Tensor:
    """Collapse leading dimensions of ``x`` that are broadcast views (stride 0) to size 1,
    keeping the last ``k`` dimensions; the result broadcasts back to ``x``'s shape."""
    for d in range(x.ndim - k):
        if x.stride(d) == 0 and x.shape[d] > 1:
            x = x.narrow(d, 0, 1)
    return x

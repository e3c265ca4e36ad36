r"""The fast backend of :func:`pgm_wm.kalman.kalman_filter` and of :func:`pgm_wm.kalman.rts_smoother`
(Chapter 1): the same numbers as the book's reference loops (tested in float32 and float64),
with fewer tensor operations per step.

* Shared covariances: with unbatched parameters and the same mask (or none) for every sequence,
  one covariance sequence (Eqs. kf-update, kf-joseph, kf-predict) serves the whole batch; without
  a mask and a gradient it stops at its bitwise steady state. The means are then the linear
  recursion :math:`\mu^-_{t+1} = F(I - K_tH)\mu^-_t + FK_ty_t + Bu_t`, one small GEMM per step,
  and posteriors and log-likelihoods (Eq. kf-loglik) follow for all steps at once.
* A covariance per sequence: batch-last storage ("structure of arrays"), every map linear in
  the covariance one GEMM with a constant matrix, closed-form 2×2 inverses, preallocated outputs.
* The smoother with a covariance per sequence: gains and Joseph-form conditional covariances for
  blocks of steps at once by an elementwise Cholesky, then nine elementwise operations per step.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .filtering import FilterResult
from .gaussian import _LOG_2PI, Gaussian, _predict_cov, _sandwich_operator, _sym

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
    return _sym(A @ P @ A.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)), K, S_inv, logdet


def _filter_fast(
    y: Tensor, init: Gaussian, F: Tensor, H: Tensor, Q: Tensor, R: Tensor,
    mask: Tensor | None, offsets: Tensor | None, batch: torch.Size,
) -> FilterResult[Gaussian]:
    """The fast backend (module docstring) on validated inputs; see :func:`kalman_filter`."""
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

    if shared:
        # One covariance sequence for the whole batch (Riccati recursion, Eqs. kf-update/kf-predict).
        w = None if w_all is None else w_all[0]
        op_F = _sandwich_operator(F)
        steady_ok = mask is None and not needs_grad
        P, Ps, Ks, Sinvs, logdets, Pps = init.cov, [], [], [], [], []
        t_steady = T                           # first step from which everything repeats
        for t in range(T):
            Ps.append(P)
            step = _joseph_step(P, H, R, None if w is None else w[t], eye)
            nxt = _predict_cov(step[0], F, Q, op_F)
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

        if params_2d and m <= 2 and not needs_grad:
            bufs = _masked_loop(F, H, Q, R, flat(init.cov, 2), flat(init.mean, 1), y_tm, off_tm, w_all, T, n, m, N)
        step = _SequenceStep(F, H, Q, R, n, m, N) if params_2d else None
        P, mean = flat(init.cov, 2), flat(init.mean, 1)
        if step is not None:
            P, mean = P.permute(1, 2, 0).contiguous(), mean.T.contiguous()
            y_soa = y_tm.permute(0, 2, 1).contiguous()                             # (T, m, N)
            u_soa = None if off_tm is None else off_tm.permute(0, 2, 1).contiguous()
        done = bool(bufs.pop("_done", False))
        if not done:
            put("P", 0, P, soa=step is not None)
            put("M", 0, mean, soa=step is not None)
        for t in range(0 if not done else T, T):
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
                P = _sym(Fb @ Pp @ Fb.transpose(-1, -2)) + (flat(Q, 2) if Q.ndim > 2 else Q)
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
    ll = -0.5 * (quad + logdet_tm + m * _LOG_2PI)
    if w_all is not None:
        ll = torch.where(w_all.T > 0, ll, torch.zeros((), dtype=dt))
    ll = ll.T.reshape(*batch, T)

    def belief(mean_tm: Tensor, cov_tm: Tensor) -> Gaussian:
        mean = mean_tm.reshape(T, *batch, n).movedim(0, -2)
        cov = cov_tm.expand(T, N, n, n).reshape(T, *batch, n, n).movedim(0, -3) if cov_tm.shape[1] == N \
            else cov_tm.reshape(T, *([1] * len(batch)), n, n).movedim(0, -3).expand(*batch, T, n, n)
        return Gaussian(mean, cov)

    return FilterResult(belief(M[:T], cov_prior), belief(M_post, cov_post), belief(M[1:], cov_next), ll)


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


def _masked_loop(F: Tensor, H: Tensor, Q: Tensor, R: Tensor, P0: Tensor, mean0: Tensor, y_tm: Tensor,
                 off_tm: Tensor | None, w_all: Tensor | None, T: int, n: int, m: int, N: int) -> dict[str, Tensor]:
    r"""The per-sequence covariance path of :func:`_filter_fast` for unbatched ``F, H, Q, R``,
    ``m ≤ 2`` and no gradient, written for few tensor operations per step (about 19, each on
    the whole batch, with views of the preallocated outputs made before the loop):

    * one GEMM with a constant matrix maps :math:`\operatorname{vec}\Sigma^-_t` to
      :math:`H\Sigma^-_t`, :math:`S_t = H\Sigma^-_tH^\top + R` and the adjugate of :math:`S_t`
      (Eq. kf-update), so :math:`w_tS_t^{-1} = \operatorname{adj}(S_t)\,w_t/\det S_t`; the
      log-determinants are one ``log`` over all steps after the loop;
    * the Joseph form (Eq. kf-joseph) as :math:`M D M^\top` with :math:`M = [A\;K]`,
      :math:`D = \operatorname{diag}(\Sigma^-_t, R)`, :math:`A = I - KH`, stored transposed so
      every block is a contiguous slice of one buffer;
    * the prediction (Eq. kf-predict) one GEMM with :math:`F\otimes F` into the next slot.

    Returns the output buffers of :func:`_filter_fast` (batch last) with ``"_done"`` set."""
    dt, dev = F.dtype, F.device
    eye_n = torch.eye(n, dtype=dt, device=dev)
    nn_, nm, mm_ = n * n, n * m, m * m
    # rows: vec(H Σ) (m, n), vec(S) (m, m), vec(adj S) (m, m)
    to_HP = torch.einsum("ka,jb->kjab", H, eye_n).reshape(nm, nn_)             # (HΣ)_{kj} = Σ_a H_ka Σ_aj
    to_S = torch.einsum("ki,lj->klij", H, H).reshape(mm_, nn_)
    if m == 2:
        perm = torch.tensor([[0., 0, 0, 1], [0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]], dtype=dt, device=dev)
        to_adj, adj_bias = perm @ to_S, perm @ R.reshape(4)
    else:
        to_adj, adj_bias = torch.zeros(1, nn_, dtype=dt, device=dev), torch.ones(1, dtype=dt, device=dev)
    lin = torch.cat([to_HP, to_S, to_adj]).contiguous()
    lin_bias = torch.cat([torch.zeros(nm, dtype=dt, device=dev), R.reshape(mm_), adj_bias])[:, None].contiguous()
    # vec(Kᵀ) (m, n) -> vec(Aᵀ) = vec(I − Hᵀ Kᵀ) and vec(R Kᵀ)
    to_At = torch.einsum("ak,jl->ajkl", H.T, eye_n).reshape(nn_, nm)            # (HᵀKᵀ)_{aj} = Σ_k H_ka Kᵀ_kj
    to_RKt = torch.einsum("lk,ij->likj", R, eye_n).reshape(nm, nm)               # (RKᵀ)_{lj} = Σ_k R_lk Kᵀ_kj
    to_FPF = torch.einsum("ki,lj->klij", F, F).reshape(nn_, nn_)
    eye_vec, Qv = eye_n.reshape(nn_, 1), Q.reshape(nn_, 1)

    bufs = dict(P=torch.empty(T + 1, n, n, N, dtype=dt, device=dev), Pp=torch.empty(T, n, n, N, dtype=dt, device=dev),
                M=torch.empty(T + 1, n, N, dtype=dt, device=dev), Mp=torch.empty(T, n, N, dtype=dt, device=dev),
                Sinv=torch.empty(T, m, m, N, dtype=dt, device=dev), e=torch.empty(T, m, N, dtype=dt, device=dev))
    det = torch.empty(T, N, dtype=dt, device=dev)
    bufs["P"][0].copy_(P0.permute(1, 2, 0))
    bufs["M"][0].copy_(mean0.T)
    Pv = bufs["P"].view(T + 1, nn_, N).unbind(0)
    P4 = bufs["P"].unbind(0)
    Ppv = bufs["Pp"].view(T, nn_, N).unbind(0)
    Pp4 = bufs["Pp"].unbind(0)
    Ms, Mps, es = bufs["M"].unbind(0), bufs["Mp"].unbind(0), bufs["e"].unbind(0)
    Sinvs, dets = bufs["Sinv"].view(T, mm_, N).unbind(0), det.unbind(0)
    y_s = y_tm.permute(0, 2, 1).contiguous().unbind(0)                             # (m, N) each
    u_s = None if off_tm is None else off_tm.permute(0, 2, 1).contiguous().unbind(0)
    w_s = (torch.ones(T, N, dtype=dt, device=dev) if w_all is None else w_all.T.contiguous()).unbind(0)
    MDt = torch.empty(n + m, n, N, dtype=dt, device=dev)      # [ (AΣ)ᵀ ; (KR)ᵀ ] = [ΣAᵀ ; RKᵀ]
    Mt = torch.empty(n + m, n, N, dtype=dt, device=dev)       # [ Aᵀ ; Kᵀ ]
    At_v, Kt = Mt[:n].view(nn_, N), Mt[n:]
    PAt, RKt_v = MDt[:n], MDt[n:].view(nm, N)
    Mt_b, MDt_b, At_b = Mt.unsqueeze(1), MDt.unsqueeze(2), Mt[:n].unsqueeze(0)
    Kt_v = Kt.view(nm, N)
    lin_out = torch.empty(nm + 2 * mm_, N, dtype=dt, device=dev)
    HP = lin_out[:nm].view(1, m, n, N)
    adj = lin_out[nm + mm_:]
    scale = torch.empty(1, N, dtype=dt, device=dev)
    tmp_k = torch.empty(m, m, n, N, dtype=dt, device=dev)
    tmp_p = torch.empty(n, n, n, N, dtype=dt, device=dev)
    tmp_j = torch.empty(n + m, n, n, N, dtype=dt, device=dev)
    tmp_m = torch.empty(m, n, N, dtype=dt, device=dev)
    gain = torch.empty(n, N, dtype=dt, device=dev)
    steps = _scripted(_masked_steps)
    u_list = list(u_s) if u_s is not None else []
    steps(lin_bias, lin, list(Pv), list(P4), list(dets), lin_out, list(w_s), scale, adj, list(Sinvs), tmp_k, HP, Kt,
          eye_vec, to_At, Kt_v, At_v, to_RKt, RKt_v, tmp_p, At_b, PAt, MDt_b, Mt_b, tmp_j, list(Pp4), list(y_s), H,
          list(Ms), list(es), tmp_m, gain, list(Mps), Qv, to_FPF, list(Ppv), F, u_list, nm, m, N, T)
    bufs["ld"] = det.log_()
    bufs["_done"] = torch.ones(())
    return bufs


def _masked_steps(lin_bias: Tensor, lin: Tensor, Pv: list[Tensor], P4: list[Tensor], dets: list[Tensor],
                  lin_out: Tensor, w_s: list[Tensor], scale: Tensor, adj: Tensor, Sinvs: list[Tensor], tmp_k: Tensor,
                  HP: Tensor, Kt: Tensor, eye_vec: Tensor, to_At: Tensor, Kt_v: Tensor, At_v: Tensor, to_RKt: Tensor,
                  RKt_v: Tensor, tmp_p: Tensor, At_b: Tensor, PAt: Tensor, MDt_b: Tensor, Mt_b: Tensor, tmp_j: Tensor,
                  Pp4: list[Tensor], y_s: list[Tensor], H: Tensor, Ms: list[Tensor], es: list[Tensor], tmp_m: Tensor,
                  gain: Tensor, Mps: list[Tensor], Qv: Tensor, to_FPF: Tensor, Ppv: list[Tensor], F: Tensor,
                  u_s: list[Tensor], nm: int, m: int, N: int, T: int) -> None:
    """The loop of :func:`_masked_loop` (see there; every argument a constant, a scratch buffer or
    the list of per-step views of an output). Run compiled by TorchScript (:func:`_scripted`),
    which removes most of the interpreter's cost per tensor operation; plain Python otherwise."""
    mm_ = m * m
    S_a = lin_out[nm]
    S_b = lin_out[nm + 1]
    S_d = lin_out[nm + mm_ - 1]
    scale0 = scale[0]
    for t in range(T):
        torch.addmm(lin_bias, lin, Pv[t], out=lin_out)                                # HΣ, S, adj S
        d_t = dets[t]
        if m == 2:
            torch.mul(S_a, S_d, out=d_t)
            d_t.addcmul_(S_b, S_b, value=-1.0)
        else:
            d_t.copy_(S_a)
        torch.div(w_s[t], d_t, out=scale0)
        Sinv_t = torch.mul(adj, scale, out=Sinvs[t])                                   # w S⁻¹
        torch.mul(Sinv_t.view([m, m, 1, N]), HP, out=tmp_k)
        torch.sum(tmp_k, [1], out=Kt)                                                  # Kᵀ = w S⁻¹ H Σ
        torch.addmm(eye_vec, to_At, Kt_v, alpha=-1.0, out=At_v)                        # Aᵀ = I − Hᵀ Kᵀ
        torch.mm(to_RKt, Kt_v, out=RKt_v)                                              # R Kᵀ
        torch.mul(P4[t].unsqueeze(2), At_b, out=tmp_p)
        torch.sum(tmp_p, [1], out=PAt)                                                 # Σ Aᵀ
        torch.mul(MDt_b, Mt_b, out=tmp_j)
        torch.sum(tmp_j, [0], out=Pp4[t])                                              # A Σ Aᵀ + K R Kᵀ
        e_t = torch.addmm(y_s[t], H, Ms[t], alpha=-1.0, out=es[t])                     # y − H μ⁻
        torch.mul(Kt, e_t.unsqueeze(1), out=tmp_m)
        torch.sum(tmp_m, [0], out=gain)
        torch.add(Ms[t], gain, out=Mps[t])                                             # μ⁺ = μ⁻ + K e
        torch.addmm(Qv, to_FPF, Ppv[t], out=Pv[t + 1])                                 # F Σ⁺ Fᵀ + Q
        if len(u_s) == 0:
            torch.mm(F, Mps[t], out=Ms[t + 1])
        else:
            torch.addmm(u_s[t], F, Mps[t], out=Ms[t + 1])


def _rts_steps(Ms: list[Tensor], Cs: list[Tensor], Gs: list[Tensor], Ls: list[Tensor], mfs: list[Tensor],
               mps: list[Tensor], d: Tensor, gd: Tensor, gC: Tensor, t3: Tensor, T: int) -> None:
    """The backward loop of :func:`_rts_per_sequence` (Eq. rts) on per-step views, batch last:
    μˢ_t = μ⁺_t + G_t(μˢ_{t+1} − μ⁻_{t+1}), Σˢ_t = L_t + G_t Σˢ_{t+1} G_tᵀ; compiled like
    :func:`_masked_steps`."""
    for t in range(T - 2, -1, -1):
        g = Gs[t]
        torch.sub(Ms[t + 1], mps[t], out=d)
        torch.mul(g, d, out=gd)
        torch.add(mfs[t], gd.sum(1), out=Ms[t])
        torch.mul(g.unsqueeze(2), Cs[t + 1].unsqueeze(0), out=t3)
        torch.sum(t3, [1], out=gC)                                                     # G Σˢ_{t+1}
        torch.mul(gC.unsqueeze(1), g.unsqueeze(0), out=t3)
        torch.add(Ls[t], t3.sum(2), out=Cs[t])


_SCRIPTED: dict = {}


def _scripted(fn):
    """``fn`` compiled by TorchScript once per process (``fn`` itself if compiling fails)."""
    if fn.__name__ not in _SCRIPTED:
        try:
            _SCRIPTED[fn.__name__] = torch.jit.script(fn)
        except Exception:                                   # noqa: BLE001 - any failure: run uncompiled
            _SCRIPTED[fn.__name__] = fn
    return _SCRIPTED[fn.__name__]


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


def _cholesky_soa(A: Tensor) -> Tensor:
    """Lower Cholesky factors of batch-last SPD matrices ``A: (n, n, B)`` by the column
    algorithm, elementwise over the contiguous batch axis (no LAPACK call per matrix)."""
    n = A.shape[0]
    L = torch.zeros_like(A)
    for j in range(n):
        d = (A[j, j] - L[j, :j].square().sum(0)).sqrt()
        L[j, j] = d
        if j + 1 < n:
            L[j + 1:, j] = (A[j + 1:, j] - (L[j + 1:, :j] * L[j, :j].unsqueeze(0)).sum(1)) / d
    return L


def _cholesky_solve_soa(L: Tensor, Bm: Tensor) -> Tensor:
    """``(L Lᵀ)⁻¹ B`` for batch-last ``L: (n, n, B)`` and ``B: (n, r, B)``, by forward and back
    substitution elementwise over the batch axis."""
    n = L.shape[0]
    Z = torch.empty_like(Bm)
    for i in range(n):
        Z[i] = (Bm[i] - (L[i, :i].unsqueeze(1) * Z[:i]).sum(0)) / L[i, i]
    X = torch.empty_like(Bm)
    for i in range(n - 1, -1, -1):
        X[i] = (Z[i] - (L[i + 1:, i].unsqueeze(1) * X[i + 1:]).sum(0)) / L[i, i]
    return X


_RTS_BLOCK = 8192      # matrices per block of the smoother's gains (sized for the cache: 32768 was slower)


def _rts_per_sequence(post: Gaussian, nxt: Gaussian, F: Tensor, Q: Tensor) -> Gaussian:
    """:func:`rts_smoother` for a covariance per sequence and unbatched ``F, Q``, without a
    gradient: batch-last layout, gains and conditional covariances (Joseph form) for blocks of
    steps at once (about 32k matrices per block), then 9 elementwise operations per step backwards."""
    T, n = post.mean.shape[-2], post.dim
    batch = post.batch_shape[:-1]
    N = math.prod(batch)
    chunk = max(1, _RTS_BLOCK // N)

    def soa(x: Tensor, k: int) -> Tensor:        # (*batch, T, *event) -> (T, *event, N)
        x = x.expand(*batch, T, *x.shape[x.ndim - k:]).reshape(N, T, *x.shape[x.ndim - k:])
        return x.movedim(0, -1).contiguous()

    m_f, m_p, c_f, c_p = soa(post.mean, 1), soa(nxt.mean, 1), soa(post.cov, 2), soa(nxt.cov, 2)
    eye = torch.eye(n, dtype=F.dtype, device=F.device)
    to_GF = torch.einsum("ab,kj->ajbk", eye, F).reshape(n * n, n * n)     # vec(G) -> vec(G F)
    G = torch.empty(T - 1, n, n, N, dtype=F.dtype, device=F.device)
    Lc = torch.empty_like(G)
    for s in range(0, T - 1, chunk):
        e = min(s + chunk, T - 1)
        k = e - s
        Pf = c_f[s:e].movedim(0, -2).reshape(n, n, k * N)                  # Σ⁺_t
        Pp = c_p[s:e].movedim(0, -2).reshape(n, n, k * N)                  # Σ⁻_{t+1}
        FP = (F @ Pf.reshape(n, n * k * N)).view(n, n, k * N)                 # F Σ⁺
        X = _cholesky_solve_soa(_cholesky_soa(Pp), FP)                     # (Σ⁻)⁻¹ F Σ⁺ = Gᵀ
        Gs = X.transpose(0, 1)
        A = (eye.reshape(n * n, 1) - to_GF @ Gs.reshape(n * n, k * N)).view(n, n, k * N)   # I − G F
        GQ = _mm(Gs, Q.unsqueeze(-1))                                         # G Q
        Ls = _mm_t(_mm(A, Pf), A) + _mm_t(GQ, Gs)
        G[s:e] = Gs.reshape(n, n, k, N).movedim(2, 0)
        Lc[s:e] = Ls.reshape(n, n, k, N).movedim(2, 0)
    M = torch.empty(T, n, N, dtype=F.dtype, device=F.device)
    C = torch.empty(T, n, n, N, dtype=F.dtype, device=F.device)
    M[T - 1], C[T - 1] = m_f[T - 1], c_f[T - 1]
    # views and scratch made once: the loop is 9 tensor operations per step, no allocation
    Ms, Cs, Gs_, Ls_, mfs, mps = M.unbind(0), C.unbind(0), G.unbind(0), Lc.unbind(0), m_f.unbind(0), m_p.unbind(0)
    d = torch.empty(n, N, dtype=F.dtype, device=F.device)
    gd = torch.empty(n, n, N, dtype=F.dtype, device=F.device)
    gC = torch.empty(n, n, N, dtype=F.dtype, device=F.device)
    t3 = torch.empty(n, n, n, N, dtype=F.dtype, device=F.device)
    _scripted(_rts_steps)(list(Ms), list(Cs), list(Gs_), list(Ls_), list(mfs), list(mps), d, gd, gC, t3, T)
    _sym_soa_(C)
    mean = M.movedim(-1, 0).reshape(*batch, T, n)
    cov = C.movedim(-1, 0).reshape(*batch, T, n, n)
    return Gaussian(mean, cov)


def _sym_soa_(C: Tensor) -> None:
    """Replace batch-last matrices ``C: (T, n, n, N)`` by their symmetric part ``(C + Cᵀ)/2`` in
    place, one off-diagonal pair at a time (no full-size temporaries)."""
    n = C.shape[1]
    for i in range(n):
        for j in range(i + 1, n):
            avg = torch.add(C[:, i, j], C[:, j, i]).mul_(0.5)
            C[:, i, j] = avg
            C[:, j, i] = avg


def _compact(x: Tensor, k: int) -> Tensor:
    """Collapse leading dimensions of ``x`` that are broadcast views (stride 0) to size 1,
    keeping the last ``k`` dimensions; the result broadcasts back to ``x``'s shape."""
    for d in range(x.ndim - k):
        if x.stride(d) == 0 and x.shape[d] > 1:
            x = x.narrow(d, 0, 1)
    return x

r"""The tensor backend of :func:`pgm_wm.factorized.diagonal_factorized_filter` (Chapters 3 and 6).

The loop of the diagonal factorized filter on the packed state (``z = [z^u, z^l]``,
``s = [σ^u, σ^s, σ^l]``, batch flattened): Eq. (rkn-update) elementwise in product form,
Eq. (rkn-predict) as two GEMMs with constant matrices (:math:`z^- = z^+A^\top + b`,
:math:`s^- = s^+C_s + v`), about 12 tensor operations per step. Plain Python (differentiable to
any order, works under ``torch.func`` transforms and on every device). It is also what the
compiled loop's autograd function (:mod:`pgm_wm._backends.factorized_jit`) runs to
differentiate its backward pass when second derivatives are asked for.
"""

from __future__ import annotations

import torch
from torch import Tensor


def variance_map(coef: Tensor) -> Tensor:
    r"""The predict map of the packed variances as one ``(3m, 3m)`` matrix :math:`C_s`
    (``s⁻ = s⁺ C_s``) from ``coef: (3, 3, m)`` (``coef[k, l]``: coefficient of :math:`s^+_k` in
    :math:`s^-_l`, lane by lane)."""
    m = coef.shape[-1]
    return torch.diag_embed(coef).permute(0, 2, 1, 3).reshape(3 * m, 3 * m)


def diagonal_steps(z0: Tensor, s0: Tensor, w: Tensor, r: Tensor, mu: Tensor | None, in_z: Tensor | None,
                   in_s: Tensor, A: Tensor, coef: Tensor) -> tuple[Tensor, ...]:
    """The diagonal factorized filter as tensor operations, on the arguments of
    :func:`pgm_wm._backends.factorized_jit.diagonal_filter_jit` (``in_z`` may be ``None``: no
    input mean). Returns ``(Z, S, Zp, Sp, z_last, s_last)``: priors ``(N, T, 2m)``,
    ``(N, T, 3m)``, posteriors, and the last prediction."""
    N, T, m = w.shape
    At, Cs = A.T, variance_map(coef)
    z, s = z0, s0
    zs, ss_, zps, sps = [], [], [], []
    for t in range(T):
        su, ss, sl = s.reshape(N, 3, m).unbind(1)
        zu = z[:, :m]
        s2 = s.reshape(N, 3, m)[:, :2]                                  # [σ^u, σ^s]
        if mu is None:
            g = (su + r[:, t]).reciprocal()
            ratio = r[:, t] * g
        else:
            g = torch.div(mu[:, t], su + r[:, t])
            ratio = torch.addcmul(1.0 - mu[:, t], r[:, t], g)        # σ^obs ⊘ S, exactly 1 where missing
        ge = g * (w[:, t] - zu)
        z_p = torch.addcmul(z.reshape(N, 2, m), s2, ge.unsqueeze(1)).reshape(N, 2 * m)   # z + [σ^u; σ^s] g (w − z^u)
        s_p = torch.cat([(s2 * ratio.unsqueeze(1)).reshape(N, 2 * m), torch.addcmul(sl, ss, ss * g, value=-1.0)], -1)
        zs.append(z)
        ss_.append(s)
        zps.append(z_p)
        sps.append(s_p)
        z = torch.mm(z_p, At) if in_z is None else torch.addmm(in_z[:, t], z_p, At)
        s = torch.addmm(in_s[:, t], s_p, Cs)
    Z, S, Zp, Sp = (torch.stack(x, 1) for x in (zs, ss_, zps, sps))
    return Z, S, Zp, Sp, z, s

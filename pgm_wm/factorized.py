r"""The factorized Gaussian belief of the Recurrent Kalman Network (Chapter 3).

The latent state :math:`z = [z^u; z^l] \in \mathbb R^{2m}` has an *upper* (observed) half and a
*lower* (memory) half; the observation model is :math:`H = [I_m, 0]`. The covariance is kept in
the factorized form (Eq. rkn-factorized-cov)

.. math:: \Sigma = \begin{bmatrix}\operatorname{diag}(\sigma^u) & \operatorname{diag}(\sigma^s)\\
                  \operatorname{diag}(\sigma^s) & \operatorname{diag}(\sigma^l)\end{bmatrix},

three vectors of length :math:`m` instead of a :math:`2m\times 2m` matrix. Code names:
``var_upper`` = :math:`\sigma^u`, ``var_lower`` = :math:`\sigma^l`, ``cov_side`` = :math:`\sigma^s`.

What is exact and what is an approximation:

* :func:`factorized_update` is **exact**: for a belief of this form and :math:`H=[I,0]` with a
  diagonal observation variance, the dense Kalman update returns a belief of the same form, and
  the scalar formulas below equal it to rounding error.
* :func:`block_inverse` is **exact** (covariance :math:`\leftrightarrow` precision by scalars).
* :func:`factorized_predict` is **exact when the four transition blocks are diagonal**. For band
  (or full) blocks, :math:`A\Sigma A^\top` has full blocks; we keep their exact diagonals and drop
  the off-diagonal entries inside each block. This is the RKN's approximation.
* :func:`linear_cause` maps an independent Gaussian cause with diagonal covariance through a
  matrix :math:`C`; again the block diagonals are exact, off-diagonals inside blocks are dropped.

The filter over a whole sequence (a constant transition, causes known before the loop) comes in
two versions with one signature: :func:`factorized_filter`, the readable reference (the book's
loop "update, then predict", :func:`pgm_wm.filtering.filter_loop`), and
:func:`diagonal_factorized_filter`, its elementwise fast path for diagonal blocks (MTS3's fast
level), tested equal to it in float32 and float64.

The belief containers live in :mod:`pgm_wm.beliefs` (``FactorizedBelief`` and ``DiagGaussian`` are
re-exported here). Step argument order everywhere: ``(prior, model..., observation, mask, *,
validate)``.
"""

from __future__ import annotations

from typing import Sequence

from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import (check_finite, check_last_dims, check_mask, check_nonnegative, check_positive, check_same_dtype,
                      check_tensor)
from .beliefs import DiagGaussian, FactorizedBelief, block_inverse
from .filtering import FilterResult, filter_loop
from ._backends import Backend, select
from ._backends.factorized_fast import diagonal_steps
from ._backends.factorized_jit import diagonal_filter_jit

__all__ = [
    "FactorizedBelief",
    "DiagGaussian",
    "block_inverse",
    "factorized_update",
    "update_unchecked",
    "as_observation",
    "factorized_predict",
    "factorized_predict_from_matrix",
    "linear_cause",
    "known_input",
    "factorized_filter",
    "diagonal_factorized_filter",
]


def as_observation(name: str, observation: DiagGaussian | Tensor, rest: tuple, mask: Tensor | None
                 ) -> tuple[DiagGaussian, Tensor | None]:
    """``(observation, mask)`` from ``DiagGaussian(w, w_var), mask`` or the older positional form
    ``w, w_var, mask`` (the argument convention of every factorized filter and update)."""
    if isinstance(observation, DiagGaussian):
        if len(rest) > 1:
            raise ValueError(f"{name}: unexpected extra positional arguments (pass causes=..., init=... by name)")
        return observation, (rest[0] if rest else mask)
    if isinstance(observation, Tensor) and rest and isinstance(rest[0], Tensor):  # legacy (w, w_var[, mask])
        if len(rest) > 2:
            raise ValueError(f"{name}: unexpected extra positional arguments (pass causes=..., init=... by name)")
        w_var = rest[0]
        check_tensor(f"{name}.mean", observation, 1)
        check_tensor(f"{name}.var", w_var, 1)
        if tuple(w_var.shape) != tuple(observation.shape):
            raise ValueError(f"{name}.var: expected the shape of {name}.mean {tuple(observation.shape)}, "
                             f"got {tuple(w_var.shape)}")
        return DiagGaussian(observation, w_var), (rest[1] if len(rest) > 1 else mask)
    raise ValueError(f"{name}: expected a DiagGaussian (w, w_var), got {type(observation).__name__}")


def factorized_update(
    prior: FactorizedBelief,
    observation: DiagGaussian,
    *args: Tensor | None,
    mask: Tensor | None = None,
    validate: bool = True,
) -> FactorizedBelief:
    r"""Exact Kalman update of a factorized belief with :math:`H = [I, 0]`, Eq. (rkn-update).

    With latent observation :math:`w` of variance :math:`\sigma^{obs}` (``observation =
    DiagGaussian(w, w_var)``) and :math:`S = \sigma^u + \sigma^{obs}` (elementwise), the Kalman
    gain is :math:`[\mathrm{diag}(\sigma^u\oslash S);\ \mathrm{diag}(\sigma^s\oslash S)]` and

    .. math::
        z^{u+} &= z^u + \sigma^u\odot(w - z^u)\oslash S, &
        z^{l+} &= z^l + \sigma^s\odot(w - z^u)\oslash S,\\
        \sigma^{u+} &= \sigma^u\odot\sigma^{obs}\oslash S, &
        \sigma^{s+} &= \sigma^s\odot\sigma^{obs}\oslash S, \qquad
        \sigma^{l+} = \sigma^l - \sigma^s\odot\sigma^s\oslash S.

    Exact: it equals the dense update :math:`\Sigma^+ = (I - KH)\Sigma^-` to rounding error.
    (The thesis prints :math:`\sigma^u\odot\sigma^u\oslash S` and :math:`\sigma^u\odot\sigma^s\oslash S`
    for the first two variances and :math:`\sigma^l` instead of :math:`\sigma^s` in the lower mean;
    those are typos — see the book's errata page.) :math:`\sigma^{u+}` and :math:`\sigma^{s+}` are
    computed in the product form above, which has no cancellation in floating point (the form
    :math:`\sigma^u(1 - \sigma^u/S)` loses all digits when :math:`\sigma^{obs}\ll\sigma^u`).

    A missing observation (``mask`` False) multiplies the gain by zero, so the posterior equals
    the prior exactly; ``w`` and ``w_var`` must still be finite there (any finite values).

    Call as ``factorized_update(prior, DiagGaussian(w, w_var), mask)``; the older form
    ``factorized_update(prior, w, w_var, mask)`` is still accepted.

    Args:
        prior: the belief before the update, batch ``(...)``.
        observation: ``DiagGaussian(w, w_var)``, each ``(..., m)``; ``w_var`` positive.
        mask: ``(...)`` bool, True = observed. Where False the posterior equals the prior.
        validate: check the prior belief (positive variances, positive-definite 2×2 blocks),
            ``w_var > 0`` and finite ``w`` (set False inside training loops to avoid a host
            sync); shapes are always checked.
    """
    if not isinstance(prior, FactorizedBelief):
        raise ValueError(f"prior: expected a FactorizedBelief, got {type(prior).__name__}")
    obs, mask = as_observation("observation", observation, args, mask)
    m = prior.latent_obs_dim
    check_last_dims("observation.mean", obs.mean, (m,))
    check_same_dtype(("prior.mean", "prior.var_upper", "prior.var_lower", "prior.cov_side", "observation.mean",
                      "observation.var"), (prior.mean, prior.var_upper, prior.var_lower, prior.cov_side, obs.mean,
                                           obs.var))
    batch = prior.mean.shape[:-1]
    try:
        full = torch.broadcast_shapes(batch, obs.mean.shape[:-1])
    except RuntimeError as err:
        raise ValueError(f"observation: batch shape {tuple(obs.mean.shape[:-1])} does not broadcast with the "
                         f"prior's {tuple(batch)}") from err
    if validate:
        prior.validate("prior")
        check_positive("observation.var", obs.var)
        check_finite("observation.mean", obs.mean)
    if mask is not None:
        mask = check_mask("mask", mask, tuple(full))
    return update_unchecked(prior, obs.mean, obs.var, mask)


def update_unchecked(prior: FactorizedBelief, w: Tensor, w_var: Tensor, mask: Tensor | None) -> FactorizedBelief:
    """Arithmetic of Eq. (rkn-update) without checks (see :func:`factorized_update`): for loops that
    checked their inputs once before the first step."""
    su, sl, ss = prior.var_upper, prior.var_lower, prior.cov_side
    inv_S = 1.0 / (su + w_var)
    if mask is None:
        ratio = w_var * inv_S  # σ^obs ⊘ S
    else:
        keep = mask.to(inv_S.dtype)[..., None]
        inv_S = inv_S * keep  # zero gain where the observation is missing
        ratio = w_var * inv_S + (1.0 - keep)  # = σ^obs ⊘ S where observed, exactly 1 where missing
    gain_u, gain_l = su * inv_S, ss * inv_S
    resid = w - prior.mean_upper
    mean = prior.mean + torch.cat([gain_u * resid, gain_l * resid], dim=-1)
    return FactorizedBelief(mean, su * ratio, sl - gain_l * ss, ss * ratio)


def known_input(b: Tensor) -> FactorizedBelief:
    """A known additive input ``b: (..., 2m)`` (e.g. a control term) as a zero-variance cause."""
    return FactorizedBelief.known(b)


def linear_cause(C: Tensor, cause: DiagGaussian, *legacy_var: Tensor) -> FactorizedBelief:
    r"""Push an independent cause :math:`u\sim\mathcal N(\mu, \mathrm{diag}(\sigma))` through
    :math:`C = [C^u; C^l]`, Eq. (gauss-marginal) restricted to block diagonals:

    .. math:: C\mu,\quad \sigma^u = (C^u\circ C^u)\sigma,\quad \sigma^l = (C^l\circ C^l)\sigma,\quad
              \sigma^s = (C^l\circ C^u)\sigma.

    Exact for the block diagonals of :math:`C\,\mathrm{diag}(\sigma)C^\top`; off-diagonals inside
    the blocks are dropped. Shapes: ``C: (..., 2m, k)``, ``cause = DiagGaussian(mean, var)`` with
    ``(..., k)`` (the older ``linear_cause(C, mean, var)`` is still accepted).
    """
    check_tensor("C", C, 2)
    if legacy_var:
        cause = DiagGaussian(cause, legacy_var[0])  # type: ignore[arg-type]
    if not isinstance(cause, DiagGaussian):
        raise ValueError(f"cause: expected a DiagGaussian, got {type(cause).__name__}")
    if C.shape[-2] % 2:
        raise ValueError(f"C: number of rows must be even (2m), got {C.shape[-2]}")
    k = C.shape[-1]
    check_last_dims("cause.mean", cause.mean, (k,))
    m = C.shape[-2] // 2
    Cu, Cl = C[..., :m, :], C[..., m:, :]
    mv = lambda M, v: (M @ v.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    var = cause.var
    return FactorizedBelief(mv(C, cause.mean), mv(Cu * Cu, var), mv(Cl * Cl, var), mv(Cl * Cu, var))


def factorized_predict(
    prior: FactorizedBelief,
    A11: Tensor,
    A12: Tensor,
    A21: Tensor,
    A22: Tensor,
    trans_var: Tensor,
    causes: Sequence[FactorizedBelief] = (),
    *,
    validate: bool = True,
) -> FactorizedBelief:
    r"""Predict step for a 2×2-block transition :math:`A = [[A_{11}, A_{12}], [A_{21}, A_{22}]]`,
    Eq. (rkn-predict), plus independent additive causes.

    Mean :math:`z^- = A z^+ + \sum_i \mu_i`. Covariance: the block diagonals of
    :math:`A\Sigma^+A^\top`, with ``∘`` the elementwise product of matrices,

    .. math::
        \sigma^{u-} &= (A_{11}\circ A_{11})\sigma^u + 2(A_{11}\circ A_{12})\sigma^s
                      + (A_{12}\circ A_{12})\sigma^l + q^u,\\
        \sigma^{l-} &= (A_{21}\circ A_{21})\sigma^u + 2(A_{21}\circ A_{22})\sigma^s
                      + (A_{22}\circ A_{22})\sigma^l + q^l,\\
        \sigma^{s-} &= (A_{21}\circ A_{11})\sigma^u + (A_{22}\circ A_{11} + A_{21}\circ A_{12})\sigma^s
                      + (A_{22}\circ A_{12})\sigma^l,

    plus the factorized covariances of the ``causes`` (e.g. :func:`known_input` for an action
    term :math:`b(a)`, :func:`linear_cause` for a latent task :math:`C l`). Exact when all blocks
    are diagonal; otherwise the off-diagonals inside each block are dropped.

    Shapes: ``A11..A22: (..., m, m)``; ``trans_var`` = :math:`[q^u; q^l]`: ``(..., 2m)``, >= 0.
    ``validate`` checks ``trans_var >= 0`` (set False inside training loops to avoid a host sync);
    shapes are always checked.
    """
    if not isinstance(prior, FactorizedBelief):
        raise ValueError(f"prior: expected a FactorizedBelief, got {type(prior).__name__}")
    m = prior.latent_obs_dim
    for name, blk in (("A11", A11), ("A12", A12), ("A21", A21), ("A22", A22)):
        check_last_dims(name, blk, (m, m))
    check_last_dims("trans_var", trans_var, (2 * m,))
    check_same_dtype(("prior.mean", "prior.var_upper", "prior.var_lower", "prior.cov_side", "A11", "A12", "A21",
                      "A22", "trans_var"), (prior.mean, prior.var_upper, prior.var_lower, prior.cov_side, A11, A12,
                                            A21, A22, trans_var))
    if validate:
        prior.validate("prior")
        check_nonnegative("trans_var", trans_var)
    A = torch.cat([torch.cat(torch.broadcast_tensors(A11, A12), dim=-1),
                   torch.cat(torch.broadcast_tensors(A21, A22), dim=-1)], dim=-2)
    return _predict_core(prior, A, trans_var, causes)


def factorized_predict_from_matrix(
    prior: FactorizedBelief,
    A: Tensor,
    trans_var: Tensor,
    causes: Sequence[FactorizedBelief] = (),
    *,
    validate: bool = True,
) -> FactorizedBelief:
    r""":func:`factorized_predict` with the transition given as one ``(..., 2m, 2m)`` matrix
    :math:`A = [[A_{11}, A_{12}], [A_{21}, A_{22}]]`; same result, same approximation, Eq. (rkn-predict).
    """
    if not isinstance(prior, FactorizedBelief):
        raise ValueError(f"prior: expected a FactorizedBelief, got {type(prior).__name__}")
    m = prior.latent_obs_dim
    check_last_dims("A", A, (2 * m, 2 * m))
    check_last_dims("trans_var", trans_var, (2 * m,))
    if validate:
        check_nonnegative("trans_var", trans_var)
    return _predict_core(prior, A, trans_var, causes)


def _predict_core(
    belief: FactorizedBelief, A: Tensor, trans_var: Tensor, causes: Sequence[FactorizedBelief]
) -> FactorizedBelief:
    r"""Arithmetic of Eq. (rkn-predict) without input checks; ``A: (..., 2m, 2m)``.

    Uses the structure of :math:`\Sigma` to form :math:`A\Sigma` with elementwise products
    (column block ``u`` of :math:`A\Sigma` is :math:`A_{:,u}\,\mathrm{diag}(\sigma^u) +
    A_{:,l}\,\mathrm{diag}(\sigma^s)`, column block ``l`` likewise), then reads off the needed
    diagonals :math:`(A\Sigma A^\top)_{rr} = \sum_c (A\Sigma)_{rc} A_{rc}` and
    :math:`(A\Sigma A^\top)_{m+i,\,i} = \sum_c (A\Sigma)_{m+i,c} A_{ic}`. This equals the
    block-product formulas in :func:`factorized_predict` term by term, in fewer tensor operations.
    """
    m = belief.latent_obs_dim
    mean = (A @ belief.mean.unsqueeze(-1)).squeeze(-1)
    Au, Al = A[..., :m], A[..., m:]  # columns acting on z^u and on z^l
    su, sl, ss = (x.unsqueeze(-2) for x in (belief.var_upper, belief.var_lower, belief.cov_side))
    AS = torch.cat([Au * su + Al * ss, Au * ss + Al * sl], dim=-1)  # A Σ
    var = (AS * A).sum(-1) + trans_var  # [σu⁻; σl⁻] = diag(A Σ Aᵀ) + [q^u; q^l]
    side = (AS[..., m:, :] * A[..., :m, :]).sum(-1)  # σs⁻ = diag of the (l, u) block
    out = FactorizedBelief(mean, var[..., :m], var[..., m:], side)
    for i, c in enumerate(causes):
        if not isinstance(c, FactorizedBelief) or c.latent_obs_dim != m:
            raise ValueError(f"causes[{i}]: expected a FactorizedBelief with m={m}")
        out = out + c
    return out



def _known_inputs(inputs: FactorizedBelief | None, T: int, m: int) -> FactorizedBelief | None:
    if inputs is None:
        return None
    if not isinstance(inputs, FactorizedBelief) or inputs.latent_obs_dim != m:
        raise ValueError(f"inputs: expected a FactorizedBelief with m={m} and a time axis (..., T, 2m)")
    if inputs.mean.ndim < 2 or inputs.mean.shape[-2] != T:
        raise ValueError(f"inputs: expected a time axis of length {T} before the event axis, got "
                         f"mean shape {tuple(inputs.mean.shape)}")
    return inputs


def _check_filter_args(prior: FactorizedBelief, A: Tensor, trans_var: Tensor, observation: DiagGaussian,
                       mask: Tensor | None, inputs: FactorizedBelief | None, validate: bool
                       ) -> tuple[Tensor | None, FactorizedBelief | None]:
    if not isinstance(prior, FactorizedBelief):
        raise ValueError(f"prior: expected a FactorizedBelief, got {type(prior).__name__}")
    if not isinstance(observation, DiagGaussian):
        raise ValueError(f"observation: expected a DiagGaussian (w, w_var), got {type(observation).__name__}")
    m = prior.latent_obs_dim
    check_last_dims("A", A, (2 * m, 2 * m))
    check_last_dims("trans_var", trans_var, (2 * m,))
    check_last_dims("observation.mean", observation.mean, (None, m))
    T = observation.mean.shape[-2]
    if T == 0:
        raise ValueError("observation: need at least one time step, got T = 0")
    check_same_dtype(("prior.mean", "prior.var_upper", "prior.var_lower", "prior.cov_side", "A", "trans_var",
                      "observation.mean", "observation.var"), (prior.mean, prior.var_upper, prior.var_lower,
                                                               prior.cov_side, A, trans_var, observation.mean,
                                                               observation.var))
    if mask is not None:
        mask = check_mask("mask", mask, tuple(observation.mean.shape[:-1]))
    if validate:
        prior.validate("prior")
        check_nonnegative("trans_var", trans_var)
        check_positive("observation.var", observation.var)
        check_finite("observation.mean", observation.mean)
    return mask, _known_inputs(inputs, T, m)


def factorized_filter(
    prior: FactorizedBelief,
    A: Tensor,
    trans_var: Tensor,
    observation: DiagGaussian,
    mask: Tensor | None = None,
    inputs: FactorizedBelief | None = None,
    *,
    validate: bool = True,
) -> FilterResult[FactorizedBelief]:
    r"""The factorized filter (the RKN's loop with a constant transition), reference version:
    :func:`pgm_wm.filtering.filter_loop` with :func:`factorized_update` (Eq. rkn-update) and
    :func:`factorized_predict_from_matrix` (Eq. rkn-predict), the known causes of step ``t``
    (``inputs.at(t)``: an action term, a task cause, ...) added in its predict step.

    Args:
        prior: belief of the first step, batch ``(...)``.
        A: constant transition ``(2m, 2m)`` (or ``(..., 2m, 2m)``); trans_var: ``(2m,)``, >= 0.
        observation: ``DiagGaussian(w, w_var)`` with ``(..., T, m)``.
        mask: ``(..., T)`` bool, True = observed.
        inputs: the sum of all causes known before the loop, a :class:`FactorizedBelief` with
            ``mean: (..., T, 2m)`` (``None``: no input).
    """
    mask, inputs = _check_filter_args(prior, A, trans_var, observation, mask, inputs, validate)

    def predict(post: FactorizedBelief, t: int) -> FactorizedBelief:
        causes = () if inputs is None else (inputs.at(t),)
        return _predict_core(post, A, trans_var, causes)

    update = lambda b, y, m_t: update_unchecked(b, y.mean, y.var, m_t)  # noqa: E731
    return filter_loop(prior, update, predict, observation, mask)


@dataclass(frozen=True)
class _DiagonalProblem:
    """The inputs of a constant transition with diagonal blocks, checked and flattened to ``N``
    sequences (see :func:`diagonal_factorized_filter`)."""

    batch: torch.Size
    N: int
    T: int
    m: int
    z0: Tensor                   # (N, 2m): [z^u, z^l]
    s0: Tensor                   # (N, 3m): [σ^u, σ^s, σ^l]
    a: tuple[Tensor, ...]        # diagonals of A11, A12, A21, A22, each (m,)
    coef: Tensor                 # (3, 3, m): coefficient of s⁺_k in s⁻_l, per lane
    w: Tensor                    # (N, T, m)
    r: Tensor                    # (N, T, m)
    mu: Tensor | None            # (N, T, m) 1 = observed, or None
    in_z: Tensor | None          # (N, T, 2m) input means, or None
    in_s: Tensor                 # (N, T, 3m) input variances plus q

    def packed(self, Z: Tensor, S: Tensor) -> FactorizedBelief:
        """A belief from packed ``Z: (N, T, 2m)``, ``S: (N, T, 3m)``, batch restored."""
        m = self.m
        Z, S = Z.reshape(*self.batch, self.T, 2 * m), S.reshape(*self.batch, self.T, 3 * m)
        return FactorizedBelief(Z, S[..., :m], S[..., 2 * m:], S[..., m:2 * m])


def _diagonal_problem(prior: FactorizedBelief, A: Tensor, trans_var: Tensor, observation: DiagGaussian,
                      mask: Tensor | None, inputs: FactorizedBelief | None, validate: bool) -> _DiagonalProblem:
    """Check the arguments of :func:`diagonal_factorized_filter` (``A`` one ``(2m, 2m)`` matrix
    with diagonal blocks) and flatten them."""
    mask, inputs = _check_filter_args(prior, A, trans_var, observation, mask, inputs, validate)
    m = prior.latent_obs_dim
    if A.ndim != 2:
        raise ValueError(f"A: the diagonal fast path needs one constant (2m, 2m) matrix, got {tuple(A.shape)}")
    blocks = [A[:m, :m], A[:m, m:], A[m:, :m], A[m:, m:]]
    if validate:
        off = ~torch.eye(m, dtype=torch.bool, device=A.device)
        if any(bool((blk[off] != 0).any()) for blk in blocks):
            raise ValueError("A: the diagonal fast path needs diagonal m x m blocks (use factorized_filter)")
    a11, a12, a21, a22 = (torch.diagonal(blk) for blk in blocks)
    w, w_var = observation.mean, observation.var
    T = w.shape[-2]
    batch = torch.broadcast_shapes(prior.mean.shape[:-1], w.shape[:-2])
    if mask is not None:
        batch = torch.broadcast_shapes(batch, mask.shape[:-1])
    if inputs is not None:
        batch = torch.broadcast_shapes(batch, inputs.mean.shape[:-2])
    N = 1
    for b in batch:
        N *= b
    z = prior.mean.expand(*batch, 2 * m).reshape(N, 2 * m)
    s = torch.cat([prior.var_upper, prior.cov_side, prior.var_lower], -1).expand(*batch, 3 * m).reshape(N, 3 * m)
    # Eq. (rkn-predict) for diagonal blocks: coef[k, l] is the coefficient of s⁺_k in s⁻_l
    coef = torch.stack([torch.stack([a11 * a11, a21 * a11, a21 * a21]),                        # from σ^u
                        torch.stack([2.0 * a11 * a12, a22 * a11 + a21 * a12, 2.0 * a21 * a22]),  # from σ^s
                        torch.stack([a12 * a12, a22 * a12, a22 * a22])])                         # from σ^l
    q = torch.cat([trans_var[..., :m], torch.zeros_like(trans_var[..., :m]), trans_var[..., m:]], -1)
    full = lambda x, k: x.expand(*batch, T, k).reshape(N, T, k)  # noqa: E731
    in_s = full(q, 3 * m) if inputs is None else full(
        torch.cat([inputs.var_upper, inputs.cov_side, inputs.var_lower], -1) + q, 3 * m)
    return _DiagonalProblem(
        batch, N, T, m, z, s, (a11, a12, a21, a22), coef, full(w, m), full(w_var, m),
        None if mask is None else full(mask.to(w.dtype).unsqueeze(-1), m),
        None if inputs is None else full(inputs.mean, 2 * m), in_s)


def diagonal_factorized_filter(
    prior: FactorizedBelief,
    A: Tensor,
    trans_var: Tensor,
    observation: DiagGaussian,
    mask: Tensor | None = None,
    inputs: FactorizedBelief | None = None,
    *,
    validate: bool = True,
    backend: Backend = "auto",
) -> FilterResult[FactorizedBelief]:
    r"""Fast path of :func:`factorized_filter` (same signature, same result) for a constant
    transition whose four :math:`m\times m` blocks are **diagonal** (the MTS3 fast level), written
    elementwise on the two halves: about 3x fewer tensor operations per step.

    With :math:`a_{ij}` the diagonals of the blocks :math:`A_{ij}` and
    :math:`g = m_t\oslash(\sigma^u + \sigma^{obs})` (:math:`m_t\in\{0, 1\}` the mask), the update
    is Eq. (rkn-update) in product form (:math:`r = \sigma^{obs}\odot g + 1 - m_t` equals
    :math:`\sigma^{obs}\oslash S` where observed and 1 where not: no cancellation),

    .. math:: \begin{aligned}
              z^{u+} &= z^u + \sigma^u\odot g\odot(w - z^u), &
              z^{l+} &= z^l + \sigma^s\odot g\odot(w - z^u),\\
              \sigma^{u+} &= \sigma^u\odot r,\quad \sigma^{s+} = \sigma^s\odot r, &
              \sigma^{l+} &= \sigma^l - \sigma^s\odot\sigma^s\odot g,
              \end{aligned}

    and the predict is Eq. (rkn-predict), exact for diagonal blocks:
    :math:`\sigma^{u-} = a_{11}^2\sigma^u + 2a_{11}a_{12}\sigma^s + a_{12}^2\sigma^l + q^u`, and
    likewise for :math:`\sigma^{l-}, \sigma^{s-}`, plus ``inputs.at(t)``.
    ``validate`` also checks that the blocks of ``A`` are diagonal.

    ``backend`` (the table of :mod:`pgm_wm._backends`): ``"compiled"``, the loop compiled lane by
    lane with a hand-written backward pass (:mod:`pgm_wm._backends.factorized_jit`; second
    derivatives, ``create_graph=True``, through the tensor path); ``"tensor"``, tensor operations
    on the packed state (``z = [z^u, z^l]``, ``s = [σ^u, σ^s, σ^l]``, batch flattened), about 12
    per step (:mod:`pgm_wm._backends.factorized_fast`), differentiable to any order, any device,
    ``torch.func`` transforms; ``"reference"``, :func:`factorized_filter`; ``"parallel"``,
    :func:`parallel_factorized_filter`; ``"auto"`` (or ``"fast"``): compiled for CPU float
    tensors without a ``torch.func`` transform where numba is installed and ``PGM_WM_JIT`` is
    not ``0``, tensor otherwise. All are tested equal to :func:`factorized_filter`, values and
    gradients, in float32 and float64.
    """
    which = select("diagonal_factorized_filter", observation.mean, observation.var, A, trans_var, prior.mean,
                   backend=backend, masked=mask is not None)
    if which == "reference":
        return factorized_filter(prior, A, trans_var, observation, mask, inputs, validate=validate)
    if which == "parallel":
        return parallel_factorized_filter(prior, A, trans_var, observation, mask, inputs, validate=validate)
    d = _diagonal_problem(prior, A, trans_var, observation, mask, inputs, validate)
    if which == "compiled":          # compiled loop with its own backward pass
        in_z = torch.zeros(d.N, d.T, 2 * d.m, dtype=d.z0.dtype, device=d.z0.device) if d.in_z is None else d.in_z
        Z, S, Zp, Sp, z_last, s_last = diagonal_filter_jit(d.z0, d.s0, d.w, d.r, d.mu, in_z, d.in_s, A, d.coef)
    else:
        Z, S, Zp, Sp, z_last, s_last = diagonal_steps(d.z0, d.s0, d.w, d.r, d.mu, d.in_z, d.in_s, A, d.coef)
    return FilterResult(d.packed(Z, S), d.packed(Zp, Sp),
                        d.packed(torch.cat([Z[:, 1:], z_last[:, None]], 1), torch.cat([S[:, 1:], s_last[:, None]], 1)))


def parallel_factorized_filter(
    prior: FactorizedBelief,
    A: Tensor,
    trans_var: Tensor,
    observation: DiagGaussian,
    mask: Tensor | None = None,
    inputs: FactorizedBelief | None = None,
    *,
    validate: bool = True,
) -> FilterResult[FactorizedBelief]:
    r""":func:`diagonal_factorized_filter` (same signature, same result) by associative scan:
    :math:`O(\log T)` sequential depth instead of :math:`T` steps, differentiable.

    With diagonal blocks, latent dimension :math:`i` of a sequence (a "lane") is a Kalman filter
    of its own with the two-dimensional state :math:`(z^u_i, z^l_i)`, transition
    :math:`F_i = [[a_{11,i}, a_{12,i}], [a_{21,i}, a_{22,i}]]`, observation row :math:`H = [1, 0]`,
    observation noise :math:`\sigma^{obs}_{t,i}`, input :math:`b_{t,i}` and process noise
    :math:`Q_{t,i} = [[q^u_i + v^u_{t,i}, v^s_{t,i}], [v^s_{t,i}, q^l_i + v^l_{t,i}]]` (the
    transition noise plus the variances of the known causes): the factorized belief of
    Eq. (rkn-update) is then exact, and the lanes' covariances are the entries
    :math:`(\sigma^u, \sigma^s, \sigma^l)`. All lanes of all sequences are filtered at once by
    :func:`pgm_wm.kalman_parallel.scan_filter` (the elements and the operator of
    Eq. kf-assoc, Chapter 1), with noise that changes with time. Tested equal to
    :func:`factorized_filter` (values and gradients) in float32 and float64; gradients with
    respect to ``A`` reach its block diagonals only, the entries such a transition has.
    """
    from .kalman_parallel import scan_filter

    d = _diagonal_problem(prior, A, trans_var, observation, mask, inputs, validate)
    N, T, m = d.N, d.T, d.m
    L, dt, dev = N * m, d.z0.dtype, d.z0.device
    lanes = lambda x: x.permute(1, 0, 2).reshape(T, L)  # noqa: E731  (N, T, m) -> (T, N m)

    def mat(a: Tensor, b: Tensor, c: Tensor, e: Tensor) -> Tensor:     # [[a, b], [c, e]]
        return torch.stack([torch.stack([a, b], -1), torch.stack([c, e], -1)], -2)

    su, ss, sl = d.s0[:, :m], d.s0[:, m:2 * m], d.s0[:, 2 * m:]
    m0 = torch.stack([d.z0[:, :m], d.z0[:, m:]], -1).reshape(L, 2)
    P0 = mat(su, ss, ss, sl).reshape(L, 2, 2)
    F = mat(*d.a).expand(N, m, 2, 2).reshape(1, L, 2, 2)
    H = torch.tensor([[1.0, 0.0]], dtype=dt, device=dev).expand(1, L, 1, 2)
    vu, vs, vl = (lanes(d.in_s[..., k * m:(k + 1) * m]) for k in range(3))
    Q = mat(vu, vs, vs, vl)                                                       # (T, L, 2, 2)
    c = torch.zeros(T, L, 2, dtype=dt, device=dev) if d.in_z is None else \
        torch.stack([lanes(d.in_z[..., :m]), lanes(d.in_z[..., m:])], -1)
    w = torch.ones(T, L, dtype=dt, device=dev) if d.mu is None else lanes(d.mu)
    m_prior, P_prior, m_post, P_post, m_next, P_next, _ = scan_filter(
        lanes(d.w)[..., None], w, c, m0, P0, F, H, Q, lanes(d.r)[..., None, None])

    def packed(mean: Tensor, cov: Tensor) -> FactorizedBelief:    # lanes (T, L, 2), (T, L, 2, 2) -> belief
        back = lambda x: x.reshape(T, N, m).transpose(0, 1)  # noqa: E731
        Z = torch.cat([back(mean[..., 0]), back(mean[..., 1])], -1)
        S = torch.cat([back(cov[..., 0, 0]), back(cov[..., 0, 1]), back(cov[..., 1, 1])], -1)
        return d.packed(Z, S)

    return FilterResult(packed(m_prior, P_prior), packed(m_post, P_post), packed(m_next, P_next))

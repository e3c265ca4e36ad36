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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_mask, check_nonnegative, check_positive, check_tensor
from .gaussian import Gaussian

__all__ = [
    "FactorizedBelief",
    "block_inverse",
    "factorized_update",
    "factorized_predict",
    "factorized_predict_from_matrix",
    "linear_cause",
    "known_input",
]


@dataclass(frozen=True)
class FactorizedBelief:
    """Factorized Gaussian belief over :math:`z = [z^u; z^l]`.

    Attributes:
        mean: ``(..., 2m)``
        var_upper: :math:`\\sigma^u`, ``(..., m)``, positive
        var_lower: :math:`\\sigma^l`, ``(..., m)``, positive
        cov_side: :math:`\\sigma^s`, ``(..., m)``, with :math:`(\\sigma^s)^2 < \\sigma^u\\sigma^l`
    """

    mean: Tensor
    var_upper: Tensor
    var_lower: Tensor
    cov_side: Tensor

    def __post_init__(self) -> None:
        check_tensor("mean", self.mean, min_ndim=1)
        if self.mean.shape[-1] % 2:
            raise ValueError(f"mean: last dimension must be even (2m), got {self.mean.shape[-1]}")
        m = self.mean.shape[-1] // 2
        check_last_dims("var_upper", self.var_upper, (m,))
        check_last_dims("var_lower", self.var_lower, (m,))
        check_last_dims("cov_side", self.cov_side, (m,))

    @property
    def latent_obs_dim(self) -> int:
        """:math:`m`, the size of each half."""
        return self.mean.shape[-1] // 2

    @property
    def mean_upper(self) -> Tensor:
        return self.mean[..., : self.latent_obs_dim]

    @property
    def mean_lower(self) -> Tensor:
        return self.mean[..., self.latent_obs_dim :]

    @property
    def var(self) -> Tensor:
        """Marginal variances ``[σᵘ; σˡ]``: ``(..., 2m)``."""
        return torch.cat([self.var_upper, self.var_lower], dim=-1)

    def validate(self, name: str = "belief") -> "FactorizedBelief":
        """Check positivity of the variances and positive-definiteness of each 2×2 block."""
        check_positive(f"{name}.var_upper", self.var_upper)
        check_positive(f"{name}.var_lower", self.var_lower)
        det = self.var_upper * self.var_lower - self.cov_side**2
        if not bool((det > 0).all()):
            raise ValueError(f"{name}.cov_side: |cov_side| must be < sqrt(var_upper * var_lower)")
        return self

    def to_dense(self) -> Gaussian:
        """The equivalent dense Gaussian, Eq. (rkn-factorized-cov): cov ``(..., 2m, 2m)``."""
        top = torch.cat([torch.diag_embed(self.var_upper), torch.diag_embed(self.cov_side)], dim=-1)
        bot = torch.cat([torch.diag_embed(self.cov_side), torch.diag_embed(self.var_lower)], dim=-1)
        return Gaussian(self.mean, torch.cat([top, bot], dim=-2))

    @classmethod
    def from_dense(cls, belief: Gaussian) -> "FactorizedBelief":
        """Keep the diagonals of the four ``m×m`` blocks of a dense ``(2m)×(2m)`` covariance.

        Exact when the dense covariance already has the factorized structure; otherwise
        this is the projection the RKN uses (off-diagonals inside blocks are dropped).
        """
        n = belief.dim
        if n % 2:
            raise ValueError(f"belief: dimension must be even (2m), got {n}")
        m = n // 2
        c = belief.cov
        diag = lambda M: torch.diagonal(M, dim1=-2, dim2=-1)  # noqa: E731
        return cls(belief.mean, diag(c[..., :m, :m]), diag(c[..., m:, m:]), diag(c[..., m:, :m]))

    @classmethod
    def isotropic(
        cls, batch_shape: Sequence[int], m: int, var: float = 10.0, dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> "FactorizedBelief":
        """Zero mean, ``σᵘ = σˡ = var``, ``σˢ = 0`` (the usual initial belief)."""
        z = torch.zeros(*batch_shape, 2 * m, dtype=dtype, device=device)
        v = torch.full((*batch_shape, m), float(var), dtype=dtype, device=device)
        return cls(z, v, v.clone(), torch.zeros_like(v))

    def where(self, keep_self: Tensor, other: "FactorizedBelief") -> "FactorizedBelief":
        """Select ``self`` where ``keep_self`` (``(...)``, bool) is True, else ``other``."""
        k = keep_self.to(torch.bool)[..., None]
        return FactorizedBelief(
            torch.where(k, self.mean, other.mean),
            torch.where(k, self.var_upper, other.var_upper),
            torch.where(k, self.var_lower, other.var_lower),
            torch.where(k, self.cov_side, other.cov_side),
        )

    @classmethod
    def stack(cls, beliefs: Sequence["FactorizedBelief"], dim: int = -2) -> "FactorizedBelief":
        """Stack beliefs along a new batch axis (``dim`` counts with the event axis last, so the
        default ``-2`` gives ``mean: (..., T, 2m)`` for a list of ``T`` beliefs)."""
        if len(beliefs) == 0:
            raise ValueError("beliefs: need at least one belief to stack")
        if dim >= 0:
            raise ValueError("dim: use a negative dimension (counted from the event axis)")
        return cls(*(torch.stack([getattr(b, f) for b in beliefs], dim=dim)
                     for f in ("mean", "var_upper", "var_lower", "cov_side")))

    def at(self, index: int) -> "FactorizedBelief":
        """Select one element along the time axis of a stacked belief (``mean: (..., T, 2m)``)."""
        return FactorizedBelief(self.mean[..., index, :], self.var_upper[..., index, :],
                                self.var_lower[..., index, :], self.cov_side[..., index, :])

    def drop_side(self) -> "FactorizedBelief":
        r"""The same belief with ``cov_side`` set to zero: a purely diagonal covariance.

        Used by the diagonal-only ablation of Chapter 3 (``RKN(..., diagonal_only=True)``). With
        :math:`\sigma^s = 0` the update, Eq. (rkn-update), leaves the lower half untouched.
        """
        return FactorizedBelief(self.mean, self.var_upper, self.var_lower, torch.zeros_like(self.cov_side))

    def detach(self) -> "FactorizedBelief":
        return FactorizedBelief(
            self.mean.detach(), self.var_upper.detach(), self.var_lower.detach(), self.cov_side.detach()
        )

    def __add__(self, other: "FactorizedBelief") -> "FactorizedBelief":
        """Sum of two *independent* factorized Gaussians (means and covariances add)."""
        return FactorizedBelief(
            self.mean + other.mean,
            self.var_upper + other.var_upper,
            self.var_lower + other.var_lower,
            self.cov_side + other.cov_side,
        )


def block_inverse(upper: Tensor, lower: Tensor, side: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""Invert :math:`M = [[\mathrm{diag}(a^u), \mathrm{diag}(a^s)], [\mathrm{diag}(a^s),
    \mathrm{diag}(a^l)]]` by scalar operations, Eq. (rkn-block-inverse):

    .. math:: d = a^u\odot a^l - a^s\odot a^s,\qquad
              M^{-1} = \begin{bmatrix}\mathrm{diag}(a^l\oslash d) & \mathrm{diag}(-a^s\oslash d)\\
                       \mathrm{diag}(-a^s\oslash d) & \mathrm{diag}(a^u\oslash d)\end{bmatrix}.

    Works in both directions (covariance → precision and back). Exact. Shapes ``(..., m)``.
    Raises ``ValueError`` if a 2×2 block is singular or not positive definite.
    """
    check_tensor("upper", upper, 1)
    check_last_dims("lower", lower, (upper.shape[-1],))
    check_last_dims("side", side, (upper.shape[-1],))
    d = upper * lower - side * side
    if not bool((d > 0).all()) or not bool((upper > 0).all()):
        raise ValueError("side: the 2x2 blocks must be positive definite (upper > 0, upper*lower > side^2)")
    return lower / d, upper / d, -side / d


def factorized_update(
    belief: FactorizedBelief,
    w: Tensor,
    w_var: Tensor,
    mask: Tensor | None = None,
    validate: bool = True,
) -> FactorizedBelief:
    r"""Exact Kalman update of a factorized belief with :math:`H = [I, 0]`, Eq. (rkn-update).

    With latent observation :math:`w` of variance :math:`\sigma^{obs}` and
    :math:`S = \sigma^u + \sigma^{obs}` (elementwise), the Kalman gain is
    :math:`[\mathrm{diag}(\sigma^u\oslash S);\ \mathrm{diag}(\sigma^s\oslash S)]` and

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
    computed in the product form above, which has no cancellation in floating point.

    A missing observation (``mask`` False) multiplies the gain by zero, so the posterior equals
    the prior exactly; ``w`` and ``w_var`` must still be finite there (any finite values).

    Args:
        w: latent observation ``(..., m)``; w_var: its variance ``(..., m)``, positive.
        mask: ``(...)`` bool, True = observed. Where False the posterior equals the prior.
        validate: check ``w_var > 0`` and finite (set False inside training loops to avoid a
            host sync); shapes are always checked.
    """
    if not isinstance(belief, FactorizedBelief):
        raise ValueError(f"belief: expected a FactorizedBelief, got {type(belief).__name__}")
    m = belief.latent_obs_dim
    check_last_dims("w", w, (m,))
    check_last_dims("w_var", w_var, (m,))
    if validate:
        check_positive("w_var", w_var)
        check_finite("w", w)
    su, sl, ss = belief.var_upper, belief.var_lower, belief.cov_side
    inv_S = 1.0 / (su + w_var)
    if mask is None:
        ratio = w_var * inv_S  # σ^obs ⊘ S
    else:
        mask = check_mask("mask", mask, tuple(torch.broadcast_shapes(belief.mean.shape[:-1], w.shape[:-1])))
        keep = mask.to(inv_S.dtype)[..., None]
        inv_S = inv_S * keep  # zero gain where the observation is missing
        ratio = w_var * inv_S + (1.0 - keep)  # = σ^obs ⊘ S where observed, exactly 1 where missing
    gain_u, gain_l = su * inv_S, ss * inv_S
    resid = w - belief.mean_upper
    mean = belief.mean + torch.cat([gain_u * resid, gain_l * resid], dim=-1)
    return FactorizedBelief(mean, su * ratio, sl - gain_l * ss, ss * ratio)


def known_input(b: Tensor) -> FactorizedBelief:
    """A known additive input ``b: (..., 2m)`` (e.g. a control term) as a zero-variance cause."""
    check_tensor("b", b, 1)
    if b.shape[-1] % 2:
        raise ValueError(f"b: last dimension must be even (2m), got {b.shape[-1]}")
    z = torch.zeros_like(b[..., : b.shape[-1] // 2])
    return FactorizedBelief(b, z, z, z)


def linear_cause(C: Tensor, mean: Tensor, var: Tensor) -> FactorizedBelief:
    r"""Push an independent cause :math:`u\sim\mathcal N(\mu, \mathrm{diag}(\sigma))` through
    :math:`C = [C^u; C^l]`, Eq. (gauss-marginal) restricted to block diagonals:

    .. math:: C\mu,\quad \sigma^u = (C^u\circ C^u)\sigma,\quad \sigma^l = (C^l\circ C^l)\sigma,\quad
              \sigma^s = (C^l\circ C^u)\sigma.

    Exact for the block diagonals of :math:`C\,\mathrm{diag}(\sigma)C^\top`; off-diagonals inside
    the blocks are dropped. Shapes: ``C: (..., 2m, k)``, ``mean, var: (..., k)``.
    """
    check_tensor("C", C, 2)
    if C.shape[-2] % 2:
        raise ValueError(f"C: number of rows must be even (2m), got {C.shape[-2]}")
    k = C.shape[-1]
    check_last_dims("mean", mean, (k,))
    check_last_dims("var", var, (k,))
    m = C.shape[-2] // 2
    Cu, Cl = C[..., :m, :], C[..., m:, :]
    mv = lambda M, v: (M @ v.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    return FactorizedBelief(mv(C, mean), mv(Cu * Cu, var), mv(Cl * Cl, var), mv(Cl * Cu, var))


def factorized_predict(
    belief: FactorizedBelief,
    A11: Tensor,
    A12: Tensor,
    A21: Tensor,
    A22: Tensor,
    trans_var: Tensor,
    causes: Sequence[FactorizedBelief] = (),
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
    if not isinstance(belief, FactorizedBelief):
        raise ValueError(f"belief: expected a FactorizedBelief, got {type(belief).__name__}")
    m = belief.latent_obs_dim
    for name, blk in (("A11", A11), ("A12", A12), ("A21", A21), ("A22", A22)):
        check_last_dims(name, blk, (m, m))
    check_last_dims("trans_var", trans_var, (2 * m,))
    if validate:
        check_nonnegative("trans_var", trans_var)
    A = torch.cat([torch.cat(torch.broadcast_tensors(A11, A12), dim=-1),
                   torch.cat(torch.broadcast_tensors(A21, A22), dim=-1)], dim=-2)
    return _predict_core(belief, A, trans_var, causes)


def factorized_predict_from_matrix(
    belief: FactorizedBelief,
    A: Tensor,
    trans_var: Tensor,
    causes: Sequence[FactorizedBelief] = (),
    validate: bool = True,
) -> FactorizedBelief:
    r""":func:`factorized_predict` with the transition given as one ``(..., 2m, 2m)`` matrix
    :math:`A = [[A_{11}, A_{12}], [A_{21}, A_{22}]]`; same result, same approximation, Eq. (rkn-predict).
    """
    if not isinstance(belief, FactorizedBelief):
        raise ValueError(f"belief: expected a FactorizedBelief, got {type(belief).__name__}")
    m = belief.latent_obs_dim
    check_last_dims("A", A, (2 * m, 2 * m))
    check_last_dims("trans_var", trans_var, (2 * m,))
    if validate:
        check_nonnegative("trans_var", trans_var)
    return _predict_core(belief, A, trans_var, causes)


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


r"""The one belief family of the book: dense, diagonal and factorized Gaussians (Chapters 1–6).

Every model in the book carries a Gaussian belief over a latent variable, in one of three forms:

* :class:`Gaussian` ``(mean, cov)`` — a dense covariance (Chapter 1, the Kalman filter);
* :class:`DiagGaussian` ``(mean, var)`` — a diagonal covariance: latent observations with their
  variances, set encoders, task beliefs, abstract actions (Chapters 2, 5, 6);
* :class:`FactorizedBelief` ``(mean, var_upper, var_lower, cov_side)`` — the RKN's factorized
  covariance, Eq. (rkn-factorized-cov) (Chapters 3–6).

They share one protocol, so code that moves beliefs around does not care which form it holds:

* ``.mean`` ``(..., n)``, ``.var`` (marginal variances ``(..., n)``), ``.to_dense()`` (the
  equivalent :class:`Gaussian`: the *oracle* the tests compare the other two with);
* ``a + b``: the sum of two **independent** Gaussians (means and covariances add,
  Eq. gauss-marginal with identity maps);
* ``.map(fn)`` applies ``fn`` to every tensor field; ``Cls.stack(seq, dim)`` / ``Cls.cat(seq, dim)``
  stack / concatenate along a batch axis; ``.where(mask, other)`` selects per batch element;
  ``.detach()``; ``belief[index]`` indexes the batch dimensions; ``.at(t)`` selects one step of a
  belief stacked over time (``mean: (..., T, n)``).

Axis convention of ``stack``/``cat``/``at``: a *negative* ``dim`` counts as in the ``mean`` tensor
(event axis last), so the default ``dim=-2`` puts a time axis just before the event axis
(``mean: (..., T, n)``) in every form; non-negative ``dim`` indexes the leading batch axes.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable, ClassVar, Iterator, Sequence, TypeVar

import torch
from torch import Tensor

from ._checks import check_finite, check_last_dims, check_positive, check_same_batch, check_spd, check_tensor
from ._linalg import chol_logpdf, symmetrize

__all__ = [
    "block_inverse", "Gaussian", "DiagGaussian", "FactorizedBelief"]

B = TypeVar("B", bound="_Belief")


class _Belief:
    """The shared protocol: every field is a tensor whose trailing ``_event_dims[field]`` axes
    are event axes and whose leading axes are batch axes."""

    _event_dims: ClassVar[dict[str, int]] = {}

    def _tensors(self) -> list[Tensor]:
        return [getattr(self, f.name) for f in fields(self)]  # type: ignore[arg-type]

    def map(self: B, fn: Callable[[Tensor], Tensor]) -> B:
        """The belief with ``fn`` applied to every tensor field (``fn`` must keep event axes)."""
        return type(self)(*(fn(t) for t in self._tensors()))

    def detach(self: B) -> B:
        return self.map(Tensor.detach)

    def to(self: B, *args: Any, **kwargs: Any) -> B:
        """``Tensor.to`` on every field (dtype and/or device)."""
        return self.map(lambda t: t.to(*args, **kwargs))

    @classmethod
    def _axis(cls, name: str, dim: int) -> int:
        return dim - (cls._event_dims[name] - 1) if dim < 0 else dim

    @classmethod
    def _join(cls: type[B], op: Callable[..., Tensor], beliefs: Sequence[B], dim: int, what: str) -> B:
        if len(beliefs) == 0:
            raise ValueError(f"beliefs: need at least one belief to {what}")
        names = [f.name for f in fields(cls)]  # type: ignore[arg-type]
        return cls(*(op([getattr(b, n) for b in beliefs], dim=cls._axis(n, dim)) for n in names))

    @classmethod
    def stack(cls: type[B], beliefs: Sequence[B], dim: int = -2) -> B:
        """Stack beliefs along a new batch axis (see the module docstring for ``dim``)."""
        return cls._join(torch.stack, beliefs, dim, "stack")

    @classmethod
    def cat(cls: type[B], beliefs: Sequence[B], dim: int = -2) -> B:
        """Concatenate beliefs along an existing batch axis (see the module docstring for ``dim``)."""
        return cls._join(torch.cat, beliefs, dim, "concatenate")

    def at(self: B, index: int) -> B:
        """One step of a belief stacked over time (``mean: (..., T, n)``) -> ``mean: (..., n)``."""
        names = [f.name for f in fields(self)]  # type: ignore[arg-type]
        return type(self)(*(getattr(self, n).select(self._axis(n, -2), index) for n in names))

    def where(self: B, keep_self: Tensor, other: B) -> B:
        """Select ``self`` where ``keep_self`` (shape ``(...)``, the batch shape) is True, else ``other``."""
        if type(other) is not type(self):
            raise ValueError(f"other: expected a {type(self).__name__}, got {type(other).__name__}")
        k = keep_self.to(torch.bool)
        names = [f.name for f in fields(self)]  # type: ignore[arg-type]
        return type(self)(*(
            torch.where(k.reshape(*k.shape, *([1] * self._event_dims[n])), getattr(self, n), getattr(other, n))
            for n in names))

    def __add__(self: B, other: B) -> B:
        """Sum of two *independent* Gaussians of the same form: means and covariances add."""
        if type(other) is not type(self):
            return NotImplemented
        return type(self)(*(a + b for a, b in zip(self._tensors(), other._tensors())))

    def __getitem__(self: B, index: object) -> B:
        """Index the batch dimensions, e.g. ``belief[0]`` or ``belief[:, t]`` (no Ellipsis)."""
        if not isinstance(index, tuple):
            index = (index,)
        if any(i is Ellipsis for i in index):
            raise ValueError("index: Ellipsis is not supported; index the batch dimensions explicitly")
        return self.map(lambda t: t[index])


@dataclass(frozen=True)
class Gaussian(_Belief):
    """A (batch of) multivariate Gaussian belief(s) :math:`\\mathcal N(\\mu, \\Sigma)`.

    Attributes:
        mean: ``(..., n)``
        cov: ``(..., n, n)``, symmetric positive (semi-)definite. The leading (batch)
            dimensions of ``mean`` and ``cov`` must broadcast against each other.

    Construction checks shapes only (cheap); call :meth:`validate` to also check that
    ``cov`` is positive definite.
    """

    mean: Tensor
    cov: Tensor
    _event_dims: ClassVar[dict[str, int]] = {"mean": 1, "cov": 2}

    def __post_init__(self) -> None:
        check_tensor("mean", self.mean, min_ndim=1)
        n = self.mean.shape[-1]
        check_last_dims("cov", self.cov, (n, n))
        check_same_batch(("cov", "mean"), (self.cov, self.mean), (2, 1))

    @property
    def dim(self) -> int:
        """Event dimension ``n``."""
        return self.mean.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        """Broadcast leading shape of ``mean`` and ``cov``."""
        return torch.broadcast_shapes(self.mean.shape[:-1], self.cov.shape[:-2])

    @property
    def var(self) -> Tensor:
        """Marginal variances, the diagonal of ``cov``: ``(..., n)``."""
        return torch.diagonal(self.cov, dim1=-2, dim2=-1)

    @property
    def std(self) -> Tensor:
        """Marginal standard deviations: ``(..., n)``."""
        return self.var.clamp_min(0).sqrt()

    def validate(self, name: str = "belief") -> "Gaussian":
        """Check that ``cov`` is symmetric positive definite; raise ``ValueError`` naming ``name``."""
        check_spd(f"{name}.cov", self.cov.detach())
        return self

    def to_dense(self) -> "Gaussian":
        """The dense form of a dense Gaussian is itself."""
        return self

    @classmethod
    def _join(cls, op: Callable[..., Tensor], beliefs: Sequence["Gaussian"], dim: int, what: str) -> "Gaussian":
        """Stack / concatenate after broadcasting every belief to the common batch shape (a
        covariance shared by a batch of means is expanded first)."""
        if len(beliefs) == 0:
            raise ValueError(f"beliefs: need at least one belief to {what}")
        batch = torch.broadcast_shapes(*(b.batch_shape for b in beliefs))
        return super()._join(op, [b.expand(*batch) for b in beliefs], dim, what)

    def expand(self, *batch_shape: int) -> "Gaussian":
        """Broadcast ``mean`` and ``cov`` to the leading shape ``batch_shape``."""
        n = self.dim
        return Gaussian(self.mean.expand(*batch_shape, n), self.cov.expand(*batch_shape, n, n))

    def __getitem__(self, index: object) -> "Gaussian":
        """Index the batch dimensions, e.g. ``belief[0]`` or ``belief[:, t]``.

        Both tensors are first broadcast to :attr:`batch_shape`, so the index refers to the
        same batch element in ``mean`` and ``cov``.
        """
        return _Belief.__getitem__(self.expand(*self.batch_shape), index)

    def log_prob(self, x: Tensor) -> Tensor:
        """Log-density :math:`\\log\\mathcal N(x\\mid\\mu,\\Sigma)`, Eq. (gauss-logpdf). Returns ``(...)``."""
        check_tensor("x", x, min_ndim=1)
        check_last_dims("x", x, (self.dim,))
        check_finite("x", x.detach())
        chol, info = torch.linalg.cholesky_ex(symmetrize(self.cov))
        if bool((info != 0).any()):
            raise ValueError("cov: matrix is not positive definite")
        return chol_logpdf(x - self.mean, chol)

    def sample(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw ``n`` samples :math:`\\mu + L\\epsilon` with :math:`LL^\\top = \\Sigma`: returns ``(n, ..., dim)``."""
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"n: expected a positive integer, got {n!r}")
        chol, info = torch.linalg.cholesky_ex(0.5 * (self.cov + self.cov.transpose(-1, -2)))
        if bool((info != 0).any()):
            raise ValueError("cov: matrix is not positive definite")
        shape = (n, *self.batch_shape, self.dim)
        eps = torch.randn(shape, dtype=self.mean.dtype, device=self.mean.device, generator=generator)
        return self.mean + (chol @ eps.unsqueeze(-1)).squeeze(-1)


@dataclass(frozen=True)
class DiagGaussian(_Belief):
    r"""A (batch of) Gaussian(s) with diagonal covariance :math:`\mathcal N(\mu, \operatorname{diag}\sigma)`.

    The form of every latent observation with its variance (``w, w_var``), every set element
    ``(r_n, σ_n)``, task belief ``(μ_l, σ_l)`` and abstract action ``(μ_α, σ_α)`` in the book.

    Attributes:
        mean: ``(..., n)``; var: ``(..., n)``, the same shape (positive; :meth:`validate` checks).

    For compatibility with code that unpacks a ``(mean, var)`` pair, a ``DiagGaussian`` unpacks
    as one: ``mean, var = belief``.
    """

    mean: Tensor
    var: Tensor
    _event_dims: ClassVar[dict[str, int]] = {"mean": 1, "var": 1}

    def __post_init__(self) -> None:
        check_tensor("mean", self.mean, min_ndim=1)
        check_tensor("var", self.var, min_ndim=1)
        if tuple(self.var.shape) != tuple(self.mean.shape):
            raise ValueError(f"var: expected the shape of mean {tuple(self.mean.shape)}, got {tuple(self.var.shape)}")

    def __iter__(self) -> Iterator[Tensor]:
        return iter((self.mean, self.var))

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]

    def validate(self, name: str = "belief") -> "DiagGaussian":
        """Check finite means and positive finite variances; raise ``ValueError`` naming ``name``."""
        if not bool(torch.isfinite(self.mean).all()):
            raise ValueError(f"{name}.mean: contains NaN or infinite values")
        check_positive(f"{name}.var", self.var)
        return self

    def to_dense(self) -> Gaussian:
        """The equivalent dense Gaussian, ``cov = diag(var)``: ``(..., n, n)``."""
        return Gaussian(self.mean, torch.diag_embed(self.var))

    @classmethod
    def standard(cls, batch_shape: Sequence[int], n: int, var: float = 1.0, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> "DiagGaussian":
        """Zero mean and variance ``var`` in every dimension (e.g. the N(0, I) aggregation prior)."""
        z = torch.zeros(*batch_shape, n, dtype=dtype, device=device)
        return cls(z, torch.full_like(z, float(var)))


@dataclass(frozen=True)
class FactorizedBelief(_Belief):
    """Factorized Gaussian belief over :math:`z = [z^u; z^l]`, Eq. (rkn-factorized-cov).

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
    _event_dims: ClassVar[dict[str, int]] = {"mean": 1, "var_upper": 1, "var_lower": 1, "cov_side": 1}

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

    @property
    def upper(self) -> DiagGaussian:
        """The marginal of the upper (observed) half, :math:`\\mathcal N(z^u, \\operatorname{diag}\\sigma^u)`."""
        return DiagGaussian(self.mean_upper, self.var_upper)

    def validate(self, name: str = "belief") -> "FactorizedBelief":
        """Check finite means, positive variances and positive-definiteness of each 2×2 block."""
        if not bool(torch.isfinite(self.mean).all()):
            raise ValueError(f"{name}.mean: contains NaN or infinite values")
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

    @classmethod
    def known(cls, b: Tensor) -> "FactorizedBelief":
        """A known quantity ``b: (..., 2m)`` as a belief with zero covariance (a point mass)."""
        check_tensor("b", b, 1)
        if b.shape[-1] % 2:
            raise ValueError(f"b: last dimension must be even (2m), got {b.shape[-1]}")
        z = torch.zeros_like(b[..., : b.shape[-1] // 2])
        return cls(b, z, z, z)

    def drop_side(self) -> "FactorizedBelief":
        r"""The same belief with ``cov_side`` set to zero: a purely diagonal covariance.

        Used by the diagonal-only ablation of Chapter 3 (``RKN(..., diagonal_only=True)``). With
        :math:`\sigma^s = 0` the update, Eq. (rkn-update), leaves the lower half untouched.
        """
        return FactorizedBelief(self.mean, self.var_upper, self.var_lower, torch.zeros_like(self.cov_side))


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

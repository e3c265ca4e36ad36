r"""The Recurrent Kalman Network (Chapter 3): a Kalman filter in a learned latent space.

An RKN is ``encoder -> [update, predict]* -> decoder``:

* the **encoder** maps an observation :math:`o_t` to a latent observation :math:`w_t\in\mathbb R^m`
  and its variance :math:`\sigma^{obs}_t` (Eq. rkn-encoder);
* the **update** is the exact factorized Kalman update with :math:`H=[I,0]`
  (:func:`pgm_wm.factorized.factorized_update`, Eq. rkn-update); a missing observation skips it;
* the **predict** step uses a locally linear transition :math:`A_t = \sum_k \alpha_k(z_t^+) A^{(k)}`
  made of band-limited blocks (Eq. rkn-transition) and learned transition noise, via
  :func:`pgm_wm.factorized.factorized_predict_from_matrix` (Eq. rkn-predict; this step keeps only
  the block diagonals of :math:`A\Sigma A^\top`, the RKN's one approximation); later chapters add
  more independent causes to this predict step (an action term, a latent task): a model is the
  previous one plus one more entry in the list of causes :meth:`RKN.filter` takes;
* the **decoder** maps the belief to a Gaussian over the target (Eq. rkn-decoder).

``RKN(..., diagonal_only=True)`` is the diagonal-covariance ablation of Chapter 3 (side
covariance forced to zero, so the memory half is never corrected by an observation).
Everything runs on CPU or CUDA (the device and dtype of the inputs are followed).

Positive quantities use ``elu(x) + 1`` (:func:`elup1`), which is smooth, equals ``x + 1`` for
``x > 0`` and decays to 0 (never reaching it) for ``x -> -inf``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_input_dtype, check_last_dims, check_mask, check_same_dtype, check_tensor, module_dtype
from .aggregation import zero_padding
from .beliefs import DiagGaussian, FactorizedBelief
from .factorized import (
    as_observation,
    update_unchecked,
    diagonal_factorized_filter,
    factorized_predict_from_matrix,
)
from .filtering import FilterResult, filter_loop
from .layers import elup1, mlp
from ._backends import select
from ._backends.locally_linear_jit import band_pairs, locally_linear_filter_jit

__all__ = [
    "elup1",
    "mlp",
    "band_mask",
    "BlockMatrix",
    "LocallyLinearTransition",
    "ObservationEncoder",
    "BeliefDecoder",
    "StateCause",
    "Cause",
    "over_time",
    "zero_missing",
    "RKN",
]


class StateCause(Protocol):
    """A cause that reads the posterior of the step it follows (only
    :class:`pgm_wm.acrkn.LocallyLinearControl` does): ``cause(t, posterior_t) -> FactorizedBelief``."""

    def __call__(self, t: int, posterior: FactorizedBelief) -> FactorizedBelief: ...


Cause = Union[FactorizedBelief, StateCause]
"""One additive independent cause of the predict step: either known before the loop (a
:class:`FactorizedBelief` stacked over time, ``mean: (B, T, 2m)``) or a :class:`StateCause`."""


def over_time(cause: FactorizedBelief, T: int) -> FactorizedBelief:
    """A cause constant over a window (batch ``(B,)``, e.g. a task) as a sequence ``(B, T, ·)``."""
    return cause.map(lambda x: x.unsqueeze(-2).expand(*x.shape[:-1], T, x.shape[-1]))


def band_mask(m: int, bandwidth: int) -> Tensor:
    """Boolean ``(m, m)`` mask of a band matrix: entry ``(i, j)`` is free iff ``|i - j| <= bandwidth``."""
    if m <= 0:
        raise ValueError(f"m: must be positive, got {m}")
    if bandwidth < 0:
        raise ValueError(f"bandwidth: must be >= 0, got {bandwidth}")
    idx = torch.arange(m)
    return (idx[:, None] - idx[None, :]).abs() <= bandwidth


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class BlockMatrix(nn.Module):
    r"""``num`` learned :math:`2m\times 2m` matrices :math:`M = [[M_{11}, M_{12}], [M_{21}, M_{22}]]`
    with band blocks of half-width ``bandwidth`` (``0``: diagonal blocks, for which pushing a
    factorized belief through :math:`M` is exact). The one block-matrix parametrisation of the
    book: the RKN's basis matrices :math:`A^{(k)}` (:class:`LocallyLinearTransition`), the MTS3 task
    transition :math:`X`, abstract-action matrix :math:`Y` and task matrices :math:`C`.

    Parameters ``basis_11 .. basis_22``: ``(num, m, m)``, each block initialised to ``d * I`` with
    ``init = (d11, d12, d21, d22)``. ``decoupled=True`` fixes :math:`M_{12} = M_{21} = 0` (zero and
    frozen, :func:`pgm_wm.mts3.decouple_halves`; the diagonal-covariance ablation).
    """

    def __init__(self, m: int, bandwidth: int = 0, init: Sequence[float] = (0.2, 0.0, 0.0, 0.2),
                 decoupled: bool = False, num: int = 1) -> None:
        super().__init__()
        if m <= 0:
            raise ValueError(f"m: must be positive, got {m}")
        if num <= 0:
            raise ValueError(f"num: must be positive, got {num}")
        if len(init) != 4:
            raise ValueError(f"init: expected four numbers (d11, d12, d21, d22), got {init!r}")
        self.m, self.bandwidth, self.num, self.decoupled = m, bandwidth, num, bool(decoupled)
        self.register_buffer("band", band_mask(m, bandwidth).to(torch.get_default_dtype()), persistent=False)
        eye = torch.eye(m).expand(num, m, m)
        self.basis_11 = nn.Parameter(float(init[0]) * eye.clone())
        self.basis_12 = nn.Parameter(float(init[1]) * eye.clone())
        self.basis_21 = nn.Parameter(float(init[2]) * eye.clone())
        self.basis_22 = nn.Parameter(float(init[3]) * eye.clone())
        if decoupled:
            with torch.no_grad():
                self.basis_12.zero_()
                self.basis_21.zero_()
            self.basis_12.requires_grad_(False)
            self.basis_21.requires_grad_(False)

    def dense_basis(self) -> Tensor:
        """The band-masked matrices as dense ``(num, 2m, 2m)`` matrices."""
        band = self.band.to(self.basis_11.dtype)
        top = torch.cat([self.basis_11 * band, self.basis_12 * band], dim=-1)
        bot = torch.cat([self.basis_21 * band, self.basis_22 * band], dim=-1)
        return torch.cat([top, bot], dim=-2)

    def dense(self) -> Tensor:
        """:math:`M` as one dense ``(2m, 2m)`` matrix (``num == 1``)."""
        if self.num != 1:
            raise ValueError(f"num: dense() needs a single matrix, this module holds {self.num}")
        return self.dense_basis()[0]

    def cause(self, belief: FactorizedBelief) -> FactorizedBelief:
        r"""The cause :math:`M l` of an independent factorized belief :math:`l\sim\mathcal N(\mu,\Sigma)`,
        Eq. (gauss-marginal): mean :math:`M\mu`, covariance the block diagonals of :math:`M\Sigma M^\top`
        (the predict arithmetic of Eq. rkn-predict with zero noise; exact for diagonal blocks)."""
        zero = belief.mean.new_zeros(belief.mean.shape[-1])
        return factorized_predict_from_matrix(belief, self.dense().to(belief.mean.dtype), zero, validate=False)


@dataclass(frozen=True)
class BandParameters:
    """A locally linear transition in band storage (:mod:`pgm_wm._backends.locally_linear_jit`):
    ``basis: (4, K, nb)`` values of the blocks 11, 12, 21, 22 at the band pairs ``(bi, bj)``,
    ``ident: (nb,)`` what is added to the diagonal blocks, and the coefficient net's ``weight:
    (K, 2m)`` and ``bias: (K,)`` (``None`` for one basis matrix)."""

    basis: Tensor
    ident: Tensor
    bi: np.ndarray
    bj: np.ndarray
    weight: Tensor | None
    bias: Tensor | None


class LocallyLinearTransition(BlockMatrix):
    r"""Locally linear transition model, Eq. (rkn-transition):

    .. math:: A_t = I + \sum_{k=1}^K \alpha_k(z_t^+)\,A^{(k)},\qquad
              \alpha(z) = \mathrm{softmax}(W z + c),

    each :math:`A^{(k)}` a :class:`BlockMatrix` entry with band blocks of half-width ``bandwidth``.
    Initialization: :math:`A^{(k)}_{11} = A^{(k)}_{22} = -d\,I`, :math:`A^{(k)}_{12} = c\,I`,
    :math:`A^{(k)}_{21} = -c\,I` with ``coupling`` :math:`c = 0.2` and ``damping`` :math:`d = 0.05`, so
    the initial :math:`A = [[(1-d)I, cI], [-cI, (1-d)I]]`: a damped Euler step of an oscillator
    coupling the observed half to the memory half, with spectral radius
    :math:`\sqrt{(1-d)^2 + c^2} = 0.971 < 1`. (The authors' code uses :math:`d = 0`, radius 1.02:
    an untrained model's prior variance then grows like :math:`1.02^{2t}` and overflows after
    about 2200 steps without observations.)

    ``num_basis = 1`` gives a constant (state-independent) linear transition; ``bandwidth = 0``
    gives diagonal blocks, for which the factorized predict is exact.

    The transition noise :math:`[q^u; q^l]` is a learned vector, positive via softplus,
    initialized to ``trans_var_init``.
    """

    def __init__(
        self,
        latent_obs_dim: int,
        num_basis: int = 15,
        bandwidth: int = 3,
        trans_var_init: float = 0.1,
        coupling: float = 0.2,
        add_identity: bool = True,
        damping: float = 0.05,
    ) -> None:
        m, K = latent_obs_dim, num_basis
        if m <= 0:
            raise ValueError(f"latent_obs_dim: must be positive, got {m}")
        if K <= 0:
            raise ValueError(f"num_basis: must be positive, got {K}")
        if trans_var_init <= 0:
            raise ValueError(f"trans_var_init: must be positive, got {trans_var_init}")
        diag = -float(damping) if add_identity else 0.0
        super().__init__(m, bandwidth, (diag, coupling, -coupling, diag), num=K)
        self.latent_obs_dim, self.num_basis = m, K
        self.add_identity = add_identity
        self.coefficient_net = nn.Linear(2 * m, K) if K > 1 else None
        self.trans_var_raw = nn.Parameter(torch.full((2 * m,), _inv_softplus(trans_var_init)))

    @property
    def constant(self) -> bool:
        """True if :math:`A_t` does not depend on the state (``num_basis == 1``)."""
        return self.num_basis == 1

    @property
    def diagonal_blocks(self) -> bool:
        """True if the four blocks of :math:`A_t` are diagonal (``bandwidth == 0``)."""
        return self.bandwidth == 0

    @classmethod
    def fixed(cls, A: Tensor, trans_var: Tensor, bandwidth: int | None = None) -> "LocallyLinearTransition":
        """A constant transition with given ``A: (2m, 2m)`` and noise ``trans_var: (2m,)`` (> 0).

        ``num_basis = 1`` and no identity is added, so :meth:`dense_matrix` returns ``A`` (entries
        outside the band of half-width ``bandwidth`` are dropped; default: the full matrix).
        The parameters stay trainable; call ``requires_grad_(False)`` to freeze them.
        Used to compare with a known linear-Gaussian model (Chapter 3's velocity example).
        """
        check_tensor("A", A, 2)
        n = A.shape[-1]
        if A.ndim != 2 or A.shape[0] != n or n % 2:
            raise ValueError(f"A: expected one square (2m, 2m) matrix, got shape {tuple(A.shape)}")
        m = n // 2
        check_last_dims("trans_var", trans_var, (n,))
        if trans_var.ndim != 1 or not bool((trans_var > 0).all()):
            raise ValueError("trans_var: expected a positive vector of shape (2m,)")
        tr = cls(m, num_basis=1, bandwidth=m - 1 if bandwidth is None else bandwidth, add_identity=False)
        tr = tr.to(A.dtype)
        with torch.no_grad():
            for name, blk in (("basis_11", A[:m, :m]), ("basis_12", A[:m, m:]),
                              ("basis_21", A[m:, :m]), ("basis_22", A[m:, m:])):
                getattr(tr, name).copy_(blk.unsqueeze(0))
            t = trans_var.to(A.dtype)
            tr.trans_var_raw.copy_(t + torch.log(-torch.expm1(-t)))  # inverse softplus
        return tr

    @property
    def trans_var(self) -> Tensor:
        """Transition noise variances :math:`[q^u; q^l]`: ``(2m,)``, positive."""
        return F.softplus(self.trans_var_raw)

    def coefficients(self, mean: Tensor) -> Tensor:
        """Mixing weights :math:`\\alpha(z)`: ``(..., K)``, non-negative and summing to one."""
        if self.coefficient_net is None:
            return torch.ones(*mean.shape[:-1], 1, dtype=mean.dtype, device=mean.device)
        return torch.softmax(self.coefficient_net(mean), dim=-1)

    def _mix(self, mean: Tensor, basis: Tensor) -> Tensor:
        """:math:`A_t` from a precomputed :meth:`dense_basis` (identity added if configured)."""
        m2 = 2 * self.latent_obs_dim
        if self.coefficient_net is None:
            A = basis[0]
        else:
            alpha = self.coefficients(mean)  # (..., K)
            A = (alpha @ basis.reshape(self.num_basis, m2 * m2)).reshape(*alpha.shape[:-1], m2, m2)
        if self.add_identity:
            A = A + torch.eye(m2, dtype=A.dtype, device=A.device)
        return A

    def dense_matrix(self, mean: Tensor) -> Tensor:
        """:math:`A_t` as a dense ``(..., 2m, 2m)`` matrix for posterior means ``(..., 2m)``
        (``(2m, 2m)`` without a batch when ``num_basis == 1``)."""
        check_last_dims("mean", mean, (2 * self.latent_obs_dim,))
        return self._mix(mean, self.dense_basis())

    def blocks(self, mean: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The four ``(..., m, m)`` blocks of :math:`A_t` for posterior means ``(..., 2m)``.

        With ``num_basis == 1`` the blocks are ``(m, m)`` and broadcast over the batch.
        """
        A, m = self.dense_matrix(mean), self.latent_obs_dim
        return A[..., :m, :m], A[..., :m, m:], A[..., m:, :m], A[..., m:, m:]

    def band_parameters(self) -> "BandParameters":
        """The transition in the band storage of the compiled filter
        (:mod:`pgm_wm._backends.locally_linear_jit`): basis values at the band pairs, differentiable."""
        bi, bj = band_pairs(self.latent_obs_dim, self.bandwidth)
        ii, jj = torch.as_tensor(bi), torch.as_tensor(bj)
        basis = torch.stack([blk[:, ii, jj] for blk in (self.basis_11, self.basis_12, self.basis_21, self.basis_22)])
        ident = (ii == jj).to(basis.dtype) * float(self.add_identity)
        net = self.coefficient_net
        return BandParameters(basis, ident, bi, bj, None if net is None else net.weight,
                              None if net is None else net.bias)

    def predictor(self) -> Callable[..., FactorizedBelief]:
        """A predict function ``(post, causes=()) -> prior`` equal to :meth:`forward`, with the
        parameter-only work (band masking of the basis, noise transform) done once. Use it inside
        a time loop; call it again after every optimizer step."""
        basis, q = self.dense_basis(), self.trans_var

        def predict(post: FactorizedBelief, causes: Sequence[FactorizedBelief] = ()) -> FactorizedBelief:
            A = self._mix(post.mean, basis)
            return factorized_predict_from_matrix(post, A, q, causes, validate=False)

        return predict

    def forward(self, post: FactorizedBelief, causes: Sequence[FactorizedBelief] = ()) -> FactorizedBelief:
        """Predict step, Eq. (rkn-predict): prior of the next step from the posterior ``post``."""
        return self.predictor()(post, causes)


class ObservationEncoder(nn.Module):
    r"""Observation encoder, Eq. (rkn-encoder): :math:`o_t \mapsto (w_t, \sigma^{obs}_t)`.

    ``trunk`` (default: an MLP with ``hidden`` units) maps ``(..., obs_dim)`` to features; two
    linear heads give :math:`w_t` and :math:`\sigma^{obs}_t = \mathrm{elu}(\cdot)+1`. With
    ``normalize_w`` the latent observation is L2-normalized, as in the original RKN; this keeps the
    latent scale fixed so that the variances carry the confidence.
    For images, pass a convolutional ``trunk`` and its ``feature_dim``.
    """

    def __init__(
        self,
        obs_dim: int,
        latent_obs_dim: int,
        hidden: Sequence[int] = (64,),
        trunk: nn.Module | None = None,
        feature_dim: int | None = None,
        normalize_w: bool = False,
        activation: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        if trunk is None:
            layers: list[nn.Module] = []
            d = obs_dim
            for h in hidden:
                layers += [nn.Linear(d, h), activation()]
                d = h
            trunk = nn.Sequential(*layers)
            feature_dim = d
        elif feature_dim is None:
            raise ValueError("feature_dim: required when a custom trunk is given")
        self.obs_dim, self.latent_obs_dim = obs_dim, latent_obs_dim
        self.trunk = trunk
        self.w_head = nn.Linear(feature_dim, latent_obs_dim)
        self.var_head = nn.Linear(feature_dim, latent_obs_dim)
        self.normalize_w = normalize_w

    def forward(self, obs: Tensor) -> DiagGaussian:
        """``obs: (..., obs_dim)`` -> ``DiagGaussian(w, w_var)``, each ``(..., m)`` (unpacks as ``w, w_var``)."""
        check_last_dims("obs", obs, (self.obs_dim,))
        h = self.trunk(obs)
        w = self.w_head(h)
        if self.normalize_w:
            w = F.normalize(w, p=2, dim=-1, eps=1e-8)
        return DiagGaussian(w, elup1(self.var_head(h)))


class BeliefDecoder(nn.Module):
    r"""Gaussian decoder, Eq. (rkn-decoder): mean from the belief mean, variance from the belief's
    variances :math:`[\sigma^u, \sigma^l, \sigma^s]` (positive via ``elu + 1``).

    With ``log_var_input=True`` the variance network reads the scale-free features
    :math:`[\log\sigma^u, \log\sigma^l, \sigma^s/\sqrt{\sigma^u\sigma^l}]` (log-variances and the
    correlation) instead. The belief variances can span many orders of magnitude (a memory half
    that is never corrected grows without bound), and raw inputs of that size drive the output
    layer into ``elu``'s flat region, where the decoded variance underflows to zero.
    """

    def __init__(
        self,
        latent_obs_dim: int,
        out_dim: int,
        hidden: Sequence[int] = (64,),
        var_hidden: Sequence[int] = (64,),
        activation: type[nn.Module] = nn.ReLU,
        log_var_input: bool = False,
    ) -> None:
        super().__init__()
        self.out_dim = out_dim
        self.log_var_input = bool(log_var_input)
        self.mean_net = mlp(2 * latent_obs_dim, hidden, out_dim, activation)
        self.var_net = mlp(3 * latent_obs_dim, var_hidden, out_dim, activation)

    def forward(self, belief: FactorizedBelief) -> tuple[Tensor, Tensor]:
        """Returns ``(mean, var)`` each ``(..., out_dim)``."""
        su, sl, ss = belief.var_upper, belief.var_lower, belief.cov_side
        if self.log_var_input:
            v = torch.cat([su.log(), sl.log(), ss * torch.rsqrt(su * sl)], dim=-1)
        else:
            v = torch.cat([su, sl, ss], dim=-1)
        return self.mean_net(belief.mean), elup1(self.var_net(v))


def locally_linear_filter(
    prior: FactorizedBelief,
    transition: nn.Module,
    observation: DiagGaussian,
    mask: Tensor | None = None,
    inputs: FactorizedBelief | None = None,
    *,
    diagonal_only: bool = False,
    backend: str = "auto",
) -> FilterResult[FactorizedBelief]:
    r"""The RKN's filter with a locally linear transition (Eq. rkn-transition): for
    :math:`t = 1..T`, the update of Eq. (rkn-update), then the predict of Eq. (rkn-predict) with
    :math:`A_t` mixed from the posterior mean, plus the known causes ``inputs.at(t)``.

    ``backend="reference"`` runs the book's loop (:func:`pgm_wm.filtering.filter_loop` with
    ``transition.predictor()``); ``"compiled"`` the compiled loop with its hand-written backward
    pass (:mod:`pgm_wm._backends.locally_linear_jit`, tested equal to the reference, values and
    gradients, in float32 and float64); ``"auto"`` lets the backend table choose
    (:mod:`pgm_wm._backends`: the compiled loop for CPU tensors where numba is available, else the
    reference loop). ``diagonal_only`` zeroes the side covariance of every prediction and of the prior.

    Args:
        prior: belief of the first step, batch ``(B,)``.
        transition: a module with ``predictor()`` and ``band_parameters()``
            (:class:`LocallyLinearTransition`, :class:`pgm_wm.acrkn.NormBoundedTransition`).
        observation: ``DiagGaussian(w, w_var)``, each ``(B, T, m)``.
        mask: ``(B, T)`` bool, True = observed.
        inputs: the sum of the causes known before the loop, ``mean: (B, T, 2m)``.
    """
    if diagonal_only:
        prior = prior.drop_side()
    w = observation.mean
    backend = select("locally_linear_factorized_filter", w, observation.var, prior.mean, backend=backend,
                     masked=mask is not None)
    if backend == "reference":
        predict_step = transition.predictor()

        def predict(post: FactorizedBelief, t: int) -> FactorizedBelief:
            nxt = predict_step(post, [] if inputs is None else [inputs.at(t)])
            return nxt.drop_side() if diagonal_only else nxt

        update = lambda b, y, m_t: update_unchecked(b, y.mean, y.var, m_t)  # noqa: E731
        return filter_loop(prior, update, predict, observation, mask)
    B, T, m = w.shape
    band = transition.band_parameters()
    dt = w.dtype
    last = lambda x: x.permute(1, 2, 0)  # noqa: E731   (B, T, k) -> (T, k, B)
    q = transition.trans_var.to(dt)
    q3 = torch.cat([q[:m], q.new_zeros(m), q[m:]])           # noise of σ^u, σ^s, σ^l
    if inputs is None:
        inp = torch.cat([q3.new_zeros(2 * m), q3])[None, :, None].expand(T, 5 * m, B)
    else:
        inp = last(torch.cat([inputs.mean, inputs.var_upper + q3[:m], inputs.cov_side, inputs.var_lower + q3[2 * m:]],
                             -1).expand(B, T, 5 * m))
    x0 = torch.cat([prior.mean, prior.var_upper, prior.cov_side, prior.var_lower], -1).expand(B, 5 * m).T
    mu = None if mask is None else mask.T.to(dt)
    X, P = locally_linear_filter_jit(
        x0, last(w), last(observation.var), mu, inp, band.basis.to(dt),
        None if band.weight is None else band.weight.to(dt), None if band.bias is None else band.bias.to(dt),
        band.ident.to(dt), band.bi, band.bj, diagonal_only)

    def belief(x: Tensor) -> FactorizedBelief:      # packed (T, 5m, B) -> batch first
        x = x.permute(2, 0, 1)
        return FactorizedBelief(x[..., :2 * m], x[..., 2 * m:3 * m], x[..., 4 * m:], x[..., 3 * m:4 * m])

    return FilterResult(belief(X[:T]), belief(P), belief(X[1:]))


class RKN(nn.Module):
    r"""Recurrent Kalman Network: ``encoder -> [update, predict]* -> decoder``.

    :meth:`filter` is the recurrent core, the loop of :func:`pgm_wm.filtering.filter_loop` with
    Eq. (rkn-update) and Eq. (rkn-predict). Its ``causes`` are the additive independent causes of
    the predict step that later chapters declare (:data:`Cause`): an action term (Chapter 4), a
    latent task (Chapters 5 and 6). Causes known before the loop are summed into one sequence
    first; state-dependent ones are evaluated inside the loop. :meth:`forward` is the filtering
    model of Chapter 3: it decodes posteriors.

    With a constant transition, diagonal blocks and no state-dependent cause, the loop runs on
    :func:`pgm_wm.factorized.diagonal_factorized_filter` (the elementwise fast path, tested equal
    to the reference loop); a constant transition with band blocks uses
    :func:`pgm_wm.factorized.factorized_filter`.

    ``diagonal_only=True`` is the ablation of Chapter 3: the side covariance :math:`\sigma^s` is
    forced to zero after every predict step (and in the initial belief), so the covariance is
    purely diagonal. The update, Eq. (rkn-update), then has zero gain for the lower half: the
    memory units and their variances are never corrected by an observation and can only follow
    the transition.

    Args:
        encoder: ``obs (..., do) -> DiagGaussian(w, w_var)`` (or a ``(w, w_var)`` pair), e.g.
            :class:`ObservationEncoder`.
        transition: a module with ``predictor()`` and ``latent_obs_dim``, e.g.
            :class:`LocallyLinearTransition` or :class:`pgm_wm.acrkn.NormBoundedTransition`.
        decoder: ``FactorizedBelief -> (mean, var)``, e.g. :class:`BeliefDecoder`.
    """

    def __init__(
        self,
        encoder: nn.Module,
        transition: nn.Module,
        decoder: nn.Module,
        init_var: float = 10.0,
        diagonal_only: bool = False,
    ) -> None:
        super().__init__()
        if init_var <= 0:
            raise ValueError(f"init_var: must be positive, got {init_var}")
        if not callable(getattr(transition, "predictor", None)) or not hasattr(transition, "latent_obs_dim"):
            raise ValueError("transition: expected a transition model with predictor() and latent_obs_dim, "
                             f"got {type(transition).__name__}")
        self.encoder, self.transition, self.decoder = encoder, transition, decoder
        self.latent_obs_dim = transition.latent_obs_dim
        self.init_var = init_var
        self.diagonal_only = bool(diagonal_only)

    def initial_belief(self, batch_shape: Sequence[int], like: Tensor) -> FactorizedBelief:
        """``N(0, init_var · I)`` with zero side covariance, dtype/device of ``like``."""
        return FactorizedBelief.isotropic(batch_shape, self.latent_obs_dim, self.init_var,
                                          dtype=like.dtype, device=like.device)

    def filter(
        self,
        observation: DiagGaussian | Tensor,
        *args: Tensor | None,
        mask: Tensor | None = None,
        causes: Sequence[Cause] = (),
        init: FactorizedBelief | None = None,
        validate: bool = True,
    ) -> FilterResult[FactorizedBelief]:
        """Run update/predict over latent observations ``DiagGaussian(w, w_var)``, ``(B, T, m)``:
        the one filter loop of every model of Chapters 3–6 (a model adds its causes).

        Call as ``filter(DiagGaussian(w, w_var), mask, causes=..., init=...)``; the older form
        ``filter(w, w_var, mask)`` is still accepted. ``mask: (B, T)`` bool, True = observed
        (False: posterior = prior). ``causes``: see the class docstring; a known cause has
        ``mean: (B, T, 2m)``. ``init`` defaults to :meth:`initial_belief`. ``validate=False``
        skips the argument checks (for callers that checked them once at their boundary).

        A loop without state-dependent causes runs as one call of
        :func:`locally_linear_filter` (compiled for CPU tensors) or, for a constant transition
        with diagonal blocks, :func:`pgm_wm.factorized.diagonal_factorized_filter`; otherwise the
        book's loop runs step by step.
        """
        obs, mask = as_observation("observation", observation, args, mask)
        B, T, m = obs.mean.shape if obs.mean.ndim == 3 else (None, None, None)
        if validate:
            check_tensor("observation.mean", obs.mean, 3)
            B, T, m = obs.mean.shape
            if m != self.latent_obs_dim:
                raise ValueError(f"observation.mean: expected latent size {self.latent_obs_dim}, got {m}")
            if T == 0:
                raise ValueError("observation: need at least one time step, got T = 0")
            if mask is not None:
                mask = check_mask("mask", mask, (B, T))
            if init is not None and not isinstance(init, FactorizedBelief):
                raise ValueError(f"init: expected a FactorizedBelief, got {type(init).__name__}")
        prior = self.initial_belief((B,), obs.mean) if init is None else init
        if self.diagonal_only:
            prior = prior.drop_side()
        known = [c for c in causes if isinstance(c, FactorizedBelief)]
        state = [c for c in causes if not isinstance(c, FactorizedBelief)]
        if validate:
            for i, c in enumerate(known):
                if c.latent_obs_dim != m or c.mean.ndim != 3 or tuple(c.mean.shape[:2]) != (B, T):
                    raise ValueError(f"causes: entry {i} must be a FactorizedBelief with mean (B, T, 2m) = "
                                     f"{(B, T, 2 * m)}, got {tuple(c.mean.shape)}")
        inputs = None
        for c in known:  # causes known before the loop: one summed sequence
            inputs = c if inputs is None else inputs + c
        tr = self.transition
        if not state and not self.diagonal_only and getattr(tr, "constant", False) and tr.diagonal_blocks:
            return diagonal_factorized_filter(prior, tr.dense_matrix(prior.mean), tr.trans_var, obs, mask, inputs,
                                              validate=False)
        if not state and hasattr(tr, "band_parameters"):
            return locally_linear_filter(prior, tr, obs, mask, inputs, diagonal_only=self.diagonal_only)
        predict_step = tr.predictor()

        def predict(post: FactorizedBelief, t: int) -> FactorizedBelief:
            step_causes = [c(t, post) for c in state]
            if inputs is not None:
                step_causes.append(inputs.at(t))
            nxt = predict_step(post, step_causes)
            return nxt.drop_side() if self.diagonal_only else nxt

        update = lambda b, y, m_t: update_unchecked(b, y.mean, y.var, m_t)  # noqa: E731
        return filter_loop(prior, update, predict, obs, mask)

    def encode(self, obs: Tensor, mask: Tensor | None = None, *, validate: bool = True) -> DiagGaussian:
        """Encoder, Eq. (rkn-encoder): ``obs: (B, T, obs_dim)`` -> ``DiagGaussian(w, w_var)``, ``(B, T, m)``.

        Missing frames (``mask`` False) are replaced by zeros before encoding, so that whatever
        the data holds there (NaN, stale frames) cannot reach the outputs or the gradients.
        Present frames must be finite (checked unless ``validate=False``).
        """
        if not validate:
            return DiagGaussian(*self.encoder(obs if mask is None else torch.where(
                mask[..., None], obs, torch.zeros((), dtype=obs.dtype, device=obs.device))))
        check_tensor("obs", obs, 3)
        if obs.shape[1] == 0:
            raise ValueError("obs: need at least one time step, got T = 0")
        if obs.ndim != 3:
            raise ValueError(f"obs: expected shape (B, T, d) (images flattened to H*W), got {tuple(obs.shape)}")
        check_same_dtype(("obs",), (obs,))
        check_input_dtype("obs", obs, module_dtype(self))
        if mask is not None:
            mask = check_mask("mask", mask, tuple(obs.shape[:2]))
        obs = zero_missing(obs, mask)
        return DiagGaussian(*self.encoder(obs))

    def forward(self, obs: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Filtering: ``obs: (B, T, obs_dim)`` -> decoded posterior ``(mean, var)`` per step."""
        check_tensor("obs", obs, 3)
        if mask is not None:
            mask = check_mask("mask", mask, tuple(obs.shape[:2]))
        out = self.filter(self.encode(obs, mask), mask=mask, validate=False)   # encode checked the rest
        return self.decoder(out.posterior)


def zero_missing(x: Tensor, mask: Tensor | None, name: str = "obs") -> Tensor:
    """``x: (B, T, d)`` with the steps where ``mask: (B, T)`` is False set to zero (so NaN or stale
    values there never reach a network or a gradient); the remaining entries must be finite."""
    return check_finite(name, zero_padding(x, mask))

r"""Multi-time-scale state-space models (Chapter 6): one :class:`MTS3` class with N levels.

An MTS3 stacks state-space models that run at different rates. The **fast** level is the
ac-RKN of Chapter 4 (:class:`pgm_wm.acrkn.AcRKN`): one predict/update per time step. A **slow**
level (:class:`TaskSSM`) keeps a factorized belief over a latent *task* :math:`l_k` and moves only
once per window of ``window`` = :math:`H` steps. Its belief enters the fast predict step as one
more independent Gaussian cause (Eq. mts3-fast-predict): the fast level is the ac-RKN with the
causes ``[control, C l_k]`` (:meth:`MTS3.causes`),

.. math:: z^-_{t+1} = A z^+_t + b(a_t) + C\mu^-_{l_k},\qquad
          \Sigma^-_{t+1} = A\Sigma^+_tA^\top + Q + C\Sigma^-_{l_k}C^\top ,

where :math:`\mathcal N(\mu^-_{l_k}, \Sigma^-_{l_k})` is the task **prior** of window :math:`k`:
it has seen the abstract observations of windows :math:`1..k-1` and the abstract actions of
windows :math:`1..k` only (the authors' code uses the task posterior here, which has already
absorbed window :math:`k`'s own observations — a look-ahead we do not reproduce).

The slow level per window :math:`k` (all three are Gaussian identities of Chapters 1 and 2):

* **abstract action** (Eq. mts3-abstract-action): each primitive action with a time encoding
  :math:`\tau_t = t/H` is encoded to :math:`(\alpha_{k,t}, \rho_{k,t})` and Bayesian aggregation
  with prior :math:`\mathcal N(0, I)` gives :math:`\mathcal N(\mu_{\alpha_k}, \operatorname{diag}\sigma_{\alpha_k})`
  (:func:`pgm_wm.aggregation.bayesian_aggregation`);
* **task predict** (Eq. mts3-task-predict), marginalizing the previous task and the abstract
  action as independent causes (:func:`task_predict`):

  .. math:: \mu^-_{l_k} = X\mu^+_{l_{k-1}} + Y\mu_{\alpha_k},\qquad
            \Sigma^-_{l_k} = X\Sigma^+_{l_{k-1}}X^\top + Y\Sigma_{\alpha_k}Y^\top + S

  (the authors' code drops :math:`Y\Sigma_{\alpha_k}Y^\top`; we keep it and test it);
* **task update** (Eq. mts3-task-update): the window's observations, each with a time encoding,
  are encoded to abstract observations :math:`(\beta_{k,t}, \nu_{k,t})` with the observation model
  :math:`\beta_{k,t}\mid l_k \sim \mathcal N([I, 0]\,l_k, \operatorname{diag}\nu_{k,t})` and conditioned
  on as a set in precision form (:func:`pgm_wm.aggregation.set_update`).

Fast-scale bookkeeping: the prior of the first step of window :math:`k` is the prior after the
last step of window :math:`k-1` (the fast belief runs on across windows), but with
``detach_fast=True`` (default) gradients are cut there, so gradients between windows flow only
through the slow level.

**What is exact.** All block matrices (:math:`A, X, Y, C`) have diagonal :math:`m\times m` blocks
when ``bandwidth=0`` (the default here). Then every predict step maps a factorized belief to a
factorized belief exactly, the updates are exact (Chapter 3 and Chapter 2), and Bayesian
aggregation is exact. With ``bandwidth > 0`` the predict steps keep the exact diagonals of each
block and drop the rest (the RKN's approximation). One approximation is structural and stays:
the fast predict treats the task and the fast state as *independent* causes at every step, as
if the task were drawn afresh from its prior at each step; inside a window the true posterior
would correlate :math:`z` and :math:`l`. The slow level, not the fast one, learns about the task.

**N levels**: a list of task levels with windows :math:`H_1 < H_2 < \dots` (each dividing the
next). Level :math:`i` predicts once per window of :math:`H_i` steps, conditioned on the current
*prior* of level :math:`i+1` through its own matrix :math:`C_i` (one more cause in
Eq. mts3-task-predict), and is updated with the abstract observations of its window. With no
task level the model is the ac-RKN; with one it is the two-level MTS3 of the thesis.

Training uses imputation at both scales: :func:`pgm_wm.training.observation_mask` hides single steps and
whole windows. :func:`pgm_wm.evaluation.evaluate_open_loop` gives long-horizon predictions after a context and
their sliding-window metrics (:mod:`pgm_wm.metrics`).

Implementation notes. The slow levels never look at the fast beliefs, so :class:`MTS3` first
runs the slow level over all windows, then the fast level (:func:`run_fast_level`). Because the
fast gradients are cut at window boundaries anyway, the fast level can be run as one pass
without gradients (to get each window's initial belief) followed by *all windows in parallel*
as a batch — same values and gradients, a graph only :math:`H` steps deep. With diagonal blocks
the fast loop runs on :func:`pgm_wm.factorized.diagonal_factorized_filter` (compiled for CPU
tensors, with a hand-written backward pass), and an unconditioned slow level with a constant
:math:`X` runs as one such filter over its windows (:func:`slow_level_filter`: a window's set
update is one update with the summed precision). Both are tested equal to the explicit loops,
values and gradients (Section 6.3.6).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor, nn

from ._checks import check_last_dims
from .acrkn import AcRKN, DifferenceReadout, MLPControl, check_sequences
from .aggregation import BayesianContextEncoder, SetEncoder, precision_sums, set_update
from .beliefs import DiagGaussian, FactorizedBelief
from .factorized import as_observation, diagonal_factorized_filter, factorized_predict, linear_cause
from .filtering import FilterResult
from .rkn import BeliefDecoder, BlockMatrix, Cause, LocallyLinearTransition, ObservationEncoder, zero_missing
from .datasets.windows import pad_to_windows, to_windows

__all__ = [
    "time_encoding",
    "BlockMatrix",
    "set_block_init",
    "decouple_halves",
    "run_fast_level",
    "task_predict",
    "TaskSSM",
    "MTS3Output",
    "MTS3",
    "build_fast_acrkn",
    "build_mts3",
    "build_hierarchical_mts3",
]


# ----------------------------------------------------------------------------- windows
def time_encoding(window: int, like: Tensor) -> Tensor:
    r"""Relative position inside a window, :math:`\tau_t = t / H` for :math:`t = 0..H-1`: ``(H, 1)``."""
    if window <= 0:
        raise ValueError(f"window: must be positive, got {window}")
    return (torch.arange(window, dtype=like.dtype, device=like.device) / window).unsqueeze(-1)


def _with_time(x: Tensor) -> Tensor:
    """Append :func:`time_encoding` to windows ``x: (B, K, H, d)`` -> ``(B, K, H, d + 1)``."""
    tau = time_encoding(x.shape[-2], x).expand(*x.shape[:-1], 1)
    return torch.cat([x, tau], dim=-1)


# ----------------------------------------------------------------------------- block matrices
def set_block_init(matrix: BlockMatrix, init: Sequence[float]) -> BlockMatrix:
    r"""Set a single (``num = 1``) :class:`pgm_wm.rkn.BlockMatrix` — e.g. a constant transition —
    to :math:`[[d_{11}I, d_{12}I], [d_{21}I, d_{22}I]]`.

    Accounts for the identity that :class:`pgm_wm.rkn.LocallyLinearTransition` adds to the
    diagonal blocks when ``add_identity`` is set. Returns ``matrix`` (modified in place).
    """
    if matrix.num != 1:
        raise ValueError(f"transition: expected num_basis=1, got {matrix.num}")
    if len(init) != 4:
        raise ValueError(f"init: expected four numbers (d11, d12, d21, d22), got {init!r}")
    eye = torch.eye(matrix.m, dtype=matrix.basis_11.dtype)
    shift = 1.0 if getattr(matrix, "add_identity", False) else 0.0
    with torch.no_grad():
        matrix.basis_11.copy_(((float(init[0]) - shift) * eye)[None])
        matrix.basis_12.copy_((float(init[1]) * eye)[None])
        matrix.basis_21.copy_((float(init[2]) * eye)[None])
        matrix.basis_22.copy_(((float(init[3]) - shift) * eye)[None])
    return matrix


def decouple_halves(matrix: BlockMatrix) -> BlockMatrix:
    r"""Fix :math:`M_{12} = M_{21} = 0` (zero and frozen) in a :class:`pgm_wm.rkn.BlockMatrix`
    (e.g. a transition).

    With decoupled transitions and decoupled causes the side covariance :math:`\sigma^s` stays 0:
    the belief is diagonal, the update never reaches the lower (memory) half — the
    "no memory half" ablation. Returns ``matrix`` (modified in place).
    """
    with torch.no_grad():
        matrix.basis_12.zero_()
        matrix.basis_21.zero_()
    matrix.basis_12.requires_grad_(False)
    matrix.basis_21.requires_grad_(False)
    return matrix


def task_predict(
    post: FactorizedBelief,
    X: Tensor | tuple[Tensor, Tensor, Tensor, Tensor],
    S: Tensor,
    Y: Tensor | None = None,
    alpha: DiagGaussian | Tensor | None = None,
    alpha_var: Tensor | None = None,
    extra_causes: Sequence[FactorizedBelief] = (),
) -> FactorizedBelief:
    r"""Slow-scale predict, Eq. (mts3-task-predict):

    .. math:: \mu^-_{l_k} = X\mu^+_{l_{k-1}} + Y\mu_{\alpha_k},\qquad
              \Sigma^-_{l_k} = X\Sigma^+_{l_{k-1}}X^\top + Y\operatorname{diag}(\sigma_{\alpha_k})Y^\top + S,

    plus any ``extra_causes`` (the :math:`C_i l^{(i+1)}` term of a level below another).

    Args:
        post: posterior of the previous window, mean ``(..., 2m)``.
        X: ``(2m, 2m)`` or its four ``(m, m)`` blocks. S: noise variances ``(2m,)``, >= 0.
        Y: dense ``(2m, d_alpha)`` (``None``: no abstract action).
        alpha: the abstract action ``DiagGaussian(mean, var)``, ``(..., d_alpha)`` (or the older
            ``alpha_mean, alpha_var`` pair).
    """
    if isinstance(X, Tensor):
        m = post.latent_obs_dim
        X = (X[..., :m, :m], X[..., :m, m:], X[..., m:, :m], X[..., m:, m:])
    causes = list(extra_causes)
    if Y is not None:
        if alpha is None:
            raise ValueError("alpha: the abstract action is required when Y is given")
        causes.insert(0, linear_cause(Y, alpha if isinstance(alpha, DiagGaussian) else DiagGaussian(alpha, alpha_var)))
    return factorized_predict(post, *X, S, causes, validate=False)


# ----------------------------------------------------------------------------- the slow level
class TaskSSM(nn.Module):
    r"""One slow level of an MTS3: a factorized SSM over the task :math:`l_k\in\mathbb R^{2m}`,
    stepped once per window of ``window`` fast steps.

    Parts: ``obs_encoder`` (:class:`pgm_wm.aggregation.SetEncoder`,
    :math:`[o_{k,t}, \tau_t]\mapsto(\beta_{k,t}, \nu_{k,t})`), ``action_encoder``
    (:class:`pgm_wm.aggregation.BayesianContextEncoder`, :math:`[a_{k,t}, \tau_t]\mapsto
    \mathcal N(\mu_{\alpha_k}, \sigma_{\alpha_k})`, omitted with ``use_actions=False``), the task
    transition :math:`X` with noise :math:`S` (a constant
    :class:`pgm_wm.rkn.LocallyLinearTransition`), :math:`Y` and, if ``conditioned``, the matrix
    :math:`C_i` through which the level above acts on this one (both :class:`pgm_wm.rkn.BlockMatrix`).

    Initial values (a documented choice): :math:`X = [[0, 0.2I], [-0.2I, 0]]` as in the authors'
    public code (spectral radius 0.2: an unobserved task relaxes within a window or two towards
    what the abstract actions say; training may lengthen that memory — on our validation data
    this started better than a slowly relaxing :math:`X` with radius 0.9), :math:`Y = 0.2 I`,
    :math:`C_i = 0.2 I`, :math:`S = 0.1`, initial belief :math:`\mathcal N(0, 10 I)` with zero side
    covariance.

    Args:
        obs_dim, action_dim: sizes of :math:`o` and :math:`a`. latent_dim: :math:`m` (task state ``2m``).
        window: :math:`H`, fast steps per slow step. hidden: hidden sizes of both set encoders.
        bandwidth: band half-width of the blocks of :math:`X, Y, C_i` (0 = diagonal, exact).
        use_actions: with an abstract action (False: the "no action abstraction" ablation).
        conditioned: has a level above it (gets :math:`C_i`).
        init_var, trans_var_init, X_init, Y_init, C_init: initial values (see above).
        decoupled: off-diagonal blocks fixed at zero (the diagonal-covariance ablation).
        min_var: variance floor of the set encoders.
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        latent_dim: int,
        window: int,
        hidden: Sequence[int] = (32,),
        bandwidth: int = 0,
        use_actions: bool = True,
        conditioned: bool = False,
        init_var: float = 10.0,
        trans_var_init: float = 0.1,
        X_init: Sequence[float] = (0.0, 0.2, -0.2, 0.0),
        Y_init: Sequence[float] = (0.2, 0.0, 0.0, 0.2),
        C_init: Sequence[float] = (0.2, 0.0, 0.0, 0.2),
        decoupled: bool = False,
        min_var: float = 1e-4,
    ) -> None:
        super().__init__()
        for name, v in (("obs_dim", obs_dim), ("action_dim", action_dim), ("latent_dim", latent_dim),
                        ("window", window)):
            if int(v) <= 0:
                raise ValueError(f"{name}: must be positive, got {v}")
        if init_var <= 0:
            raise ValueError(f"init_var: must be positive, got {init_var}")
        m = latent_dim
        self.obs_dim, self.action_dim, self.latent_obs_dim, self.window = obs_dim, action_dim, m, window
        self.init_var = init_var
        self.obs_encoder = SetEncoder(obs_dim + 1, m, hidden, min_var=min_var)
        self.action_encoder = (BayesianContextEncoder(action_dim + 1, 2 * m, hidden, min_var=min_var)
                               if use_actions else None)
        self.transition = LocallyLinearTransition(m, num_basis=1, bandwidth=bandwidth,
                                                  trans_var_init=trans_var_init, add_identity=False)
        set_block_init(self.transition, X_init)
        if decoupled:
            decouple_halves(self.transition)
        self.action_matrix = BlockMatrix(m, bandwidth, Y_init, decoupled) if use_actions else None
        self.above_matrix = BlockMatrix(m, bandwidth, C_init, decoupled) if conditioned else None

    @property
    def use_actions(self) -> bool:
        return self.action_encoder is not None

    @property
    def filters_as_one_run(self) -> bool:
        """True if all windows of this level can be filtered by one run of
        :func:`pgm_wm.factorized.diagonal_factorized_filter` (:func:`slow_level_filter`): not
        conditioned on a level above, :math:`X` constant with diagonal blocks."""
        return self.above_matrix is None and self.transition.constant and self.transition.diagonal_blocks

    def initial_belief(self, batch_shape: Sequence[int], like: Tensor) -> FactorizedBelief:
        """:math:`\\mathcal N(0, \\text{init\\_var}\\, I)` with zero side covariance."""
        return FactorizedBelief.isotropic(batch_shape, self.latent_obs_dim, self.init_var,
                                          dtype=like.dtype, device=like.device)

    def encode_observations(self, obs_windows: Tensor) -> DiagGaussian:
        r"""Abstract observations :math:`(\beta_{k,t}, \nu_{k,t})`: ``(B, K, H, do) -> DiagGaussian (B, K, H, m)``.

        Pass observations that are zero where missing; the mask is applied in :meth:`update`."""
        check_last_dims("obs_windows", obs_windows, (self.window, self.obs_dim))
        return self.obs_encoder(_with_time(obs_windows))

    def encode_actions(self, action_windows: Tensor, present: Tensor | None = None) -> DiagGaussian | None:
        r"""Abstract actions, Eq. (mts3-abstract-action): ``(B, K, H, da) -> DiagGaussian (B, K, 2m)``;
        ``present: (B, K, H)`` marks real (non-padding) steps. ``None`` without actions."""
        if self.action_encoder is None:
            return None
        check_last_dims("action_windows", action_windows, (self.window, self.action_dim))
        return self.action_encoder(_with_time(action_windows), present)

    def predict(
        self,
        post: FactorizedBelief,
        alpha: DiagGaussian | tuple[Tensor, Tensor] | None,
        above: FactorizedBelief | None = None,
    ) -> FactorizedBelief:
        """Task predict, Eq. (mts3-task-predict), with the abstract action ``alpha`` (a
        ``DiagGaussian``, ``(B, 2m)``) and, for a conditioned level, the prior of the level above."""
        extra: list[FactorizedBelief] = []
        if self.above_matrix is not None:
            if above is None:
                raise ValueError("above: this level is conditioned on the level above; pass its prior")
            extra.append(self.above_matrix.cause(above))
        elif above is not None:
            raise ValueError("above: this level was built with conditioned=False")
        X = self.transition.dense_matrix(post.mean)
        S = self.transition.trans_var
        if self.action_matrix is None:
            return task_predict(post, X, S, extra_causes=extra)
        if alpha is None:
            raise ValueError("alpha: this level uses abstract actions; pass DiagGaussian(mean, var)")
        return task_predict(post, X, S, self.action_matrix.dense(), DiagGaussian(*alpha), extra_causes=extra)

    def update(self, prior: FactorizedBelief, observation: DiagGaussian | Tensor, *args: Tensor | None,
               mask: Tensor | None = None) -> FactorizedBelief:
        """Task update, Eq. (mts3-task-update): precision-form set conditioning
        (:func:`pgm_wm.aggregation.set_update`) on the window's abstract observations
        ``DiagGaussian(beta, beta_var)`` with ``(B, H, m)``, ``mask: (B, H)`` (the older
        ``update(prior, beta, beta_var, mask)`` is accepted too)."""
        obs, mask = as_observation("observation", observation, args, mask)
        return set_update(prior, obs, mask, validate=False)


def slow_level_filter(level: TaskSSM, beta: DiagGaussian, alpha: DiagGaussian | None, observed: Tensor,
                      init: FactorizedBelief) -> tuple[FactorizedBelief, FactorizedBelief]:
    r"""All windows of an unconditioned task level at once: the priors and posteriors
    :math:`p(l_k\mid\beta_{<k}, \alpha_{\le k})`, :math:`p(l_k\mid\beta_{\le k}, \alpha_{\le k})`
    (``(B, K, 2m)`` each) from ``beta: (B, K, H, m)``, ``observed: (B, K, H)``, the abstract
    actions ``alpha: (B, K, 2m)`` (or ``None``) and the initial belief ``init``.

    The set update of a window, Eq. (mts3-task-update), only adds the summed precision
    :math:`\lambda_k = \sum_t m_{k,t}\,\nu_{k,t}^{\ominus}` to the upper precision block and
    :math:`\sum_t m_{k,t}\,\beta_{k,t}\oslash\nu_{k,t}` to the information, so it equals **one**
    factorized update (Eq. rkn-update) with the observation
    :math:`\bar\beta_k = \lambda_k^{\ominus}\odot\sum_t m_{k,t}\,\beta_{k,t}\oslash\nu_{k,t}` of
    variance :math:`\lambda_k^{\ominus}` (a window without observations is a missing step). The
    task predict, Eq. (mts3-task-predict), is the factorized predict with :math:`X, S` and the
    abstract action's cause :math:`Y\alpha_{k+1}` known before the loop. So the level is the
    factorized filter of Chapter 3 over windows, started at the first prior
    :math:`p(l_1\mid\alpha_1)`; with diagonal blocks of :math:`X` it runs compiled
    (:func:`pgm_wm.factorized.diagonal_factorized_filter`). Tested equal to the window loop of
    :meth:`MTS3.run_task_levels` (values and gradients).
    """
    if not level.filters_as_one_run:
        raise ValueError("level: needs an unconditioned level with a constant X with diagonal blocks")
    # the set's two sufficient statistics (Chapter 2), centred at 0: λ_k and Σ_t m β / ν
    zero_center = beta.mean.new_zeros(beta.mean.shape[:-2] + beta.mean.shape[-1:])          # (B, K, m)
    lam, info = precision_sums(beta.mean, beta.var, observed, zero_center)
    present = observed.any(-1)                                                      # (B, K)
    lam_safe = torch.where(present.unsqueeze(-1), lam, torch.ones_like(lam))
    summary = DiagGaussian(info / lam_safe, lam_safe.reciprocal())
    first = level.predict(init, None if alpha is None else alpha.map(lambda x: x[:, 0]))
    inputs = None
    if alpha is not None:                      # the cause of window k + 1, known before the loop
        cause = linear_cause(level.action_matrix.dense(), alpha)
        inputs = FactorizedBelief.cat([cause.map(lambda x: x[:, 1:]), cause.map(lambda x: torch.zeros_like(x[:, :1]))])
    tr = level.transition
    run = diagonal_factorized_filter(first, tr.dense_matrix(init.mean), tr.trans_var, summary, present, inputs,
                                     validate=False)
    return run.prior, run.posterior


# ----------------------------------------------------------------------------- the fast level
def run_fast_level(fast: AcRKN, observation: DiagGaussian, observed: Tensor, causes: Sequence[FactorizedBelief],
                   window: int, detach_fast: bool = True, parallel_windows: bool = True) -> FilterResult:
    r"""Run the fast level over ``K`` windows of ``window`` steps through its filter path
    (:meth:`pgm_wm.acrkn.AcRKN.latent_filter`) with the given causes, all known before the loop
    (``(B, K * H, ·)`` sequences: the fast level's own :meth:`pgm_wm.acrkn.AcRKN.causes` and the
    window task cause :math:`C l_k` repeated over its window).

    Args:
        fast: the fast :class:`pgm_wm.acrkn.AcRKN` (its causes known in advance).
        observation: encoded ``DiagGaussian(w, w_var)`` (:meth:`pgm_wm.acrkn.AcRKN.encode`),
            ``(B, K * H, m)``; observed: ``(B, K * H)`` bool.
        detach_fast: cut gradients of the fast belief at window boundaries.
        parallel_windows: with ``detach_fast`` and gradients enabled, first run all windows in
            order **without** gradients (one run over their steps) to get each window's initial
            belief, then run all windows at once as a batch of ``B * K`` sequences of ``H`` steps.
            Values and gradients equal the sequential run (the initial beliefs are detached
            anyway) at a fraction of the cost: the recorded graph is ``H`` steps deep instead of
            ``K * H``.

    Returns the fast beliefs ``(B, K * H, ...)``. The prior of the first step of window ``k`` is the
    prior after the last step of window ``k - 1``.
    """
    B, Tp = observed.shape
    H = window
    K = Tp // H
    if Tp != K * H:
        raise ValueError(f"observed: {Tp} steps are not a multiple of window={H}")
    m = fast.latent_obs_dim
    for i, c in enumerate(causes):
        if not isinstance(c, FactorizedBelief) or tuple(c.mean.shape) != (B, Tp, 2 * m):
            raise ValueError(f"causes: entry {i} must be a FactorizedBelief sequence with mean {(B, Tp, 2 * m)}")

    def run(sel: Callable[[Tensor], Tensor], init: FactorizedBelief | None) -> FilterResult:
        return fast.latent_filter(observation.map(sel), sel(observed), [c.map(sel) for c in causes], init)

    if detach_fast and parallel_windows and torch.is_grad_enabled() and K > 1:
        inits = [fast.initial_belief((B,), observation.mean)]
        with torch.no_grad():      # windows 1..K-1 in order = one run over their steps
            head = run(lambda x: x[:, : (K - 1) * H], inits[0])
            inits += [head.next_prior.at(k * H - 1) for k in range(1, K)]
        init = FactorizedBelief.stack(inits).map(lambda x: x.reshape(B * K, x.shape[-1]))
        out = run(lambda x: x.reshape(B * K, H, *x.shape[2:]), init)
        return out.map(lambda b: b.map(lambda x: x.reshape(B, K * H, x.shape[-1])))
    outs: list[FilterResult] = []
    init: FactorizedBelief | None = None
    for k in range(K):
        out = run(lambda x: x[:, k * H:(k + 1) * H], init)
        last = out.next_prior.at(-1)
        init = last.detach() if detach_fast else last
        outs.append(out)
    return FilterResult(*(FactorizedBelief.cat([getattr(o, f) for o in outs])
                          for f in ("prior", "posterior", "next_prior")))


@dataclass(frozen=True)
class _Prepared:
    obs: Tensor          # (B, Tp, do), zero where not observed
    actions: Tensor      # (B, Tp, da)
    observed: Tensor     # (B, Tp) bool: observed and not padding
    present: Tensor      # (B, Tp) bool: not padding
    mask: Tensor | None  # the caller's mask (B, T) after checks
    T: int


def _prepare(obs: Tensor, actions: Tensor, mask: Tensor | None, multiple: int,
             obs_dim: int, action_dim: int, model: object | None = None) -> _Prepared:
    mask = check_sequences(obs, actions, mask, obs_dim, action_dim, model=model)
    B, T = obs.shape[:2]
    observed = torch.ones(B, T, dtype=torch.bool, device=obs.device) if mask is None else mask
    obs_in = zero_missing(obs, observed)
    present = torch.ones(B, T, dtype=torch.bool, device=obs.device)
    return _Prepared(pad_to_windows(obs_in, multiple), pad_to_windows(actions, multiple),
                     pad_to_windows(observed, multiple), pad_to_windows(present, multiple), mask, T)


# ----------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class MTS3Output:
    r"""Everything an MTS3 run produced.

    Attributes:
        mean, var: predictions of :math:`o_{t+1}` at index ``t``, ``(B, T, do)``.
        fast: the fast beliefs (:class:`pgm_wm.filtering.FilterResult`), each ``(B, T, ...)``.
        task_priors, task_posteriors: per task level ``i`` (ordered from the level just above the
            fast one), :math:`p(l_k\mid\beta_{<k}, \alpha_{\le k})` and
            :math:`p(l_k\mid\beta_{\le k}, \alpha_{\le k})` with ``mean: (B, K_i, 2m)``.
        abstract_actions: per task level, ``DiagGaussian`` ``(B, K_i, 2m)`` or ``None``.

    ``task_prior``, ``task_posterior``, ``alpha_mean``, ``alpha_var``: those of the first task level.
    """

    mean: Tensor
    var: Tensor
    fast: FilterResult
    task_priors: list[FactorizedBelief]
    task_posteriors: list[FactorizedBelief]
    abstract_actions: list[DiagGaussian | None]

    @property
    def task_prior(self) -> FactorizedBelief:
        return self.task_priors[0]

    @property
    def task_posterior(self) -> FactorizedBelief:
        return self.task_posteriors[0]

    @property
    def alpha_mean(self) -> Tensor | None:
        a = self.abstract_actions[0]
        return None if a is None else a.mean

    @property
    def alpha_var(self) -> Tensor | None:
        a = self.abstract_actions[0]
        return None if a is None else a.var


class MTS3(nn.Module):
    r"""MTS3 with N levels: the fast ac-RKN plus a list of task levels ``levels[0..N-2]`` with
    windows :math:`H_1 < H_2 < \dots`, each a multiple of the previous one. With one task level
    this is the two-level MTS3 of the thesis; with none it is the ac-RKN.

    The fast level is the ac-RKN with one more cause (Eq. mts3-fast-predict): its causes are
    ``fast.causes(actions) + [C l_k]``, the task matrix :math:`C` (``task_matrix``) applied to the
    task **prior** of ``levels[0]`` for the window the step is in. All of them are known before the
    fast loop (the slow levels never look at the fast beliefs), so :meth:`run` first runs the task
    levels over all windows, then the fast level (:func:`run_fast_level`).

    Task scheduling, walking through time in steps of :math:`H_1`: at the start of each of its
    windows level :math:`i` predicts, top-down, conditioned on the current prior of level
    :math:`i+1` (``levels[i].above_matrix``; the top level is unconditioned); at the end of each of
    its windows it is updated, bottom-up, with its window's abstract observations.

    Args:
        fast: the fast level, an :class:`pgm_wm.acrkn.AcRKN` (its readout's ``var_floor`` is the one
            variance floor of the predictions: :func:`build_mts3` sets it).
        levels: a :class:`TaskSSM` (the two-level model) or a sequence of them (bottom to top).
        task_matrix: :math:`C` of Eq. (mts3-fast-predict), a :class:`pgm_wm.rkn.BlockMatrix`
            (required when there is a task level).
        detach_fast: cut the gradient of the fast belief between windows (default True).
        parallel_windows: see :func:`run_fast_level` (same values and gradients, faster training).

    ``forward(obs, actions, mask) -> (mean, var)`` follows the world-model interface (index ``t``
    predicts :math:`o_{t+1}`); :meth:`run` returns all beliefs. ``T`` need not be a multiple of the
    windows: the last window is padded and the padding masked.
    """

    def __init__(self, fast: AcRKN, levels: TaskSSM | Sequence[TaskSSM] = (), task_matrix: BlockMatrix | None = None,
                 detach_fast: bool = True, parallel_windows: bool = True) -> None:
        super().__init__()
        if not isinstance(fast, AcRKN):
            raise ValueError(f"fast: expected an AcRKN, got {type(fast).__name__}")
        if not fast.causes_known_in_advance:
            raise ValueError("fast: the control model must not depend on the state (MLPControl, LinearControl "
                             "or ZeroControl), so that b(a) can be computed for a whole window at once")
        levels = [levels] if isinstance(levels, TaskSSM) else list(levels)
        m = fast.latent_obs_dim
        for i, lev in enumerate(levels):
            if not isinstance(lev, TaskSSM):
                raise ValueError(f"levels: entry {i} is not a TaskSSM")
            if lev.latent_obs_dim != m or lev.obs_dim != fast.obs_dim:
                raise ValueError(f"levels: entry {i} must share latent_obs_dim={m} and obs_dim with the fast level")
            top = i == len(levels) - 1
            if top and lev.above_matrix is not None:
                raise ValueError(f"levels: the top level (entry {i}) must not be conditioned")
            if not top and lev.above_matrix is None:
                raise ValueError(f"levels: entry {i} must be conditioned on the level above (conditioned=True)")
            if i > 0 and (lev.window <= levels[i - 1].window or lev.window % levels[i - 1].window):
                raise ValueError(f"levels: window {lev.window} of entry {i} must be a larger multiple of "
                                 f"{levels[i - 1].window}")
        if levels and (task_matrix is None or task_matrix.m != m):
            raise ValueError(f"task_matrix: required (a BlockMatrix with m={m}) when there are task levels")
        self.fast, self.levels, self.task_matrix = fast, nn.ModuleList(levels), task_matrix
        self.detach_fast, self.parallel_windows = detach_fast, parallel_windows
        self.obs_dim, self.action_dim = fast.obs_dim, fast.action_dim
        self.windows = [lev.window for lev in levels]

    @property
    def slow(self) -> TaskSSM:
        """The task level just above the fast one (the slow level of the two-level model)."""
        if not len(self.levels):
            raise ValueError("slow: this MTS3 has no task level")
        return self.levels[0]

    @property
    def window(self) -> int:
        """:math:`H_1`, the window of the first task level."""
        return self.slow.window

    def run_task_levels(self, p: "_Prepared") -> tuple[list[FactorizedBelief], list[FactorizedBelief],
                                                       list[DiagGaussian | None]]:
        """Eqs. (mts3-abstract-action), (mts3-task-predict), (mts3-task-update) for every level
        and window; returns the stacked priors, posteriors and abstract actions per level."""
        levels = list(self.levels)
        B, Tp = p.obs.shape[:2]
        beta = [lev.encode_observations(to_windows(p.obs, lev.window)) for lev in levels]
        alpha = [lev.encode_actions(to_windows(p.actions, lev.window), to_windows(p.present, lev.window))
                 for lev in levels]
        observed = [to_windows(p.observed, lev.window) for lev in levels]
        post = [lev.initial_belief((B,), p.obs) for lev in levels]
        if len(levels) == 1 and levels[0].filters_as_one_run:
            prior_k, post_k = slow_level_filter(levels[0], beta[0], alpha[0], observed[0], post[0])
            return [prior_k], [post_k], alpha
        prior: list[FactorizedBelief | None] = [None] * len(levels)
        priors: list[list[FactorizedBelief]] = [[] for _ in levels]
        posts: list[list[FactorizedBelief]] = [[] for _ in levels]
        for t0 in range(0, Tp, self.windows[0]):
            for i in reversed(range(len(levels))):  # window starts: top-down predicts
                if t0 % self.windows[i] == 0:
                    k = t0 // self.windows[i]
                    a_k = None if alpha[i] is None else alpha[i][:, k]
                    prior[i] = levels[i].predict(post[i], a_k, prior[i + 1] if i + 1 < len(levels) else None)
                    priors[i].append(prior[i])
            t1 = t0 + self.windows[0]
            for i in range(len(levels)):  # window ends: bottom-up updates
                if t1 % self.windows[i] == 0:
                    k = t1 // self.windows[i] - 1
                    post[i] = levels[i].update(prior[i], beta[i][:, k], mask=observed[i][:, k])
                    posts[i].append(post[i])
        return ([FactorizedBelief.stack(x) for x in priors], [FactorizedBelief.stack(x) for x in posts], alpha)

    def task_cause(self, task_prior: FactorizedBelief) -> FactorizedBelief:
        """The cause :math:`C l_k` of Eq. (mts3-fast-predict) for the window of every step, from the
        first level's priors ``task_prior: (B, K, 2m)``: a ``(B, K * H, 2m)`` sequence."""
        H = self.windows[0]
        return self.task_matrix.cause(task_prior).map(lambda x: x.repeat_interleave(H, dim=1))

    def causes(self, actions: Tensor, task_prior: FactorizedBelief | None) -> list[Cause]:
        """The causes of the fast predict step: the ac-RKN's ``[control]`` plus, with a task level,
        :meth:`task_cause`. MTS3 fast level = ac-RKN + this last cause."""
        return self.fast.causes(actions) + ([] if task_prior is None else [self.task_cause(task_prior)])

    def run(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> MTS3Output:
        """Filter ``obs: (B, T, do)`` with ``actions: (B, T, da)``, ``mask: (B, T)`` (True = observed)."""
        p = _prepare(obs, actions, mask, self.windows[-1] if self.windows else 1, self.obs_dim, self.action_dim, self)
        task_priors, task_posts, alphas = self.run_task_levels(p) if self.windows else ([], [], [])
        causes = self.causes(p.actions, task_priors[0] if task_priors else None)
        window = self.windows[0] if self.windows else p.obs.shape[1]
        w = self.fast.encode(p.obs, validate=False)       # _prepare checked the inputs and zeroed the masked steps
        out = run_fast_level(self.fast, w, p.observed, causes, window, self.detach_fast, self.parallel_windows)
        out = out.map(lambda b: b.map(lambda x: x[:, : p.T]))
        mean, var = self.fast.decode_predictions(out, obs, p.mask)
        return MTS3Output(mean, var, out, task_priors, task_posts, alphas)

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(mean, var)`` each ``(B, T, do)``; index ``t`` predicts ``obs[:, t + 1]``."""
        out = self.run(obs, actions, mask)
        return out.mean, out.var




# ----------------------------------------------------------------------------- builders
FAST_A_INIT = (0.95, 0.2, -0.2, 0.95)


def build_fast_acrkn(obs_dim: int, action_dim: int, latent_obs_dim: int, hidden: Sequence[int] = (32,),
                     bandwidth: int = 0, A_init: Sequence[float] = FAST_A_INIT, decoupled: bool = False,
                     init_var: float = 10.0, trans_var_init: float = 0.1, var_floor: float = 1e-4) -> AcRKN:
    r"""The fast level: an ac-RKN with a constant transition (``num_basis=1``), an MLP control
    model and absolute (not difference) readout.

    :math:`A` starts at :math:`[[0.95I, 0.2I], [-0.2I, 0.95I]]` (spectral radius 0.971 < 1, so
    open-loop predictions over hundreds of steps stay bounded; the RKN's usual
    :math:`[[I, 0.2I], [-0.2I, I]]` has radius 1.02 and grows ~ :math:`1.02^t`).
    """
    m = latent_obs_dim
    transition = LocallyLinearTransition(m, num_basis=1, bandwidth=bandwidth, trans_var_init=trans_var_init)
    set_block_init(transition, A_init)
    if decoupled:
        decouple_halves(transition)
    return AcRKN(ObservationEncoder(obs_dim, m, hidden), transition, MLPControl(action_dim, m, hidden),
                 BeliefDecoder(m, obs_dim, hidden, hidden), init_var=init_var,
                 readout=DifferenceReadout(obs_dim, predict_differences=False, var_floor=var_floor))


def build_mts3(obs_dim: int, action_dim: int, latent_obs_dim: int, window: int, hidden: Sequence[int] = (32,),
               bandwidth: int = 0, use_actions: bool = True, decoupled: bool = False,
               detach_fast: bool = True, min_var: float = 1e-4) -> MTS3:
    """A small 2-level :class:`MTS3` with the defaults documented in :func:`build_fast_acrkn` and
    :class:`TaskSSM`. ``decoupled=True`` gives the diagonal-covariance ("no memory half") ablation,
    ``use_actions=False`` the one without action abstraction."""
    m = latent_obs_dim
    fast = build_fast_acrkn(obs_dim, action_dim, m, hidden, bandwidth, decoupled=decoupled, var_floor=min_var)
    slow = TaskSSM(obs_dim, action_dim, m, window, hidden, bandwidth, use_actions, decoupled=decoupled)
    return MTS3(fast, slow, BlockMatrix(m, bandwidth, decoupled=decoupled), detach_fast)


def build_hierarchical_mts3(obs_dim: int, action_dim: int, latent_obs_dim: int, windows: Sequence[int],
                            hidden: Sequence[int] = (32,), bandwidth: int = 0, detach_fast: bool = True,
                            min_var: float = 1e-4) -> MTS3:
    """An N-level :class:`MTS3` with ``len(windows)`` task levels (N = that + 1)."""
    m = latent_obs_dim
    fast = build_fast_acrkn(obs_dim, action_dim, m, hidden, bandwidth, var_floor=min_var)
    n = len(windows)
    levels = [TaskSSM(obs_dim, action_dim, m, H, hidden, bandwidth, conditioned=i < n - 1)
              for i, H in enumerate(windows)]
    return MTS3(fast, levels, BlockMatrix(m, bandwidth) if n else None, detach_fast)

r"""Multi-time-scale state-space models (Chapter 6): MTS3 with two and with N levels.

An MTS3 stacks state-space models that run at different rates. The **fast** level is the
ac-RKN of Chapter 4 (:class:`pgm_wm.acrkn.AcRKN`): one predict/update per time step. A **slow**
level (:class:`TaskSSM`) keeps a factorized belief over a latent *task* :math:`l_k` and moves only
once per window of ``window`` = :math:`H` steps. Its belief enters the fast predict step as one
more independent Gaussian cause (Eq. mts3-fast-predict),

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
  on as a set in precision form (:func:`pgm_wm.aggregation.set_condition`).

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

**N levels** (:class:`HierarchicalMTS3`): a list of task levels with windows
:math:`H_1 < H_2 < \dots` (each dividing the next). Level :math:`i` predicts once per window of
:math:`H_i` steps, conditioned on the current *prior* of level :math:`i+1` through its own matrix
:math:`C_i` (one more cause in Eq. mts3-task-predict), and is updated with the abstract
observations of its window. With no task level it is the ac-RKN; with one it is :class:`MTS3`.

Training uses imputation at both scales: :func:`pgm_wm.training.observation_mask` hides single steps and
whole windows. :func:`pgm_wm.evaluation.evaluate_open_loop` gives long-horizon predictions after a context and
their sliding-window metrics (:mod:`pgm_wm.metrics`).

Implementation notes. The slow levels never look at the fast beliefs, so :class:`MTS3` first
runs the slow level over all windows, then the fast level (:func:`run_fast_level`). Because the
fast gradients are cut at window boundaries anyway, the fast level can be run as one pass
without gradients (to get each window's initial belief) followed by *all windows in parallel*
as a batch — same values and gradients, a graph only :math:`H` steps deep. With diagonal blocks
the fast loop is :func:`diagonal_filter`, the factorized update/predict written elementwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor, nn

from ._checks import check_last_dims
from .acrkn import AcRKN, LinearControl, MLPControl, ZeroControl, check_sequences
from .aggregation import BayesianContextEncoder, SetEncoder, set_condition
from .factorized import FactorizedBelief, factorized_predict, linear_cause
from .rkn import BeliefDecoder, FilterOutput, LocallyLinearTransition, ObservationEncoder, band_mask
from .datasets.windows import pad_to_windows, to_windows

__all__ = [
    "time_encoding",
    "BlockMatrix",
    "set_block_init",
    "decouple_halves",
    "factorized_linear_cause",
    "diagonal_filter",
    "run_fast_level",
    "task_predict",
    "TaskSSM",
    "MTS3Output",
    "MTS3",
    "HierarchicalOutput",
    "HierarchicalMTS3",
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
class BlockMatrix(nn.Module):
    r"""A learned :math:`2m\times 2m` matrix :math:`M = [[M_{11}, M_{12}], [M_{21}, M_{22}]]` with
    band blocks of half-width ``bandwidth`` (``0``: diagonal blocks, for which pushing a factorized
    belief through :math:`M` is exact). Used for the task matrices :math:`C` and the abstract-action
    matrix :math:`Y`. ``init = (d11, d12, d21, d22)`` sets each block to ``d * I``.
    ``decoupled=True`` fixes :math:`M_{12} = M_{21} = 0` (the diagonal-covariance ablation).
    """

    def __init__(self, m: int, bandwidth: int = 0, init: Sequence[float] = (0.2, 0.0, 0.0, 0.2),
                 decoupled: bool = False) -> None:
        super().__init__()
        if m <= 0:
            raise ValueError(f"m: must be positive, got {m}")
        if len(init) != 4:
            raise ValueError(f"init: expected four numbers (d11, d12, d21, d22), got {init!r}")
        self.m, self.bandwidth, self.decoupled = m, bandwidth, decoupled
        self.register_buffer("band", band_mask(m, bandwidth).to(torch.get_default_dtype()), persistent=False)
        eye = torch.eye(m)
        self.M11 = nn.Parameter(float(init[0]) * eye)
        self.M22 = nn.Parameter(float(init[3]) * eye)
        if decoupled:
            self.register_buffer("M12", torch.zeros(m, m))
            self.register_buffer("M21", torch.zeros(m, m))
        else:
            self.M12 = nn.Parameter(float(init[1]) * eye)
            self.M21 = nn.Parameter(float(init[2]) * eye)

    def blocks(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The four ``(m, m)`` blocks (band-masked)."""
        band = self.band.to(self.M11.dtype)
        return self.M11 * band, self.M12 * band, self.M21 * band, self.M22 * band

    def dense(self) -> Tensor:
        """:math:`M` as a dense ``(2m, 2m)`` matrix."""
        b11, b12, b21, b22 = self.blocks()
        return torch.cat([torch.cat([b11, b12], -1), torch.cat([b21, b22], -1)], -2)

    def cause(self, belief: FactorizedBelief) -> FactorizedBelief:
        """:func:`factorized_linear_cause` of ``belief`` through this matrix."""
        return factorized_linear_cause(belief, *self.blocks())


def set_block_init(transition: LocallyLinearTransition, init: Sequence[float]) -> LocallyLinearTransition:
    r"""Set a constant (``num_basis=1``) transition to :math:`[[d_{11}I, d_{12}I], [d_{21}I, d_{22}I]]`.

    Accounts for the identity that :class:`pgm_wm.rkn.LocallyLinearTransition` adds to the
    diagonal blocks when ``add_identity`` is set. Returns ``transition`` (modified in place).
    """
    if transition.num_basis != 1:
        raise ValueError(f"transition: expected num_basis=1, got {transition.num_basis}")
    if len(init) != 4:
        raise ValueError(f"init: expected four numbers (d11, d12, d21, d22), got {init!r}")
    m = transition.latent_obs_dim
    eye = torch.eye(m, dtype=transition.basis_11.dtype)
    shift = 1.0 if transition.add_identity else 0.0
    with torch.no_grad():
        transition.basis_11.copy_(((float(init[0]) - shift) * eye)[None])
        transition.basis_12.copy_((float(init[1]) * eye)[None])
        transition.basis_21.copy_((float(init[2]) * eye)[None])
        transition.basis_22.copy_(((float(init[3]) - shift) * eye)[None])
    return transition


def decouple_halves(transition: LocallyLinearTransition) -> LocallyLinearTransition:
    r"""Fix :math:`A_{12} = A_{21} = 0` (zero and frozen) in a transition.

    With decoupled transitions and decoupled causes the side covariance :math:`\sigma^s` stays 0:
    the belief is diagonal, the update never reaches the lower (memory) half — the
    "no memory half" ablation. Returns ``transition`` (modified in place).
    """
    with torch.no_grad():
        transition.basis_12.zero_()
        transition.basis_21.zero_()
    transition.basis_12.requires_grad_(False)
    transition.basis_21.requires_grad_(False)
    return transition


def factorized_linear_cause(belief: FactorizedBelief, M11: Tensor, M12: Tensor, M21: Tensor,
                            M22: Tensor) -> FactorizedBelief:
    r"""The cause :math:`M l` of an independent factorized belief :math:`l\sim\mathcal N(\mu,\Sigma)`,
    Eq. (gauss-marginal): mean :math:`M\mu`, covariance the block diagonals of :math:`M\Sigma M^\top`.

    Same algebra as the predict step (:func:`pgm_wm.factorized.factorized_predict` with zero
    noise), so it is exact for diagonal blocks. Used for :math:`C\,l_k` (Eq. mts3-fast-predict).
    Shapes: belief ``(..., 2m)``, blocks ``(..., m, m)``.
    """
    zero = belief.mean.new_zeros(belief.mean.shape[-1])
    return factorized_predict(belief, M11, M12, M21, M22, zero, validate=False)


def task_predict(
    post: FactorizedBelief,
    X: tuple[Tensor, Tensor, Tensor, Tensor],
    S: Tensor,
    Y: Tensor | None = None,
    alpha_mean: Tensor | None = None,
    alpha_var: Tensor | None = None,
    extra_causes: Sequence[FactorizedBelief] = (),
) -> FactorizedBelief:
    r"""Slow-scale predict, Eq. (mts3-task-predict):

    .. math:: \mu^-_{l_k} = X\mu^+_{l_{k-1}} + Y\mu_{\alpha_k},\qquad
              \Sigma^-_{l_k} = X\Sigma^+_{l_{k-1}}X^\top + Y\operatorname{diag}(\sigma_{\alpha_k})Y^\top + S,

    plus any ``extra_causes`` (the :math:`C_i l^{(i+1)}` term of a level below another).

    Args:
        post: posterior of the previous window, mean ``(..., 2m)``.
        X: the four ``(m, m)`` blocks of :math:`X`. S: noise variances ``(2m,)``, >= 0.
        Y: dense ``(2m, d_alpha)`` (``None``: no abstract action). alpha_mean, alpha_var: ``(..., d_alpha)``.
    """
    causes = list(extra_causes)
    if Y is not None:
        if alpha_mean is None or alpha_var is None:
            raise ValueError("alpha_mean: alpha_mean and alpha_var are required when Y is given")
        causes.insert(0, linear_cause(Y, alpha_mean, alpha_var))
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
    :math:`C_i` through which the level above acts on this one.

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

    def initial_belief(self, batch_shape: Sequence[int], like: Tensor) -> FactorizedBelief:
        """:math:`\\mathcal N(0, \\text{init\\_var}\\, I)` with zero side covariance."""
        return FactorizedBelief.isotropic(batch_shape, self.latent_obs_dim, self.init_var,
                                          dtype=like.dtype, device=like.device)

    def encode_observations(self, obs_windows: Tensor) -> tuple[Tensor, Tensor]:
        r"""Abstract observations :math:`(\beta_{k,t}, \nu_{k,t})`: ``(B, K, H, do) -> 2 x (B, K, H, m)``.

        Pass observations that are zero where missing; the mask is applied in :meth:`update`."""
        check_last_dims("obs_windows", obs_windows, (self.window, self.obs_dim))
        return self.obs_encoder(_with_time(obs_windows))

    def encode_actions(self, action_windows: Tensor, present: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        r"""Abstract actions, Eq. (mts3-abstract-action): ``(B, K, H, da) -> (mean, var)`` each
        ``(B, K, 2m)``; ``present: (B, K, H)`` marks real (non-padding) steps. ``None`` without actions."""
        if self.action_encoder is None:
            return None
        check_last_dims("action_windows", action_windows, (self.window, self.action_dim))
        return self.action_encoder(_with_time(action_windows), present)

    def predict(
        self,
        post: FactorizedBelief,
        alpha: tuple[Tensor, Tensor] | None,
        above: FactorizedBelief | None = None,
    ) -> FactorizedBelief:
        """Task predict, Eq. (mts3-task-predict), with the abstract action ``alpha = (mean, var)``
        (``(B, 2m)`` each) and, for a conditioned level, the prior of the level above."""
        extra: list[FactorizedBelief] = []
        if self.above_matrix is not None:
            if above is None:
                raise ValueError("above: this level is conditioned on the level above; pass its prior")
            extra.append(self.above_matrix.cause(above))
        elif above is not None:
            raise ValueError("above: this level was built with conditioned=False")
        X = self.transition.blocks(post.mean)
        S = self.transition.trans_var
        if self.action_matrix is None:
            return task_predict(post, X, S, extra_causes=extra)
        if alpha is None:
            raise ValueError("alpha: this level uses abstract actions; pass (mean, var)")
        return task_predict(post, X, S, self.action_matrix.dense(), alpha[0], alpha[1], extra)

    def update(self, prior: FactorizedBelief, beta: Tensor, beta_var: Tensor, mask: Tensor | None) -> FactorizedBelief:
        """Task update, Eq. (mts3-task-update): precision-form set conditioning on the window's
        abstract observations ``beta, beta_var: (B, H, m)``, ``mask: (B, H)``."""
        return set_condition(prior, beta, beta_var, mask, validate=False)


# ----------------------------------------------------------------------------- the fast level
def _map_belief(b: FactorizedBelief, fn: Callable[[Tensor], Tensor]) -> FactorizedBelief:
    return FactorizedBelief(fn(b.mean), fn(b.var_upper), fn(b.var_lower), fn(b.cov_side))


def _cat_beliefs(beliefs: Sequence[FactorizedBelief], dim: int = -2) -> FactorizedBelief:
    return FactorizedBelief(*(torch.cat([getattr(b, f) for b in beliefs], dim=dim)
                              for f in ("mean", "var_upper", "var_lower", "cov_side")))


def _map_output(out: FilterOutput, fn: Callable[[Tensor], Tensor]) -> FilterOutput:
    return FilterOutput(*(_map_belief(getattr(out, f), fn) for f in ("prior", "posterior", "predicted")))


def _check_fast(fast: AcRKN) -> None:
    if not isinstance(fast, AcRKN):
        raise ValueError(f"fast: expected an AcRKN, got {type(fast).__name__}")
    if not isinstance(fast.control, (MLPControl, LinearControl, ZeroControl)):
        raise ValueError("fast: the control model must not depend on the state (MLPControl, LinearControl "
                         "or ZeroControl), so that b(a) can be computed for a whole window at once")


def diagonal_filter(
    init: FactorizedBelief,
    w: Tensor,
    w_var: Tensor,
    mask: Tensor,
    A_diag: Sequence[Tensor],
    trans_var: Tensor,
    inputs: Tensor,
    task: FactorizedBelief,
) -> FilterOutput:
    r"""The RKN filter loop (update, then predict) for a constant transition with **diagonal**
    blocks, written elementwise. Same equations as :func:`pgm_wm.factorized.factorized_update`
    (Eq. rkn-update) and :func:`pgm_wm.factorized.factorized_predict` (Eq. rkn-predict), exact for
    this structure, tested equal to them, and about 3x fewer tensor operations per step.

    The update is written with :math:`g = m_t\oslash(\sigma^u + \sigma^{obs})` (:math:`m_t\in\{0,1\}`
    the mask), so a missing observation (:math:`g = 0`) leaves the belief unchanged without a branch
    and an exact observation (:math:`\sigma^{obs} = 0`) is handled too:

    .. math:: z^{u+} = z^u + \sigma^u\odot g\odot(w - z^u),\quad
              z^{l+} = z^l + \sigma^s\odot g\odot(w - z^u),\quad
              \sigma^{u+} = \sigma^u\odot(1 - \sigma^u\odot g),\quad
              \sigma^{s+} = \sigma^s\odot(1 - \sigma^u\odot g),\quad
              \sigma^{l+} = \sigma^l - \sigma^s\odot\sigma^s\odot g .

    The predict adds the known inputs ``inputs: (N, T, 2m)`` and one constant independent cause
    ``task`` (mean ``(N, 2m)`` added to the mean, its variances to the noise).

    Args:
        init: prior of the first step, batch ``(N,)``. w, w_var: ``(N, T, m)``. mask: ``(N, T)`` bool.
        A_diag: the diagonals ``(a11, a12, a21, a22)`` of the blocks, each ``(m,)``. trans_var: ``(2m,)``.
    """
    m = init.latent_obs_dim
    a11, a12, a21, a22 = A_diag
    T = w.shape[1]
    mf = mask.to(w.dtype).unsqueeze(-1)
    w = torch.where(mask.unsqueeze(-1), w, torch.zeros((), dtype=w.dtype, device=w.device))
    mean_in = inputs + task.mean.unsqueeze(-2)
    in_u, in_l = mean_in[..., :m].unbind(1), mean_in[..., m:].unbind(1)
    noise_u = trans_var[:m] + task.var_upper
    noise_l = trans_var[m:] + task.var_lower
    noise_s = task.cov_side
    # coefficients of the covariance predict, Eq. (rkn-predict) with diagonal blocks
    cuu, cus, cul = a11 * a11, 2.0 * a11 * a12, a12 * a12
    clu, cls, cll = a21 * a21, 2.0 * a21 * a22, a22 * a22
    csu, css, csl = a21 * a11, a22 * a11 + a21 * a12, a22 * a12
    zu, zl = init.mean_upper, init.mean_lower
    su, sl, ss = init.var_upper, init.var_lower, init.cov_side
    ws, rs, ms = w.unbind(1), w_var.unbind(1), mf.unbind(1)
    rec: list[list[Tensor]] = [[] for _ in range(15)]
    for t in range(T):
        g = ms[t] / (su + rs[t])
        ge = g * (ws[t] - zu)
        zu_p, zl_p = zu + su * ge, zl + ss * ge
        keep = 1.0 - su * g  # = σobs / (σu + σobs) where observed, 1 where not
        su_p, ss_p, sl_p = su * keep, ss * keep, sl - ss * ss * g
        zu_n = a11 * zu_p + a12 * zl_p + in_u[t]
        zl_n = a21 * zu_p + a22 * zl_p + in_l[t]
        su_n = cuu * su_p + cus * ss_p + cul * sl_p + noise_u
        sl_n = clu * su_p + cls * ss_p + cll * sl_p + noise_l
        ss_n = csu * su_p + css * ss_p + csl * sl_p + noise_s
        for lst, x in zip(rec, (zu, zl, su, sl, ss, zu_p, zl_p, su_p, sl_p, ss_p, zu_n, zl_n, su_n, sl_n, ss_n)):
            lst.append(x)
        zu, zl, su, sl, ss = zu_n, zl_n, su_n, sl_n, ss_n
    st = [torch.stack(lst, dim=1) for lst in rec]

    def belief(i: int) -> FactorizedBelief:
        return FactorizedBelief(torch.cat([st[i], st[i + 1]], dim=-1), st[i + 2], st[i + 3], st[i + 4])

    return FilterOutput(belief(0), belief(5), belief(10))


def _window_filter(fast: AcRKN, w: Tensor, w_var: Tensor, observed: Tensor, b: Tensor, task: FactorizedBelief,
                   init: FactorizedBelief | None) -> FilterOutput:
    r"""The fast level over one window (or a batch of windows), Eq. (mts3-fast-predict): the control
    term :math:`b(a_t)` (known, ``b: (N, H, 2m)``) and the task cause :math:`C l_k` (``task``, batch
    ``(N,)``, constant over the window) enter every predict step as independent causes.
    Diagonal blocks: :func:`diagonal_filter`; otherwise the RKN's general loop."""
    tr = fast.transition
    if init is None:
        init = fast.rkn.initial_belief(w.shape[:1], w)
    if tr.num_basis == 1 and tr.bandwidth == 0 and not getattr(fast.rkn, "diagonal_only", False):
        blocks = [torch.diagonal(x) for x in tr.blocks(init.mean)]
        return diagonal_filter(init, w, w_var, observed, blocks, tr.trans_var, b, task)
    means = b + task.mean.unsqueeze(-2)

    def causes_fn(t: int, post: FactorizedBelief) -> list[FactorizedBelief]:
        return [FactorizedBelief(means[:, t], task.var_upper, task.var_lower, task.cov_side)]

    return fast.rkn.filter(w, w_var, observed, causes_fn, init)


def run_fast_level(fast: AcRKN, obs: Tensor, actions: Tensor, observed: Tensor, task: FactorizedBelief,
                   window: int, detach_fast: bool = True, parallel_windows: bool = True) -> FilterOutput:
    r"""Run the fast level over ``K`` windows, conditioned window by window on the task causes.

    Args:
        fast: the fast :class:`pgm_wm.acrkn.AcRKN` (state-independent control model).
        obs: ``(B, K * H, do)``, zero where not observed; actions: ``(B, K * H, da)``;
        observed: ``(B, K * H)`` bool.
        task: the cause :math:`C l_k` for every window, batch ``(B, K)``.
        detach_fast: cut gradients of the fast belief at window boundaries.
        parallel_windows: with ``detach_fast`` and gradients enabled, first run all windows in
            order **without** gradients to get each window's initial belief, then run all windows
            at once as a batch of ``B * K`` sequences of ``H`` steps. Values and gradients equal the
            sequential run (the initial beliefs are detached anyway) at a fraction of the cost:
            the recorded graph is ``H`` steps deep instead of ``K * H``.

    Returns the fast beliefs ``(B, K * H, ...)``. The prior of the first step of window ``k`` is the
    prior after the last step of window ``k - 1``.
    """
    B, Tp = obs.shape[:2]
    H = window
    K = Tp // H
    if Tp != K * H or tuple(task.mean.shape[:2]) != (B, K):
        raise ValueError(f"task: expected batch (B, K) = {(B, K)} for {Tp} steps and window {H}")
    zeros = actions.new_zeros(*actions.shape[:-1], 2 * fast.latent_obs_dim)
    b = fast.control(actions, zeros)
    w, w_var = fast.encoder(obs)
    at = lambda k: _map_belief(task, lambda x: x[:, k])  # noqa: E731
    sl = lambda x, k: x[:, k * H:(k + 1) * H]  # noqa: E731
    if detach_fast and parallel_windows and torch.is_grad_enabled() and K > 1:
        inits = [fast.rkn.initial_belief((B,), w)]
        with torch.no_grad():
            for k in range(K - 1):
                out = _window_filter(fast, sl(w, k), sl(w_var, k), sl(observed, k), sl(b, k), at(k), inits[-1])
                inits.append(out.predicted.at(-1))
        init = _map_belief(FactorizedBelief.stack(inits), lambda x: x.reshape(B * K, x.shape[-1]))
        flat = lambda x: x.reshape(B * K, H, *x.shape[2:])  # noqa: E731
        task_flat = _map_belief(task, lambda x: x.reshape(B * K, x.shape[-1]))
        out = _window_filter(fast, flat(w), flat(w_var), flat(observed), flat(b), task_flat, init)
        return _map_output(out, lambda x: x.reshape(B, K * H, x.shape[-1]))
    outs: list[FilterOutput] = []
    init: FactorizedBelief | None = None
    for k in range(K):
        out = _window_filter(fast, sl(w, k), sl(w_var, k), sl(observed, k), sl(b, k), at(k), init)
        last = out.predicted.at(-1)
        init = last.detach() if detach_fast else last
        outs.append(out)
    return FilterOutput(*(_cat_beliefs([getattr(o, f) for o in outs]) for f in ("prior", "posterior", "predicted")))


@dataclass(frozen=True)
class _Prepared:
    obs: Tensor          # (B, Tp, do), zero where not observed
    actions: Tensor      # (B, Tp, da)
    observed: Tensor     # (B, Tp) bool: observed and not padding
    present: Tensor      # (B, Tp) bool: not padding
    mask: Tensor | None  # the caller's mask (B, T) after checks
    T: int


def _prepare(obs: Tensor, actions: Tensor, mask: Tensor | None, multiple: int,
             obs_dim: int, action_dim: int) -> _Prepared:
    mask = check_sequences(obs, actions, mask, obs_dim, action_dim)
    B, T = obs.shape[:2]
    observed = torch.ones(B, T, dtype=torch.bool, device=obs.device) if mask is None else mask
    obs_in = torch.where(observed[..., None], obs, torch.zeros((), dtype=obs.dtype, device=obs.device))
    present = torch.ones(B, T, dtype=torch.bool, device=obs.device)
    return _Prepared(pad_to_windows(obs_in, multiple), pad_to_windows(actions, multiple),
                     pad_to_windows(observed, multiple), pad_to_windows(present, multiple), mask, T)


def _finish(fast: AcRKN, out: FilterOutput, obs: Tensor, p: _Prepared, min_var: float
            ) -> tuple[FilterOutput, Tensor, Tensor]:
    """Cut the padding and decode the predicted beliefs; add the variance floor ``min_var``."""
    out = _map_output(out, lambda x: x[:, : p.T])
    mean, var = fast.decode_predictions(out, obs, p.mask)
    return out, mean, var + min_var if min_var else var


# ----------------------------------------------------------------------------- the 2-level model
@dataclass(frozen=True)
class MTS3Output:
    """Everything a 2-level MTS3 run produced.

    Attributes:
        mean, var: predictions of :math:`o_{t+1}` at index ``t``, ``(B, T, do)``.
        fast: the fast beliefs (``prior``, ``posterior``, ``predicted``), each ``(B, T, ...)``.
        task_prior: :math:`p(l_k\\mid\\beta_{<k}, \\alpha_{\\le k})`, ``mean: (B, K, 2m)``.
        task_posterior: :math:`p(l_k\\mid\\beta_{\\le k}, \\alpha_{\\le k})`, ``mean: (B, K, 2m)``.
        alpha_mean, alpha_var: abstract actions ``(B, K, 2m)`` (``None`` without actions).
    """

    mean: Tensor
    var: Tensor
    fast: FilterOutput
    task_prior: FactorizedBelief
    task_posterior: FactorizedBelief
    alpha_mean: Tensor | None
    alpha_var: Tensor | None


class MTS3(nn.Module):
    """Two-level MTS3: a fast ac-RKN conditioned, window by window, on a slow task SSM.

    Args:
        fast: the fast level, an :class:`pgm_wm.acrkn.AcRKN` with a state-independent control model.
        slow: the slow level, a :class:`TaskSSM` (not ``conditioned``); its ``window`` is :math:`H`.
        task_matrix: :math:`C` of Eq. (mts3-fast-predict), a :class:`BlockMatrix`.
        detach_fast: cut the gradient of the fast belief between windows (default True).
        parallel_windows: see :func:`run_fast_level` (same values and gradients, faster training).
        min_var: a floor added to the predictive variance (``0`` = none; the builders use
            ``1e-4`` in normalized units), which keeps the NLL bounded when the decoder's variance
            head collapses early in training.

    ``forward(obs, actions, mask) -> (mean, var)`` follows the world-model interface of
    :mod:`pgm_wm.baselines` (index ``t`` predicts :math:`o_{t+1}`); :meth:`run` returns all beliefs.
    ``T`` need not be a multiple of :math:`H`: the last window is padded and the padding masked.
    """

    def __init__(self, fast: AcRKN, slow: TaskSSM, task_matrix: BlockMatrix, detach_fast: bool = True,
                 parallel_windows: bool = True, min_var: float = 0.0) -> None:
        super().__init__()
        _check_fast(fast)
        if min_var < 0:
            raise ValueError(f"min_var: must be >= 0, got {min_var}")
        self.min_var = float(min_var)
        if not isinstance(slow, TaskSSM) or slow.above_matrix is not None:
            raise ValueError("slow: expected an unconditioned TaskSSM (the top level)")
        m = fast.latent_obs_dim
        if slow.latent_obs_dim != m or task_matrix.m != m:
            raise ValueError(f"task_matrix: fast, slow and C must share latent_obs_dim={m}")
        if slow.obs_dim != fast.obs_dim:
            raise ValueError("slow: obs_dim differs from the fast level's")
        self.fast, self.slow, self.task_matrix = fast, slow, task_matrix
        self.detach_fast, self.parallel_windows = detach_fast, parallel_windows
        self.window = slow.window
        self.obs_dim, self.action_dim = fast.obs_dim, slow.action_dim

    def run(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> MTS3Output:
        """Filter ``obs: (B, T, do)`` with ``actions: (B, T, da)``, ``mask: (B, T)`` (True = observed)."""
        H = self.window
        p = _prepare(obs, actions, mask, H, self.obs_dim, self.action_dim)
        B, K = obs.shape[0], p.obs.shape[1] // H
        observed_w = to_windows(p.observed, H)
        beta, beta_var = self.slow.encode_observations(to_windows(p.obs, H))
        alpha = self.slow.encode_actions(to_windows(p.actions, H), to_windows(p.present, H))
        # slow level, window by window (Eqs. mts3-task-predict and mts3-task-update)
        task_post = self.slow.initial_belief((B,), obs)
        priors, posts = [], []
        for k in range(K):
            a_k = None if alpha is None else (alpha[0][:, k], alpha[1][:, k])
            task_prior = self.slow.predict(task_post, a_k)  # uses beta_{<k}, alpha_{<=k} only
            task_post = self.slow.update(task_prior, beta[:, k], beta_var[:, k], observed_w[:, k])
            priors.append(task_prior)
            posts.append(task_post)
        task_prior, task_post = FactorizedBelief.stack(priors), FactorizedBelief.stack(posts)
        # fast level: window k is conditioned on the task PRIOR of window k (Eq. mts3-fast-predict)
        out = run_fast_level(self.fast, p.obs, p.actions, p.observed, self.task_matrix.cause(task_prior), H,
                             self.detach_fast, self.parallel_windows)
        out, mean, var = _finish(self.fast, out, obs, p, self.min_var)
        return MTS3Output(mean, var, out, task_prior, task_post,
                          None if alpha is None else alpha[0], None if alpha is None else alpha[1])

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(mean, var)`` each ``(B, T, do)``; index ``t`` predicts ``obs[:, t + 1]``."""
        out = self.run(obs, actions, mask)
        return out.mean, out.var


# ----------------------------------------------------------------------------- N levels
@dataclass(frozen=True)
class HierarchicalOutput:
    """Output of :class:`HierarchicalMTS3`: predictions, fast beliefs, and per task level ``i``
    the priors/posteriors ``(B, K_i, 2m)`` (lists ordered from the level just above the fast one)."""

    mean: Tensor
    var: Tensor
    fast: FilterOutput
    task_priors: list[FactorizedBelief]
    task_posteriors: list[FactorizedBelief]


class HierarchicalMTS3(nn.Module):
    r"""N-level MTS3: the fast ac-RKN plus a list of task levels ``levels[0..N-2]`` with windows
    :math:`H_1 < H_2 < \dots`, each a multiple of the previous one.

    Scheduling (:meth:`run`), walking through time in steps of :math:`H_1`: at the start of each of
    its windows level :math:`i` predicts, top-down, conditioned on the current prior of level
    :math:`i+1` (``levels[i].above_matrix``; the top level is unconditioned); at the end of each of
    its windows it is updated, bottom-up, with its window's abstract observations. The fast level
    runs in windows of :math:`H_1` steps conditioned on the prior of ``levels[0]`` through
    ``task_matrix``. With no task level this is the ac-RKN. ``detach_fast``, ``parallel_windows``
    and ``min_var`` as in :class:`MTS3`.
    """

    def __init__(self, fast: AcRKN, levels: Sequence[TaskSSM], task_matrix: BlockMatrix | None = None,
                 detach_fast: bool = True, parallel_windows: bool = True, min_var: float = 0.0) -> None:
        super().__init__()
        _check_fast(fast)
        if min_var < 0:
            raise ValueError(f"min_var: must be >= 0, got {min_var}")
        self.min_var = float(min_var)
        levels = list(levels)
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
        self.obs_dim = fast.obs_dim
        self.windows = [lev.window for lev in levels]

    def run(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> HierarchicalOutput:
        """Filter ``obs: (B, T, do)``, ``actions: (B, T, da)``, ``mask: (B, T)``."""
        levels = list(self.levels)
        action_dim = self.fast.control.action_dim
        if not levels:  # the ac-RKN: one window spanning the sequence, no task cause
            p = _prepare(obs, actions, mask, obs.shape[1], self.obs_dim, action_dim)
            m2 = 2 * self.fast.latent_obs_dim
            zero = obs.new_zeros(obs.shape[0], 1, m2)
            none = FactorizedBelief(zero, zero[..., : m2 // 2], zero[..., : m2 // 2], zero[..., : m2 // 2])
            out = run_fast_level(self.fast, p.obs, p.actions, p.observed, none, p.T)
            out, mean, var = _finish(self.fast, out, obs, p, self.min_var)
            return HierarchicalOutput(mean, var, out, [], [])
        p = _prepare(obs, actions, mask, self.windows[-1], self.obs_dim, action_dim)
        B, Tp = obs.shape[0], p.obs.shape[1]
        enc = []
        for lev in levels:
            H = lev.window
            beta, beta_var = lev.encode_observations(to_windows(p.obs, H))
            alpha = lev.encode_actions(to_windows(p.actions, H), to_windows(p.present, H))
            enc.append((beta, beta_var, alpha, to_windows(p.observed, H)))
        post = [lev.initial_belief((B,), obs) for lev in levels]
        prior: list[FactorizedBelief | None] = [None] * len(levels)
        priors: list[list[FactorizedBelief]] = [[] for _ in levels]
        posts: list[list[FactorizedBelief]] = [[] for _ in levels]
        for t0 in range(0, Tp, self.windows[0]):
            for i in reversed(range(len(levels))):  # window starts: top-down predicts
                if t0 % self.windows[i] == 0:
                    k = t0 // self.windows[i]
                    alpha = enc[i][2]
                    a_k = None if alpha is None else (alpha[0][:, k], alpha[1][:, k])
                    prior[i] = levels[i].predict(post[i], a_k, prior[i + 1] if i + 1 < len(levels) else None)
                    priors[i].append(prior[i])
            t1 = t0 + self.windows[0]
            for i in range(len(levels)):  # window ends: bottom-up updates
                if t1 % self.windows[i] == 0:
                    k = t1 // self.windows[i] - 1
                    beta, beta_var, _, observed_w = enc[i]
                    post[i] = levels[i].update(prior[i], beta[:, k], beta_var[:, k], observed_w[:, k])
                    posts[i].append(post[i])
        task_priors = [FactorizedBelief.stack(x) for x in priors]
        out = run_fast_level(self.fast, p.obs, p.actions, p.observed, self.task_matrix.cause(task_priors[0]),
                             self.windows[0], self.detach_fast, self.parallel_windows)
        out, mean, var = _finish(self.fast, out, obs, p, self.min_var)
        return HierarchicalOutput(mean, var, out, task_priors, [FactorizedBelief.stack(x) for x in posts])

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        out = self.run(obs, actions, mask)
        return out.mean, out.var


# ----------------------------------------------------------------------------- builders
FAST_A_INIT = (0.95, 0.2, -0.2, 0.95)


def build_fast_acrkn(obs_dim: int, action_dim: int, latent_obs_dim: int, hidden: Sequence[int] = (32,),
                     bandwidth: int = 0, A_init: Sequence[float] = FAST_A_INIT, decoupled: bool = False,
                     init_var: float = 10.0, trans_var_init: float = 0.1) -> AcRKN:
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
                 BeliefDecoder(m, obs_dim, hidden, hidden), init_var=init_var, predict_differences=False)


def build_mts3(obs_dim: int, action_dim: int, latent_obs_dim: int, window: int, hidden: Sequence[int] = (32,),
               bandwidth: int = 0, use_actions: bool = True, decoupled: bool = False,
               detach_fast: bool = True, min_var: float = 1e-4) -> MTS3:
    """A small 2-level :class:`MTS3` with the defaults documented in :func:`build_fast_acrkn` and
    :class:`TaskSSM`. ``decoupled=True`` gives the diagonal-covariance ("no memory half") ablation,
    ``use_actions=False`` the one without action abstraction."""
    m = latent_obs_dim
    fast = build_fast_acrkn(obs_dim, action_dim, m, hidden, bandwidth, decoupled=decoupled)
    slow = TaskSSM(obs_dim, action_dim, m, window, hidden, bandwidth, use_actions, decoupled=decoupled)
    return MTS3(fast, slow, BlockMatrix(m, bandwidth, decoupled=decoupled), detach_fast, min_var=min_var)


def build_hierarchical_mts3(obs_dim: int, action_dim: int, latent_obs_dim: int, windows: Sequence[int],
                            hidden: Sequence[int] = (32,), bandwidth: int = 0, detach_fast: bool = True,
                            min_var: float = 1e-4) -> HierarchicalMTS3:
    """An N-level :class:`HierarchicalMTS3` with ``len(windows)`` task levels (N = that + 1)."""
    m = latent_obs_dim
    fast = build_fast_acrkn(obs_dim, action_dim, m, hidden, bandwidth)
    n = len(windows)
    levels = [TaskSSM(obs_dim, action_dim, m, H, hidden, bandwidth, conditioned=i < n - 1)
              for i, H in enumerate(windows)]
    return HierarchicalMTS3(fast, levels, BlockMatrix(m, bandwidth) if n else None, detach_fast, min_var=min_var)

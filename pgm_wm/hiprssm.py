r"""Hidden-parameter recurrent state-space models, HiP-RSSM (Chapter 5).

A HiP-SSM is a family of state-space models indexed by a latent *task* :math:`l` that is
constant over a short stretch of time (a window) and is observed only through a *context set*
of recent interactions :math:`\mathcal C = \{(o_t, a_t, o_{t+1})\}_n`. The HiP-RSSM is the
ac-RKN of Chapter 4 plus **one more independent cause** in the predict step:

1. **Context update** (Chapter 2): a set encoder maps every interaction to a latent observation
   :math:`(r_n, \sigma_n)` and Bayesian aggregation gives the task posterior
   :math:`p(l\mid\mathcal C) = \mathcal N(\mu_l, \operatorname{diag}\sigma_l)`
   (:class:`pgm_wm.aggregation.BayesianContextEncoder`, Eq. ba-update). The ablation replaces
   it by :class:`RecurrentContextEncoder`, an RKN run over the context in time order.
2. **Task-conditional predict**, Eq. (hip-predict). :math:`z_t`, :math:`l` and the known action
   are the parents of :math:`z_{t+1}` (a V-structure at the unobserved :math:`z_{t+1}`). Treating
   the state belief and the task belief as independent (an approximation: the task is not
   refined by the window's own observations), Eq. (gauss-marginal) gives

   .. math:: z^-_{t+1} = A_t z^+_t + b(a_t) + C\mu_l,\qquad
             \Sigma^-_{t+1} = A_t\Sigma^+_tA_t^\top + C\operatorname{diag}(\sigma_l)C^\top + Q.

   :class:`LinearTaskTransform` adds exactly this (the block diagonals of
   :math:`C\operatorname{diag}(\sigma_l)C^\top`, via :func:`pgm_wm.factorized.linear_cause`);
   :class:`NonlinearTaskTransform` is the additive nonlinear variant, Eq. (hip-predict-nonlinear):
   :math:`f(\mu_l)` in the mean and :math:`g(\sigma_l)\ge 0` on the covariance diagonal.
3. **Observation update**: the exact factorized Kalman update of the RKN (unchanged).

The model declares its causes (:meth:`HiPRSSM.causes`): the ac-RKN's ``[control]`` plus
``[task]``, the task cause known before the loop (one sequence, constant over the window). No
filtering code is duplicated: dropping the last cause gives the ac-RKN exactly.

Data (Algorithm "multitask dataset"): :func:`make_windows` cuts each trajectory into
non-overlapping windows of ``k`` steps; the context of window :math:`j` is the set of the
``k - 1`` interactions that lie entirely inside window :math:`j-1`, so every time index in a
window's context is strictly before the window's first step. The state filter restarts from
its initial belief in every window; only the task carries information across windows.
Test-time inference over a long trajectory (:func:`infer_trajectory`) runs the same model
window by window. :func:`resample_past_contexts` swaps contexts for those of random earlier
windows of the same trajectory (a training variant); :func:`evaluate_windows` computes the
chapter's one-step / open-loop RMSEs, with and without hidden observations, in original units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_last_dims, check_mask, check_tensor
from .beliefs import DiagGaussian, FactorizedBelief
from .context import transition_features
from .factorized import linear_cause
from .filtering import FilterResult
from .metrics import rmse
from .rkn import RKN, Cause, LocallyLinearTransition, ObservationEncoder, mlp, over_time

__all__ = [
    "context_features",
    "HiPWindows",
    "make_windows",
    "resample_past_contexts",
    "LinearTaskTransform",
    "NonlinearTaskTransform",
    "RecurrentContextEncoder",
    "HiPRSSM",
    "hip_loss_fn",
    "floor_variance",
    "infer_trajectory",
    "eval_masks",
    "predict_windows",
    "window_rmse",
    "evaluate_windows",
    "latent_pca",
]

WorldModel = Callable[..., tuple[Tensor, Tensor]]


# ============================================================================= context sets, windows
def context_features(
    obs: Tensor,
    actions: Tensor,
    valid: Tensor | None = None,
    diff_shift: Tensor | None = None,
    diff_scale: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Interaction features :math:`x_t = [o_t,\ a_t,\ (o_{t+1} - o_t - s)\oslash c]` for
    :math:`t = 0..T-2` and their presence mask.

    ``obs: (..., T, do)``, ``actions: (..., T, da)``, ``valid: (..., T)`` bool (default all True)
    -> ``x: (..., T-1, 2 do + da)``, ``mask: (..., T-1)`` with ``mask[t] = valid[t] & valid[t+1]``.
    ``diff_shift`` :math:`s` and ``diff_scale`` :math:`c` (``(do,)``, e.g. from
    :func:`pgm_wm.acrkn.difference_scaling`) standardize the difference so all three blocks have
    unit scale; by default the raw difference is used (:func:`pgm_wm.context.transition_features`).
    Missing observations are zeroed, so their values never reach a present feature.
    """
    check_tensor("obs", obs, 2)
    check_tensor("actions", actions, 2)
    T, do = obs.shape[-2], obs.shape[-1]
    if valid is None:
        valid = torch.ones(obs.shape[:-1], dtype=torch.bool, device=obs.device)
    valid = check_mask("valid", valid, tuple(obs.shape[:-1]))
    obs = torch.where(valid[..., None], obs, torch.zeros((), dtype=obs.dtype, device=obs.device))
    x = transition_features(obs, actions)
    if diff_shift is not None or diff_scale is not None:
        shift = torch.zeros(do, dtype=obs.dtype) if diff_shift is None else torch.as_tensor(diff_shift, dtype=obs.dtype)
        scale = torch.ones(do, dtype=obs.dtype) if diff_scale is None else torch.as_tensor(diff_scale, dtype=obs.dtype)
        check_last_dims("diff_shift", shift, (do,))
        check_last_dims("diff_scale", scale, (do,))
        if not bool((scale > 0).all()):
            raise ValueError("diff_scale: must be positive")
        x = torch.cat([x[..., :-do], (x[..., -do:] - shift.to(x.device)) / scale.to(x.device)], dim=-1)
    return x, valid[..., :-1] & valid[..., 1:]


@dataclass(frozen=True)
class HiPWindows:
    r"""Windows of ``k`` steps with their context sets (output of :func:`make_windows`).

    Every field has the window index first (``W`` windows):

    Attributes:
        obs, actions: the window itself, ``(W, k, do)`` / ``(W, k, da)``.
        valid: ``(W, k)`` bool, observation present.
        context, context_mask: the context set ``(W, N, F)`` / ``(W, N)`` with ``N = k - 1``:
            interaction features (:func:`context_features`) of the previous window.
        prev_obs, prev_actions, prev_valid: the previous window's raw steps (the history a
            recurrent baseline may see), ``(W, k, ·)``; zeros / False for a trajectory's first
            window.
        seq: ``(W,)`` index of the source trajectory; start: ``(W,)`` time index of step 0.
        context_time: ``(W, N)`` time index of the *later* observation :math:`o_{t+1}` of each
            context interaction (``-1`` where absent) — always ``< start``.
        hidden: per-window copies of per-step hidden variables, each ``(W, k, ...)``.
    """

    obs: Tensor
    actions: Tensor
    valid: Tensor
    context: Tensor
    context_mask: Tensor
    prev_obs: Tensor
    prev_actions: Tensor
    prev_valid: Tensor
    seq: Tensor
    start: Tensor
    context_time: Tensor
    hidden: dict[str, Tensor] = field(default_factory=dict)

    @property
    def n_windows(self) -> int:
        return int(self.obs.shape[0])

    @property
    def window_len(self) -> int:
        return int(self.obs.shape[1])

    def with_history(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(obs, actions, valid)`` of length ``2k``: previous window followed by this one."""
        return (torch.cat([self.prev_obs, self.obs], 1), torch.cat([self.prev_actions, self.actions], 1),
                torch.cat([self.prev_valid, self.valid], 1))

    def select(self, index: Tensor) -> "HiPWindows":
        """The windows at ``index`` (any index that works on the first axis)."""
        pick = lambda t: t[index]  # noqa: E731
        return HiPWindows(*(pick(getattr(self, f)) for f in (
            "obs", "actions", "valid", "context", "context_mask", "prev_obs", "prev_actions",
            "prev_valid", "seq", "start", "context_time")), hidden={k: pick(v) for k, v in self.hidden.items()})

    def tensors(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(obs, actions, valid, context, context_mask)``: the minibatch layout of :func:`hip_loss_fn`."""
        return self.obs, self.actions, self.valid, self.context, self.context_mask


def make_windows(
    obs: Tensor,
    actions: Tensor,
    window_len: int,
    valid: Tensor | None = None,
    hidden: dict[str, Tensor] | None = None,
    diff_shift: Tensor | None = None,
    diff_scale: Tensor | None = None,
    include_first: bool = False,
) -> HiPWindows:
    r"""Multitask dataset: cut trajectories into windows, each with the previous window as context.

    ``obs: (n, T, do)``, ``actions: (n, T, da)``, ``valid: (n, T)``. Window :math:`j` of a
    trajectory covers steps :math:`[jk, (j+1)k)` (a tail shorter than ``k`` is dropped). Its
    context is the set of interactions :math:`(o_t, a_t, o_{t+1})` with
    :math:`(j-1)k \le t < t+1 \le jk-1`, i.e. the ``k - 1`` interactions inside window
    :math:`j-1`: the interaction that would end at :math:`o_{jk}` is left out, so nothing at or
    after the window's first step is ever in its context. An interaction is present in the set
    only if both of its observations are valid.

    ``include_first`` keeps each trajectory's first window with an *empty* context (all
    ``context_mask`` False): the model then uses its task prior. Training sets leave it out.
    ``hidden`` values of shape ``(n, T, ...)`` are cut the same way (e.g. the payload).
    """
    check_tensor("obs", obs, 3)
    check_tensor("actions", actions, 3)
    n, T, do = obs.shape
    if tuple(actions.shape[:2]) != (n, T):
        raise ValueError(f"actions: expected leading shape {(n, T)}, got {tuple(actions.shape)}")
    if not isinstance(window_len, int) or window_len < 2:
        raise ValueError(f"window_len: must be an int >= 2, got {window_len!r}")
    n_win = T // window_len
    first = 0 if include_first else 1
    if n_win - first < 1:
        raise ValueError(f"window_len: T={T} gives {n_win} windows of {window_len} steps; need at least "
                         f"{first + 1}")
    if valid is None:
        valid = torch.ones(n, T, dtype=torch.bool, device=obs.device)
    valid = check_mask("valid", valid, (n, T))
    k = window_len
    Tc = n_win * k
    # (n, n_win, k, ·) views of the usable part of every trajectory.
    cut = lambda x: x[:, :Tc].reshape(n, n_win, k, *x.shape[2:])  # noqa: E731
    o, a, v = cut(obs), cut(actions), cut(valid)
    # Previous-window views: a zero/False window in front of each trajectory.
    shift = lambda x: torch.cat([torch.zeros_like(x[:, :1]), x[:, :-1]], 1)  # noqa: E731
    po, pa, pv = shift(o), shift(a), shift(v)
    ctx, cmask = context_features(po, pa, pv, diff_shift, diff_scale)  # (n, n_win, k-1, F)
    times = torch.arange(Tc, device=obs.device).reshape(n_win, k)
    ctx_time = (times - k)[:, 1:].expand(n, n_win, k - 1)  # time of o_{t+1} of each interaction
    ctx_time = torch.where(cmask, ctx_time, torch.full_like(ctx_time, -1))
    seq = torch.arange(n, device=obs.device)[:, None].expand(n, n_win)
    start = times[:, 0][None, :].expand(n, n_win)
    sel = lambda x: x[:, first:].reshape(n * (n_win - first), *x.shape[2:])  # noqa: E731
    hid = {}
    for key, val in (hidden or {}).items():
        if val.shape[:2] != (n, T):
            raise ValueError(f"hidden: {key!r} must have leading shape {(n, T)}, got {tuple(val.shape)}")
        hid[key] = sel(cut(val))
    return HiPWindows(sel(o), sel(a), sel(v), sel(ctx), sel(cmask), sel(po), sel(pa), sel(pv),
                      sel(seq), sel(start), sel(ctx_time), hid)


def resample_past_contexts(windows: HiPWindows, generator: torch.Generator | None = None) -> HiPWindows:
    r"""Give every window the context set of a uniformly drawn window ``j' <= j`` of the *same*
    trajectory (its own context included), i.e. the interactions of a random earlier window.

    For trajectories whose hidden parameter is constant, every earlier window shows the same task,
    but only the adjacent one also tells much about the *current motion*. Training on resampled
    contexts therefore rewards a task latent that describes the trajectory (the payload) rather
    than the recent state. Every context still lies strictly before its window
    (``context_time < start``); ``prev_*`` fields are left unchanged. Resample for every epoch or
    batch with a seeded ``generator``.
    """
    n_all = windows.n_windows
    seq, start = windows.seq, windows.start
    # candidate j' : same trajectory and start' <= start; draw uniformly among them
    same = (seq[:, None] == seq[None, :]) & (start[None, :] <= start[:, None])
    u = torch.rand(n_all, n_all, generator=generator)
    pick = torch.where(same, u, torch.full_like(u, -1.0)).argmax(1)
    return replace(windows, context=windows.context[pick], context_mask=windows.context_mask[pick],
                   context_time=windows.context_time[pick])


# ============================================================================= task transformations
class LinearTaskTransform(nn.Module):
    r"""Linear task term :math:`C l`, Eq. (hip-predict): the cause
    :math:`\mathcal N(C\mu_l,\ C\operatorname{diag}(\sigma_l)C^\top)` restricted to the factorized
    structure (exact block diagonals, :func:`pgm_wm.factorized.linear_cause`).

    ``C: (2m, task_dim)``, initialized with i.i.d. :math:`\mathcal N(0, \text{init\_std}^2)` entries.
    ``forward(task: DiagGaussian (..., task_dim)) -> FactorizedBelief`` with ``mean (..., 2m)``
    (``forward(mean, var)`` is accepted too).
    """

    def __init__(self, task_dim: int, latent_obs_dim: int, init_std: float = 0.1) -> None:
        super().__init__()
        if task_dim <= 0 or latent_obs_dim <= 0:
            raise ValueError(f"task_dim: need task_dim > 0 and latent_obs_dim > 0, got {task_dim}, {latent_obs_dim}")
        self.task_dim, self.latent_obs_dim = task_dim, latent_obs_dim
        self.C = nn.Parameter(init_std * torch.randn(2 * latent_obs_dim, task_dim))

    def forward(self, task: DiagGaussian | Tensor, var: Tensor | None = None) -> FactorizedBelief:
        task = _as_task(task, var)
        check_last_dims("task.mean", task.mean, (self.task_dim,))
        return linear_cause(self.C.to(task.mean.dtype), task)


def _as_task(task: DiagGaussian | Tensor, var: Tensor | None) -> DiagGaussian:
    """Accept a task belief ``DiagGaussian(mean, var)`` or the older ``(mean, var)`` arguments."""
    if isinstance(task, DiagGaussian):
        return task
    if isinstance(task, Tensor) and isinstance(var, Tensor):
        return DiagGaussian(task, var)
    raise ValueError(f"task: expected a DiagGaussian (mean, var), got {type(task).__name__}")


def _shifted_softplus(x: Tensor) -> Tensor:
    """``softplus(x) - log 2``: zero at 0, increasing, non-negative for ``x >= 0``."""
    return F.softplus(x) - math.log(2.0)


class NonlinearTaskTransform(nn.Module):
    r"""Additive nonlinear task term, Eq. (hip-predict-nonlinear):

    .. math:: z^- \mathrel{+}= f(\mu_l),\qquad [\sigma^{u-}; \sigma^{l-}] \mathrel{+}= g(\sigma_l),

    with :math:`f` an MLP (ReLU) and :math:`g` a small *monotone* network
    :math:`g(\sigma) = W_2^+\,\phi(W_1^+\sigma)`, :math:`W^+ = \mathrm{softplus}(W)` elementwise
    (non-negative weights) and :math:`\phi(x) = \mathrm{softplus}(x) - \log 2`. Hence
    :math:`g(\sigma)\ge 0` for :math:`\sigma\ge 0`, :math:`g(0) = 0` (a known task adds no
    uncertainty) and :math:`g` never decreases when the task becomes more uncertain. The side
    covariance is left unchanged (the term is diagonal).

    ``forward(task: DiagGaussian (..., task_dim)) -> FactorizedBelief`` with ``mean (..., 2m)``.
    """

    def __init__(self, task_dim: int, latent_obs_dim: int, hidden: Sequence[int] = (64,),
                 var_hidden: int = 32, var_init: float = 0.05) -> None:
        super().__init__()
        if task_dim <= 0 or latent_obs_dim <= 0 or var_hidden <= 0:
            raise ValueError(f"task_dim: need positive task_dim, latent_obs_dim, var_hidden, got "
                             f"{task_dim}, {latent_obs_dim}, {var_hidden}")
        if var_init <= 0:
            raise ValueError(f"var_init: must be positive, got {var_init}")
        self.task_dim, self.latent_obs_dim = task_dim, latent_obs_dim
        self.mean_net = mlp(task_dim, hidden, 2 * latent_obs_dim)
        raw = math.log(math.expm1(var_init))  # softplus(raw) = var_init
        self.w1_raw = nn.Parameter(raw + 0.5 * torch.randn(var_hidden, task_dim))
        self.w2_raw = nn.Parameter(raw + 0.5 * torch.randn(2 * latent_obs_dim, var_hidden))

    def var_term(self, var: Tensor) -> Tensor:
        """:math:`g(\\sigma_l)`: ``(..., task_dim) -> (..., 2m)``, non-negative."""
        h = _shifted_softplus(var @ F.softplus(self.w1_raw).to(var.dtype).T)
        return h @ F.softplus(self.w2_raw).to(var.dtype).T

    def forward(self, task: DiagGaussian | Tensor, var: Tensor | None = None) -> FactorizedBelief:
        task = _as_task(task, var)
        check_last_dims("task.mean", task.mean, (self.task_dim,))
        m = self.latent_obs_dim
        g = self.var_term(task.var)
        return FactorizedBelief(self.mean_net(task.mean), g[..., :m], g[..., m:], torch.zeros_like(g[..., :m]))


# ============================================================================= context encoders
class RecurrentContextEncoder(nn.Module):
    r"""Recurrent (causal) context encoder for the ablation: an RKN filters the context
    interactions **in time order** and its last posterior is the task belief,
    :math:`\mu_l = z^+_N`, :math:`\sigma_l = [\sigma^{u+}_N; \sigma^{l+}_N]`.

    Unlike :class:`pgm_wm.aggregation.BayesianContextEncoder` it is not permutation invariant and
    its cost is sequential in the set size. ``latent_dim`` must be even (the RKN state is
    ``2m``). The initial belief :math:`\mathcal N(0, \text{init\_var}\,I)` plays the role of the
    task prior; absent (masked) elements skip the update.

    ``forward(x: (..., N, in_dim), mask: (..., N) | None) -> DiagGaussian``, ``(..., latent_dim)``.
    """

    def __init__(self, in_dim: int, latent_dim: int, hidden: Sequence[int] = (64,),
                 num_basis: int = 4, bandwidth: int = 1, init_var: float = 1.0) -> None:
        super().__init__()
        if latent_dim <= 0 or latent_dim % 2:
            raise ValueError(f"latent_dim: must be a positive even number, got {latent_dim}")
        if in_dim <= 0:
            raise ValueError(f"in_dim: must be positive, got {in_dim}")
        m = latent_dim // 2
        self.in_dim, self.latent_dim = in_dim, latent_dim
        self.rkn = RKN(ObservationEncoder(in_dim, m, hidden),
                       LocallyLinearTransition(m, num_basis, min(bandwidth, m - 1)), nn.Identity(), init_var)

    def forward(self, x: Tensor, mask: Tensor | None = None) -> DiagGaussian:
        check_last_dims("x", x, (None, self.in_dim))
        lead, N = x.shape[:-2], x.shape[-2]
        flat = x.reshape(-1, N, self.in_dim)
        fmask = None if mask is None else check_mask("mask", mask, tuple(x.shape[:-1])).reshape(-1, N)
        post = self.rkn.filter(self.rkn.encode(flat, fmask), fmask).posterior.at(-1)
        return DiagGaussian(post.mean.reshape(*lead, -1), post.var.reshape(*lead, -1))


# ============================================================================= the model
class HiPRSSM(nn.Module):
    r"""Hidden-parameter RSSM: an :class:`pgm_wm.acrkn.AcRKN` whose predict step has one more
    independent cause, the latent task, Eq. (hip-predict).

    Args:
        acrkn: the state-space part (encoder, transition, control, decoder, readout).
        context_encoder: ``(context (..., N, F), mask (..., N)) -> (mu_l, var_l) (..., task_dim)``,
            e.g. :class:`pgm_wm.aggregation.BayesianContextEncoder` or :class:`RecurrentContextEncoder`.
        task_transform: ``(mu_l, var_l) -> FactorizedBelief`` (the task cause), e.g.
            :class:`LinearTaskTransform` or :class:`NonlinearTaskTransform`.

    Index ``t`` of :meth:`forward` predicts :math:`o_{t+1}` (the convention of the ac-RKN).
    """

    def __init__(self, acrkn: nn.Module, context_encoder: nn.Module, task_transform: nn.Module) -> None:
        super().__init__()
        m = getattr(acrkn, "latent_obs_dim", None)
        if getattr(task_transform, "latent_obs_dim", m) != m:
            raise ValueError(f"task_transform: latent_obs_dim {task_transform.latent_obs_dim} differs from the "
                             f"ac-RKN's {m}")
        td_enc = getattr(context_encoder, "latent_dim", None)
        td_tr = getattr(task_transform, "task_dim", None)
        if td_enc is not None and td_tr is not None and td_enc != td_tr:
            raise ValueError(f"context_encoder: latent_dim {td_enc} differs from task_transform.task_dim {td_tr}")
        self.acrkn, self.context_encoder, self.task_transform = acrkn, context_encoder, task_transform
        self.latent_obs_dim = m
        self.obs_dim = acrkn.obs_dim
        # BayesianContextEncoder keeps its input size on its inner SetEncoder
        self.context_dim = getattr(context_encoder, "in_dim",
                                   getattr(getattr(context_encoder, "encoder", None), "in_dim", None))

    def infer_task(self, context: Tensor | None, context_mask: Tensor | None = None,
                   batch_size: int | None = None, like: Tensor | None = None) -> DiagGaussian:
        r"""Context update: :math:`p(l\mid\mathcal C) = \mathcal N(\mu_l, \operatorname{diag}\sigma_l)`.

        ``context: (B, N, F)``, ``context_mask: (B, N)``; present elements must be finite (padded
        ones may hold anything, NaN included: they are zeroed before the encoder sees them).
        ``context=None`` means an empty set: the encoder's prior is returned for ``batch_size``
        rows (dtype/device of ``like``). Returns a :class:`pgm_wm.beliefs.DiagGaussian` (it unpacks
        as ``mean, var``).
        """
        if context is None:
            if batch_size is None or like is None or self.context_dim is None:
                raise ValueError("context: None needs batch_size, like and an encoder with in_dim")
            context = torch.zeros(batch_size, 1, self.context_dim, dtype=like.dtype, device=like.device)
            context_mask = torch.zeros(batch_size, 1, dtype=torch.bool, device=like.device)
        check_tensor("context", context, 2)
        if context_mask is not None:
            context_mask = check_mask("context_mask", context_mask, tuple(context.shape[:-1]))
            context = torch.where(context_mask[..., None], context,
                                  torch.zeros((), dtype=context.dtype, device=context.device))
        check_finite("context", context)
        return DiagGaussian(*self.context_encoder(context, context_mask))

    def task_cause(self, task: DiagGaussian | Tensor, task_var: Tensor | None = None) -> FactorizedBelief:
        """The task's contribution to the prior (mean and factorized covariance), ``(B, 2m)``."""
        return self.task_transform(_as_task(task, task_var))

    def _task(self, obs: Tensor, context: Tensor | None, context_mask: Tensor | None,
              task: DiagGaussian | tuple[Tensor, Tensor] | None) -> DiagGaussian:
        if task is not None:
            mean, var = task
            check_tensor("task", mean, 2)
            if mean.shape != var.shape or mean.shape[0] != obs.shape[0]:
                raise ValueError(f"task: expected (mean, var) of shape (B={obs.shape[0]}, task_dim), "
                                 f"got {tuple(mean.shape)} and {tuple(var.shape)}")
            if not bool(torch.isfinite(mean).all() & torch.isfinite(var).all()):
                raise ValueError("task: mean and variances must be finite (got NaN or inf)")
            if bool((var < 0).any()):
                raise ValueError("task: variances must be non-negative")
            return DiagGaussian(mean, var)
        if context is not None and context.shape[0] != obs.shape[0]:
            raise ValueError(f"context: batch size {context.shape[0]} differs from obs' {obs.shape[0]}")
        return self.infer_task(context, context_mask, obs.shape[0], obs)

    def causes(self, actions: Tensor, task: DiagGaussian, T: int) -> list[Cause]:
        """The causes of the predict step: the ac-RKN's ``[control]`` plus ``[task]`` (the task
        cause of Eq. hip-predict, known before the loop and constant over the ``T`` steps).
        HiP-RSSM = ac-RKN + this last cause."""
        return self.acrkn.causes(actions) + [over_time(self.task_cause(task), T)]

    def filter(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None, context: Tensor | None = None,
               context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None
               ) -> tuple[FilterResult, DiagGaussian]:
        """Filter one window: ``(FilterResult, task)``. The task is inferred from the context (or
        given as ``task = DiagGaussian(mean, var)``) once and enters every predict step."""
        from .acrkn import check_sequences

        mask = check_sequences(obs, actions, mask)
        belief = self._task(obs, context, context_mask, task)
        w = self.acrkn.rkn.encode(obs, mask)
        out = self.acrkn.rkn.filter(w, mask=mask, causes=self.causes(actions, belief, obs.shape[1]))
        return out, belief

    def predict(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None, context: Tensor | None = None,
                context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(mean, var, task_mean, task_var)``: next-observation predictions ``(B, T, do)`` and the task."""
        check_tensor("obs", obs, 3)
        if mask is not None:
            mask = check_mask("mask", mask, tuple(obs.shape[:2]))
        out, belief = self.filter(obs, actions, mask, context, context_mask, task)
        mean, var = self.acrkn.decode_predictions(out, obs, mask)
        return mean, var, belief.mean, belief.var

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None, context: Tensor | None = None,
                context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None
                ) -> tuple[Tensor, Tensor]:
        """Predict :math:`o_{t+1}` for every ``t`` of the window: ``(mean, var)`` each ``(B, T, do)``."""
        mean, var, _, _ = self.predict(obs, actions, mask, context, context_mask, task)
        return mean, var


def floor_variance(model: WorldModel, min_var: float = 1e-8) -> WorldModel:
    r"""Wrap a world model so that its predictive variances are at least ``min_var``.

    Why: the decoders' ``elu(x) + 1`` is computed as :math:`(e^x - 1) + 1`, which in float32
    rounds to exactly 0 once :math:`e^x < 6\cdot10^{-8}`. Angle differences of the arm are almost
    deterministic given the observed velocity, so NLL training drives some variances there, and
    a single zero variance makes the NLL infinite. The floor (with zero gradient below it) only
    acts on those entries. ``wrapped(*args, **kw) -> (mean, var.clamp_min(min_var))``.
    """
    if min_var <= 0:
        raise ValueError(f"min_var: must be positive, got {min_var}")

    def wrapped(*args, **kwargs) -> tuple[Tensor, Tensor]:
        mean, var = model(*args, **kwargs)
        return mean, var.clamp_min(min_var)

    return wrapped


def hip_loss_fn(model: HiPRSSM, keep_prob: float = 1.0, context_steps: int = 1,
                loss: str = "nll", min_var: float = 1e-8, open_loop_prob: float = 0.0
                ) -> Callable[[tuple[Tensor, ...], torch.Generator], Tensor]:
    """A ``loss_fn`` for :func:`pgm_wm.training.fit` on batches ``HiPWindows.tensors()`` =
    ``(obs, actions, valid, context, context_mask)``: a fresh imputation mask per batch
    (:func:`pgm_wm.training.imputation_mask`, each observation kept with ``keep_prob``, the first
    ``context_steps`` always, and with probability ``open_loop_prob`` everything after a random
    cut hidden), then :func:`pgm_wm.training.prediction_loss` (all valid targets
    count, observed or not) with variances floored at ``min_var`` (:func:`floor_variance`)."""
    from .training import imputation_mask, prediction_loss

    floored = floor_variance(model, min_var)

    def loss_fn(batch: tuple[Tensor, ...], gen: torch.Generator) -> Tensor:
        obs, actions, valid, context, cmask = batch
        mask = imputation_mask(obs.shape[:2], keep_prob, context_steps, gen, device=obs.device,
                               open_loop_prob=open_loop_prob) & valid
        model_fn = lambda o, a, m: floored(o, a, m, context, cmask)  # noqa: E731
        return prediction_loss(model_fn, obs, actions, mask, valid, loss)

    return loss_fn


# ============================================================================= inference and evaluation
@torch.no_grad()
def infer_trajectory(model: HiPRSSM, obs: Tensor, actions: Tensor, window_len: int, valid: Tensor | None = None,
                     diff_shift: Tensor | None = None, diff_scale: Tensor | None = None
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r"""Test-time inference over long trajectories, window by window (Algorithm "HiP-RSSM test time").

    For each window :math:`j` of ``window_len`` steps: infer :math:`p(l_j\mid\mathcal C_j)` from the
    interactions of window :math:`j-1` (the first window uses the task prior), restart the state
    filter and predict inside the window with the task-conditional predict step. Windows are
    independent given their contexts, so they run as one batch.

    ``obs: (n, T, do)``, ``actions: (n, T, da)``, ``valid: (n, T)``. Returns
    ``(mean, var)`` of shape ``(n, Tc, do)`` (``Tc = T // window_len * window_len``; index ``t``
    predicts :math:`o_{t+1}`, the last index of each window is the prediction of the next
    window's first observation) and ``(task_mean, task_var)`` of shape ``(n, n_win, task_dim)``.
    """
    w = make_windows(obs, actions, window_len, valid, None, diff_shift, diff_scale, include_first=True)
    n = obs.shape[0]
    n_win = w.n_windows // n
    mean, var, t_mean, t_var = model.predict(w.obs, w.actions, w.valid, w.context, w.context_mask)
    shape = (n, n_win * window_len, obs.shape[-1])
    return (mean.reshape(shape), var.reshape(shape), t_mean.reshape(n, n_win, -1), t_var.reshape(n, n_win, -1))


def eval_masks(n_windows: int, window_len: int, keep_prob: float = 1.0, observed_steps: int | None = None,
               first_kept: int = 1, seed: int = 0) -> Tensor:
    r"""Evaluation observation masks ``(W, k)`` (True = the model may see the observation).

    Each step is kept with probability ``keep_prob`` (``0.5`` = "50 % imputation"), the first
    ``first_kept`` steps always; with ``observed_steps = c`` every step ``>= c`` is hidden (the
    model then predicts open-loop from the actions: multi-step prediction). Seeded, so every
    model is evaluated on the same masks.
    """
    if not 0.0 <= keep_prob <= 1.0:
        raise ValueError(f"keep_prob: must be in [0, 1], got {keep_prob}")
    if observed_steps is not None and not 1 <= observed_steps <= window_len:
        raise ValueError(f"observed_steps: must be in [1, {window_len}], got {observed_steps}")
    gen = torch.Generator().manual_seed(int(seed))
    mask = torch.rand(n_windows, window_len, generator=gen) < keep_prob
    mask[:, :first_kept] = True
    if observed_steps is not None:
        mask[:, observed_steps:] = False
    return mask


@torch.no_grad()
def predict_windows(model: WorldModel, windows: HiPWindows, mask: Tensor | None = None,
                    use_context: bool = True, use_history: bool = False, batch_size: int = 512
                    ) -> tuple[Tensor, Tensor]:
    r"""Next-observation predictions for every window, ``(mean, var)`` each ``(W, k, do)``.

    ``mask: (W, k)`` (ANDed with ``windows.valid``) hides observations of the window; hidden
    observations are zeroed *before* the model is called, so they cannot leak.

    * ``use_context`` (a :class:`HiPRSSM`): the window's context set gives the task.
    * ``use_history`` (any world model ``model(obs, actions, mask)``): the model first runs over
      the fully observed previous window, then over this one, and the outputs of this window are
      returned — the same information the HiP-RSSM gets from its context.
    * neither: the model sees the window alone.
    """
    mask = windows.valid if mask is None else check_mask("mask", mask, tuple(windows.valid.shape)) & windows.valid
    means, vars_ = [], []
    k = windows.window_len
    for s in range(0, windows.n_windows, batch_size):
        sl = slice(s, s + batch_size)
        obs, act, m = windows.obs[sl], windows.actions[sl], mask[sl]
        if use_history:
            obs = torch.cat([windows.prev_obs[sl], obs], 1)
            act = torch.cat([windows.prev_actions[sl], act], 1)
            m = torch.cat([windows.prev_valid[sl], m], 1)
        obs = torch.where(m[..., None], obs, torch.zeros((), dtype=obs.dtype))
        if use_context and isinstance(model, HiPRSSM):
            mu, var = model(obs, act, m, windows.context[sl], windows.context_mask[sl])
        else:
            mu, var = model(obs, act, m)
        means.append(mu[:, -k:])
        vars_.append(var[:, -k:])
    return torch.cat(means), torch.cat(vars_)


def window_rmse(mean: Tensor, windows: HiPWindows, obs_std: Tensor | None = None, from_step: int = 0) -> Tensor:
    r"""RMSE of next-observation predictions inside the windows, in original units.

    Output index ``t`` (``t = from_step..k-2``) is compared with ``obs[:, t+1]`` wherever that is
    valid; differences are multiplied by ``obs_std`` (training statistics) first, so a model fed
    normalized observations is scored in the units of the data (not doubly normalized).
    """
    check_last_dims("mean", mean, (windows.window_len, windows.obs.shape[-1]))
    k = windows.window_len
    if not 0 <= from_step <= k - 2:
        raise ValueError(f"from_step: must be in [0, {k - 2}], got {from_step}")
    pred, target = mean[:, from_step:k - 1], windows.obs[:, from_step + 1:]
    sel = windows.valid[:, from_step + 1:]
    if obs_std is not None:
        std = torch.as_tensor(obs_std, dtype=pred.dtype)
        pred, target = pred * std, target * std
    return rmse(pred, target, sel)


def evaluate_windows(model: WorldModel, windows: HiPWindows, obs_std: Tensor | None = None,
                     observed_steps: int | None = None, keep_prob: float = 0.5, seed: int = 0,
                     use_context: bool = True, use_history: bool = False) -> dict[str, float]:
    r"""The four RMSEs of the chapter's results table (original units):

    * ``one_step`` / ``one_step_imp``: every next observation, with all / a ``keep_prob`` fraction
      of the window's observations visible (first step always visible);
    * ``multi_step`` / ``multi_step_imp``: only the first ``observed_steps`` observations visible
      (all / a ``keep_prob`` fraction of them), the rest predicted open-loop from the actions;
      scored on the open-loop steps only. ``observed_steps`` defaults to ``k // 2``.
    """
    W, k = windows.valid.shape
    c = k // 2 if observed_steps is None else observed_steps
    out = {}
    for name, keep, obs_steps, from_step in (("one_step", 1.0, None, 0), ("one_step_imp", keep_prob, None, 0),
                                             ("multi_step", 1.0, c, c), ("multi_step_imp", keep_prob, c, c)):
        mask = eval_masks(W, k, keep, obs_steps, 1, seed)
        mu, _ = predict_windows(model, windows, mask, use_context, use_history)
        out[name] = float(window_rmse(mu, windows, obs_std, from_step))
    return out


def latent_pca(x: Tensor, n_components: int = 2) -> tuple[Tensor, Tensor]:
    r"""Project ``x: (n, d)`` on its first principal components (centered SVD).

    Returns ``(scores (n, n_components), explained_variance_ratio (n_components,))``. Component signs
    are fixed so that the largest-magnitude loading of each component is positive.
    """
    check_tensor("x", x, 2)
    if not 1 <= n_components <= min(x.shape):
        raise ValueError(f"n_components: must be in [1, {min(x.shape)}], got {n_components}")
    xc = x - x.mean(0, keepdim=True)
    _, s, vh = torch.linalg.svd(xc, full_matrices=False)
    comps = vh[:n_components]
    idx = comps.abs().argmax(-1)
    signs = torch.sign(comps[torch.arange(n_components), idx])
    comps = comps * signs[:, None]
    ratio = (s**2 / (s**2).sum().clamp_min(torch.finfo(x.dtype).tiny))[:n_components]
    return xc @ comps.T, ratio

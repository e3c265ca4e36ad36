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

Data (Algorithm "multitask dataset"): :func:`pgm_wm.datasets.windows.make_windows` cuts each trajectory into
non-overlapping windows of ``k`` steps; the context of window :math:`j` is the set of the
``k - 1`` interactions that lie entirely inside window :math:`j-1`, so every time index in a
window's context is strictly before the window's first step. The state filter restarts from
its initial belief in every window; only the task carries information across windows.
Test-time inference over a long trajectory (:func:`pgm_wm.evaluation.infer_trajectory`) runs the same model
window by window. :func:`pgm_wm.datasets.windows.resample_past_contexts` swaps contexts for those of random earlier
windows of the same trajectory (a training variant); :func:`pgm_wm.evaluation.evaluate_windows` computes the
chapter's one-step / open-loop RMSEs, with and without hidden observations, in original units.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_last_dims, check_mask, check_tensor, mask_observations
from .beliefs import DiagGaussian, FactorizedBelief
from .factorized import linear_cause
from .filtering import FilterResult
from .rkn import RKN, Cause, LocallyLinearTransition, ObservationEncoder, mlp, over_time

__all__ = [
    "LinearTaskTransform",
    "NonlinearTaskTransform",
    "RecurrentContextEncoder",
    "HiPRSSM",
    "CarriedHiPRSSM",
]

WorldModel = Callable[..., tuple[Tensor, Tensor]]


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
                   batch_size: int | None = None, like: Tensor | None = None, *,
                   validate: bool = True) -> DiagGaussian:
        r"""Context update: :math:`p(l\mid\mathcal C) = \mathcal N(\mu_l, \operatorname{diag}\sigma_l)`.

        ``context: (B, N, F)``, ``context_mask: (B, N)``; present elements must be finite (padded
        ones may hold anything, NaN included: they are zeroed before the encoder sees them).
        ``context=None`` means an empty set: the encoder's prior is returned for ``batch_size``
        rows (dtype/device of ``like``). Returns a :class:`pgm_wm.beliefs.DiagGaussian` (it unpacks
        as ``mean, var``). ``validate=False`` skips the checks (a caller that checked once).
        """
        if context is None:
            if batch_size is None or like is None or self.context_dim is None:
                raise ValueError("context: None needs batch_size, like and an encoder with in_dim")
            context = torch.zeros(batch_size, 1, self.context_dim, dtype=like.dtype, device=like.device)
            context_mask = torch.zeros(batch_size, 1, dtype=torch.bool, device=like.device)
        if validate:
            check_tensor("context", context, 2)
            if context_mask is not None:
                context_mask = check_mask("context_mask", context_mask, tuple(context.shape[:-1]))
        if context_mask is not None:
            context = torch.where(context_mask[..., None], context,
                                  torch.zeros((), dtype=context.dtype, device=context.device))
        if validate:
            check_finite("context", context)
        return DiagGaussian(*self.context_encoder(context, context_mask))

    def task_cause(self, task: DiagGaussian | Tensor, task_var: Tensor | None = None) -> FactorizedBelief:
        """The task's contribution to the prior (mean and factorized covariance), ``(B, 2m)``."""
        return self.task_transform(_as_task(task, task_var))

    def _task(self, obs: Tensor, context: Tensor | None, context_mask: Tensor | None,
              task: DiagGaussian | tuple[Tensor, Tensor] | None, validate: bool = True) -> DiagGaussian:
        if task is not None and not validate:
            return DiagGaussian(*task)
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
               context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None,
               init: FactorizedBelief | None = None, *, validate: bool = True) -> tuple[FilterResult, DiagGaussian]:
        """Filter one window: ``(FilterResult, task)``. The task is inferred from the context (or
        given as ``task = DiagGaussian(mean, var)``, ``(B, task_dim)``) once and enters every
        predict step as one more cause of the ac-RKN's filter path
        (:meth:`pgm_wm.acrkn.AcRKN.filter`); a task given per step, ``(B, T, task_dim)``, enters
        step ``t``'s predict with its own value (:class:`CarriedHiPRSSM`). ``init`` is
        the state belief at the window's first step (default: the RKN's initial belief, i.e. the
        state restarts in every window). ``validate=False`` skips the input checks."""
        from .acrkn import check_sequences

        if validate:
            mask = check_sequences(obs, actions, mask, self.obs_dim, self.acrkn.action_dim, model=self)
        task_mean, task_var = (None, None) if task is None else task
        if task_mean is not None and task_mean.ndim == 3:          # one task per step, e.g. per window
            if validate:
                if task_mean.shape[:2] != obs.shape[:2]:
                    raise ValueError(f"task: a task per step needs shape (B, T, task_dim) with (B, T) = "
                                     f"{tuple(obs.shape[:2])}, got {tuple(task_mean.shape)}")
                self._task(obs, None, None, (task_mean.flatten(1), task_var.flatten(1)))
            belief = DiagGaussian(task_mean, task_var)
            task_cause = self.task_cause(belief)
        else:
            belief = self._task(obs, context, context_mask, task, validate)
            task_cause = over_time(self.task_cause(belief), obs.shape[1])
        out = self.acrkn.filter(obs, actions, mask, causes=[task_cause], init=init, validate=False)
        return out, belief

    def decode_predictions(self, out: FilterResult, obs: Tensor, mask: Tensor | None,
                           last: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The ac-RKN's readout of the predictions, :meth:`pgm_wm.acrkn.AcRKN.decode_predictions`."""
        return self.acrkn.decode_predictions(out, obs, mask, last)

    def predict(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None, context: Tensor | None = None,
                context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(mean, var, task_mean, task_var)``: next-observation predictions ``(B, T, do)`` and the task."""
        check_tensor("obs", obs, 3)
        if mask is not None:
            mask = check_mask("mask", mask, tuple(obs.shape[:2]))
        enc = self.context_encoder
        in_dim = getattr(enc, "in_dim", None) or getattr(getattr(enc, "encoder", None), "in_dim", None)
        if context is not None and in_dim is not None:
            check_last_dims("context", context, (None, in_dim))
        out, belief = self.filter(obs, actions, mask, context, context_mask, task)
        mean, var = self.decode_predictions(out, obs, mask)
        return mean, var, belief.mean, belief.var

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None, context: Tensor | None = None,
                context_mask: Tensor | None = None, task: DiagGaussian | tuple[Tensor, Tensor] | None = None
                ) -> tuple[Tensor, Tensor]:
        """Predict :math:`o_{t+1}` for every ``t`` of the window: ``(mean, var)`` each ``(B, T, do)``."""
        mean, var, _, _ = self.predict(obs, actions, mask, context, context_mask, task)
        return mean, var


class CarriedHiPRSSM(nn.Module):
    r"""A HiP-RSSM run over a whole sequence, window after window, that carries its beliefs.

    The sequence ``obs: (B, T, do)`` is cut into windows of ``window`` steps (padded at the end;
    padded steps are unobserved). Window :math:`j` starts from

    * the state belief the filter reached at the end of window :math:`j-1` (its last predicted
      prior) instead of restarting from :math:`\mathcal N(0, \text{init\_var}\, I)`, and
    * the task posterior :math:`p(l_j\mid\mathcal C_j)` from the observed interactions of window
      :math:`j-1`; a row whose context set is empty (window :math:`j-1` was predicted open loop)
      keeps its last task posterior. The first window uses the task prior.

    So, unlike :func:`pgm_wm.evaluation.trajectory_world_model` (windows independent given their
    contexts, run as one batch), an open-loop stretch of many windows keeps the state and the
    task inferred before it. The windows run one after another; the result is a world model
    ``f(obs, actions, mask) -> (mean, var)`` (index ``t`` predicts :math:`o_{t+1}`) that trains
    with :func:`pgm_wm.training.fit` like any other. The difference readout's memory is carried
    across window boundaries too (:meth:`pgm_wm.acrkn.DifferenceReadout.forward`, ``last``).
    """

    def __init__(self, hip: HiPRSSM, window: int, diff_shift: Tensor | Sequence[float] | None = None,
                 diff_scale: Tensor | Sequence[float] | None = None) -> None:
        super().__init__()
        if not isinstance(window, int) or window < 2:
            raise ValueError(f"window: must be an int >= 2, got {window!r}")
        if not isinstance(hip, HiPRSSM):
            raise ValueError(f"hip: expected a HiPRSSM, got {type(hip).__name__}")
        self.hip, self.window = hip, window
        do = hip.obs_dim
        self.register_buffer("diff_shift", torch.zeros(do) if diff_shift is None else torch.as_tensor(diff_shift).clone())
        self.register_buffer("diff_scale", torch.ones(do) if diff_scale is None else torch.as_tensor(diff_scale).clone())
        self.obs_dim = do

    def tasks(self, obs: Tensor, actions: Tensor, valid: Tensor) -> DiagGaussian:
        """The task of every window, ``(B, K, task_dim)``: window ``j`` gets the task posterior
        from the observed interactions of window ``j - 1``, or keeps the task of window ``j - 1``
        when that context set is empty; window 0 the task prior. ``obs, actions, valid`` are
        ``(B, K * H, ·)`` with the masked observations zeroed. The windows' context sets do not
        depend on the filter, so all are encoded at once; the carrying rule is an index gather."""
        from .datasets.windows import context_features

        B, Tp = valid.shape
        k = self.window
        n_win = Tp // k
        view = lambda x: x.reshape(B, n_win, k, *x.shape[2:])  # noqa: E731
        shift, scale = self.diff_shift.to(obs.dtype), self.diff_scale.to(obs.dtype)
        ctx, cmask = context_features(view(obs), view(actions), view(valid), shift, scale)   # window j's own
        post = self.hip.infer_task(ctx.flatten(0, 1), cmask.flatten(0, 1), validate=False)
        prior = self.hip.infer_task(None, None, B, obs)
        # table row 0: the prior; row 1 + i: the posterior from window i's context
        table_mean = torch.cat([prior.mean[:, None], post.mean.reshape(B, n_win, -1)], 1)
        table_var = torch.cat([prior.var[:, None], post.var.reshape(B, n_win, -1)], 1)
        seen = cmask.any(-1)                                                     # (B, K)
        idx = torch.arange(n_win, device=obs.device)
        last_seen = torch.where(seen, idx + 1, 0).cummax(1).values               # row of the latest seen window
        source = torch.cat([torch.zeros_like(last_seen[:, :1]), last_seen[:, :-1]], 1)   # window j: rows up to j - 1
        pick = source[..., None].expand(B, n_win, table_mean.shape[-1])
        return DiagGaussian(table_mean.gather(1, pick), table_var.gather(1, pick))

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``obs: (B, T, do)``, ``actions: (B, T, da)``, ``mask: (B, T)`` -> ``(mean, var)`` each
        ``(B, T, do)``; masked observations are zeroed first and never reach the beliefs.

        Carrying the state belief from window to window is filtering the whole sequence in one
        run, with the task cause of step ``t`` the task of ``t``'s window (:meth:`tasks`); so this
        is one call of the HiP-RSSM's filter with a task per step, and the readout's memory runs
        on across the windows as well."""
        from .acrkn import check_sequences
        from .datasets.windows import pad_to_windows

        mask = check_sequences(obs, actions, mask, self.obs_dim, model=self.hip)
        B, T, _ = obs.shape
        valid = torch.ones(B, T, dtype=torch.bool, device=obs.device) if mask is None else mask
        obs = mask_observations(obs, valid)
        o, a, v = (pad_to_windows(x, self.window) for x in (obs, actions, valid))
        task = self.tasks(o, a, v)
        per_step = task.map(lambda x: x.repeat_interleave(self.window, dim=1))
        out, _ = self.hip.filter(o, a, v, task=per_step, validate=False)
        mu, var = self.hip.decode_predictions(out, o, v)
        return mu[:, :T], var[:, :T]

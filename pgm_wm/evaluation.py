r"""Evaluation of world models: multi-step / open-loop prediction and window-wise scores.

* :func:`sliding_windows` — cut long sequences into (overlapping) evaluation windows.
* :func:`multistep_predict` — give a model a context of observations and predict open-loop from
  the actions alone, Eq. (acrkn-multistep); no later observation is passed to the model at all.
* :func:`evaluate_open_loop` / :class:`OpenLoopResult` — **the** open-loop evaluator: windows of
  ``context + horizon`` steps, predictions in original units, per-horizon
  (``metric_window=1``) or sliding-window RMSE and NLL (Eq. metric-sliding-rmse /
  metric-sliding-nll), ``inf`` where a model diverged.
* Chapter 5 (windows with context sets, :class:`pgm_wm.datasets.windows.HiPWindows`):
  :func:`infer_trajectory` (test-time inference window by window), :func:`predict_windows`,
  :func:`window_rmse`, :func:`evaluate_windows` (the chapter's four RMSEs) and
  :func:`latent_pca` (a view of the task latents).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from ._checks import check_last_dims, check_mask, check_tensor, mask_observations
from .datasets.windows import HiPWindows, make_windows, pad_to_windows
from .hiprssm import HiPRSSM
from .metrics import denormalize, denormalize_var, rmse, sliding_window_nll, sliding_window_rmse
from .training import observation_mask

__all__ = [
    "sliding_windows",
    "multistep_predict",
    "OpenLoopResult",
    "evaluate_open_loop",
    "infer_trajectory",
    "trajectory_world_model",
    "predict_windows",
    "window_rmse",
    "evaluate_windows",
    "latent_pca",
]

WorldModel = Callable[..., tuple[Tensor, Tensor]]


def sliding_windows(x: Tensor, length: int, stride: int) -> Tensor:
    """Cut ``x: (B, T, ...)`` (any dtype, e.g. a mask) into windows ``(B * n_windows, length, ...)``
    starting every ``stride`` steps (windows of sequence 0 first)."""
    if not isinstance(x, Tensor):
        raise ValueError(f"x: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 2:
        raise ValueError(f"x: expected (B, T, ...), got shape {tuple(x.shape)}")
    T = x.shape[1]
    if not isinstance(length, int) or not 1 <= length <= T:
        raise ValueError(f"length: must be an int in [1, {T}], got {length!r}")
    if not isinstance(stride, int) or stride <= 0:
        raise ValueError(f"stride: must be a positive int, got {stride!r}")
    starts = range(0, T - length + 1, stride)
    w = torch.stack([x[:, s:s + length] for s in starts], dim=1)  # (B, n, length, ...)
    return w.reshape(-1, length, *x.shape[2:])


def multistep_predict(
    model: WorldModel,
    obs: Tensor,
    actions: Tensor,
    context_len: int,
    horizon: int | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Open-loop prediction after a context, Eq. (acrkn-multistep).

    The model sees ``obs[:, :context_len]`` and the actions ``actions[:, :context_len + horizon - 1]``;
    later observations are **not passed** to it (zeros and ``mask`` False are), so no future
    observation can leak. Returns ``(mean, var)`` of shape ``(B, horizon, do)`` where index
    ``k - 1`` is the :math:`k`-step-ahead prediction of the observation at step
    ``context_len - 1 + k``.

    ``obs: (B, T_obs, do)`` needs only the context (``T_obs >= context_len``; longer is fine,
    the rest is ignored), ``actions: (B, T_act, da)`` at least ``context_len + horizon - 1``
    steps: to forecast past the end of the data, pass the observations you have and the actions
    you plan, no dummy observations. ``horizon`` defaults to ``T_act - context_len``.
    """
    check_tensor("obs", obs, 3)
    check_tensor("actions", actions, 3)
    B, T_obs = obs.shape[:2]
    if B == 0:
        raise ValueError("obs: no sequences (B = 0); is the evaluation or validation set empty?")
    if actions.shape[0] != B:
        raise ValueError(f"actions: expected {B} sequences like obs, got shape {tuple(actions.shape)}")
    T_act = actions.shape[1]
    if not isinstance(context_len, int) or not 1 <= context_len <= min(T_obs, T_act):
        raise ValueError(f"context_len: must be an int in [1, {min(T_obs, T_act)}] (observed and acted steps), "
                         f"got {context_len!r}")
    if horizon is None:
        horizon = T_act - context_len
    if not isinstance(horizon, int) or not 1 <= horizon <= T_act - context_len + 1:
        raise ValueError(f"horizon: must be an int in [1, {T_act - context_len + 1}] (the actions cover "
                         f"{T_act} steps), got {horizon!r}")
    L = context_len + horizon - 1  # inputs 0..L-1; output L-1 predicts the observation at step L
    mask = torch.zeros(B, L, dtype=torch.bool, device=obs.device)
    mask[:, :context_len] = True
    seen = obs.new_zeros(B, L, obs.shape[2])
    seen[:, :context_len] = obs[:, :context_len]
    mean, var = model(mask_observations(seen, mask), actions[:, :L], mask)
    return mean[:, context_len - 1:], var[:, context_len - 1:]


@dataclass(frozen=True)
class OpenLoopResult:
    """Open-loop predictions (original units where statistics were given) and their metrics.

    Attributes:
        mean, var, target: ``(N, horizon, do)`` for ``N`` evaluation windows; index ``k - 1`` is
            the ``k``-step-ahead prediction.
        rmse, nll: ``(horizon,)``; with ``metric_window = 1`` the RMSE / NLL of each horizon,
            otherwise Eq. (metric-sliding-rmse) / Eq. (metric-sliding-nll); ``inf`` where a
            window of the metric contains a diverged prediction.
    """

    mean: Tensor
    var: Tensor
    target: Tensor
    rmse: Tensor
    nll: Tensor

    def __getitem__(self, key: str) -> Tensor:
        """``result["rmse"]`` etc.: the fields by name (as a dict of metrics reads)."""
        if key not in ("mean", "var", "target", "rmse", "nll"):
            raise KeyError(key)
        return getattr(self, key)


@torch.no_grad()
def evaluate_open_loop(
    model: WorldModel,
    obs: Tensor,
    actions: Tensor,
    context_len: int,
    horizon: int | None = None,
    *,
    stride: int | None = None,
    obs_mean: Tensor | None = None,
    obs_std: Tensor | None = None,
    metric_window: int = 1,
    batch_size: int = 256,
) -> OpenLoopResult:
    """The package's one open-loop evaluator.

    ``obs, actions: (B, T, ·)`` (normalized, as the model sees them) are cut into windows of
    ``context_len + horizon`` steps every ``stride`` steps (:func:`sliding_windows`; defaults:
    ``horizon = T - context_len`` (whole sequences), ``stride = horizon``). In every window the
    model sees the first ``context_len`` observations and all actions and predicts the rest
    open-loop (:func:`multistep_predict`). With ``obs_mean``/``obs_std`` (training statistics)
    predictions and targets are mapped back to original units before scoring.

    A model whose predictions diverge (a non-finite mean, or a variance that is not a positive
    finite number) gets ``inf`` for both metrics at every horizon whose metric window contains
    such a prediction, instead of an error.
    """
    check_tensor("obs", obs, 3)
    if obs.shape[0] == 0:
        raise ValueError("obs: no sequences (B = 0); is the evaluation or validation set empty?")
    if (obs_mean is None) != (obs_std is None):
        raise ValueError("obs_std: give obs_mean and obs_std together")
    T = obs.shape[1]
    if not isinstance(context_len, int) or not 1 <= context_len < T:
        raise ValueError(f"context_len: must be an int in [1, {T - 1}], got {context_len!r}")
    horizon = T - context_len if horizon is None else horizon
    if not isinstance(horizon, int) or not 1 <= horizon <= T - context_len:
        raise ValueError(f"horizon: must be an int in [1, {T - context_len}], got {horizon!r}")
    if not isinstance(metric_window, int) or not 1 <= metric_window <= horizon:
        raise ValueError(f"metric_window: must be an int in [1, {horizon}], got {metric_window!r}")
    L = context_len + horizon
    ow = sliding_windows(obs, L, stride or horizon)
    aw = sliding_windows(actions, L, stride or horizon)
    parts = [multistep_predict(model, ow[i:i + batch_size], aw[i:i + batch_size], context_len, horizon)
             for i in range(0, ow.shape[0], batch_size)]
    m, v = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    y = ow[:, context_len:]
    if obs_std is not None:
        m, v, y = denormalize(m, obs_mean, obs_std), denormalize_var(v, obs_std), denormalize(y, obs_mean, obs_std)
    ok = torch.isfinite(m) & torch.isfinite(v) & (v > 0)
    m_safe, v_safe = torch.where(ok, m, y), torch.where(ok, v, torch.ones_like(v))
    bad = (~ok).flatten(2).any(-1).any(0).to(m.dtype)  # (horizon,): any diverged entry at that step
    bad = torch.cat([bad.new_zeros(metric_window - 1), bad]).unfold(0, metric_window, 1).amax(-1) > 0
    inf = torch.tensor(float("inf"), dtype=m.dtype, device=m.device)
    rmse_t = torch.where(bad, inf, sliding_window_rmse(m_safe, y, metric_window))
    nll_t = torch.where(bad, inf, sliding_window_nll(m_safe, v_safe, y, metric_window))
    return OpenLoopResult(m, v, y, rmse_t, nll_t)


# ============================================================================= Chapter 5: windows with contexts
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


def trajectory_world_model(model: HiPRSSM, window_len: int, diff_shift: Tensor | None = None,
                           diff_scale: Tensor | None = None) -> WorldModel:
    r"""A HiP-RSSM run window by window (:func:`infer_trajectory`) as a plain world model
    ``f(obs, actions, mask) -> (mean, var)`` over sequences of any length: the inputs are padded to
    whole windows (:func:`pgm_wm.datasets.windows.pad_to_windows`; padded steps are unobserved) and
    the outputs cut back, so it can be scored by :func:`evaluate_open_loop` like any other model."""
    if not isinstance(window_len, int) or window_len < 2:
        raise ValueError(f"window_len: must be an int >= 2, got {window_len!r}")

    def world_model(obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_tensor("obs", obs, 3)
        T = obs.shape[1]
        valid = torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device) if mask is None else \
            check_mask("mask", mask, tuple(obs.shape[:2]))
        o, a, v = (pad_to_windows(x, window_len) for x in (obs, actions, valid))
        mean, var, _, _ = infer_trajectory(model, o, a, window_len, v, diff_shift, diff_scale)
        return mean[:, :T], var[:, :T]

    return world_model


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
        obs = mask_observations(obs, m)
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
        mask = observation_mask((W, k), keep, 1, open_loop_prob=0.0 if obs_steps is None else 1.0,
                                open_loop_start=obs_steps, generator=torch.Generator().manual_seed(int(seed)))
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

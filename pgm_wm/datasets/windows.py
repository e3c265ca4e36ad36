r"""Cutting sequences into windows, and the windows-with-context-sets of Chapter 5.

* :func:`pad_to_windows`, :func:`to_windows` — pad the time axis to whole windows of :math:`H`
  steps and reshape ``(B, T, ...)`` to ``(B, K, H, ...)`` (the slow time scale of Chapter 6).
* :func:`context_features` — interaction features :math:`[o_t, a_t, \Delta o_t]` and their mask.
* :func:`make_windows` / :class:`HiPWindows` — the multitask dataset of Chapter 5 (Algorithm
  "multitask dataset"): non-overlapping windows of ``k`` steps, each with the interactions of
  the previous window as its context set; :func:`resample_past_contexts` swaps in the context
  of a random earlier window of the same trajectory.

Evaluation windows (overlapping, for open-loop scores) are :func:`pgm_wm.evaluation.sliding_windows`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from .._checks import check_last_dims, check_mask, check_tensor, mask_observations

__all__ = [
    "transition_features",
    "pad_to_windows",
    "to_windows",
    "context_features",
    "HiPWindows",
    "make_windows",
    "resample_past_contexts",
]


def pad_to_windows(x: Tensor, window: int, name: str = "x") -> Tensor:
    """Pad the time axis (axis 1) of ``x: (B, T, ...)`` with zeros to a multiple of ``window``."""
    if x.ndim < 2:
        raise ValueError(f"{name}: expected (B, T, ...), got shape {tuple(x.shape)}")
    if window <= 0:
        raise ValueError(f"window: must be positive, got {window}")
    T = x.shape[1]
    pad = (-T) % window
    if pad == 0:
        return x
    return torch.cat([x, x.new_zeros(x.shape[0], pad, *x.shape[2:])], dim=1)


def to_windows(x: Tensor, window: int, name: str = "x") -> Tensor:
    """Reshape ``x: (B, T, ...)`` with ``T = K * window`` to ``(B, K, window, ...)``."""
    if x.ndim < 2:
        raise ValueError(f"{name}: expected (B, T, ...), got shape {tuple(x.shape)}")
    if window <= 0 or x.shape[1] % window:
        raise ValueError(f"{name}: time length {x.shape[1]} is not a multiple of window={window}")
    return x.reshape(x.shape[0], x.shape[1] // window, window, *x.shape[2:])



def transition_features(obs: Tensor, actions: Tensor) -> Tensor:
    r"""Per-step transition elements :math:`[o_t, a_t, o_{t+1}-o_t]` for :math:`t = 1..T-1`.

    Shapes: ``obs: (..., T, d_obs)``, ``actions: (..., T, d_act)`` -> ``(..., T-1, 2 d_obs + d_act)``.
    Pass already-normalized observations/actions; the difference is taken of what is passed (for
    the arm datasets normalize it afterwards with the training ``diff`` statistics, or pass
    normalized inputs and let the network rescale).
    """
    check_tensor("obs", obs, min_ndim=2)
    check_tensor("actions", actions, min_ndim=2)
    if obs.shape[:-1] != actions.shape[:-1]:
        raise ValueError(
            f"actions: leading shape {tuple(actions.shape[:-1])} differs from obs {tuple(obs.shape[:-1])}"
        )
    if obs.shape[-2] < 2:
        raise ValueError(f"obs: need at least 2 time steps, got {obs.shape[-2]}")
    return torch.cat([obs[..., :-1, :], actions[..., :-1, :], obs[..., 1:, :] - obs[..., :-1, :]], dim=-1)



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
    unit scale; by default the raw difference is used (:func:`transition_features`).
    Missing observations are zeroed, so their values never reach a present feature.
    """
    check_tensor("obs", obs, 2)
    check_tensor("actions", actions, 2)
    do = obs.shape[-1]
    if valid is None:
        valid = torch.ones(obs.shape[:-1], dtype=torch.bool, device=obs.device)
    valid = check_mask("valid", valid, tuple(obs.shape[:-1]))
    obs = mask_observations(obs, valid)
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
        """``(obs, actions, valid, context, context_mask)``: the minibatch layout of :func:`pgm_wm.training.imputation_loss_fn`."""
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

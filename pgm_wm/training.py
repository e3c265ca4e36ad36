r"""Training and evaluation utilities shared by the model chapters (3-6).

* :func:`set_seed` — seed Python, numpy and torch; returns a seeded ``torch.Generator``.
* :func:`imputation_mask` — random observation masks for self-supervised multi-step training:
  each observation is kept with probability ``keep_prob``, the first ``context_steps`` always.
* :func:`fit` — a generic minibatch loop: Adam, gradient-norm clipping, seeded shuffling,
  optional random time crops, ``tqdm`` progress, per-epoch training loss / validation metric,
  optionally keeps the parameters of the best validation epoch.
* :func:`prediction_loss` / :func:`imputation_loss_fn` — the next-observation loss for any
  model with the world-model interface ``model(obs, actions, mask) -> (mean, var)`` whose index
  ``t`` predicts :math:`o_{t+1}` (:class:`pgm_wm.acrkn.AcRKN` and :mod:`pgm_wm.baselines`).
* :func:`multistep_predict` — give a model a context of observations and predict open-loop from
  the actions alone; no observation after the context is passed to the model at all.
* :func:`multistep_metrics` — RMSE and NLL per prediction horizon over sliding windows.
* :func:`sliding_windows` — cut long sequences into (overlapping) evaluation windows.
"""

from __future__ import annotations

import copy
import random
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from ._checks import check_mask, check_tensor
from .metrics import gaussian_nll, rmse

__all__ = [
    "set_seed",
    "imputation_mask",
    "random_crop",
    "FitHistory",
    "fit",
    "prediction_loss",
    "imputation_loss_fn",
    "multistep_predict",
    "multistep_metrics",
    "sliding_windows",
]


def set_seed(seed: int) -> torch.Generator:
    """Seed ``random``, ``numpy`` and ``torch``; return a ``torch.Generator`` seeded with ``seed``."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    random.seed(int(seed))
    np.random.seed(int(seed) % 2**32)
    torch.manual_seed(int(seed))
    return torch.Generator().manual_seed(int(seed))


def imputation_mask(
    shape: Sequence[int],
    keep_prob: float,
    context_steps: int = 0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    open_loop_prob: float = 0.0,
) -> Tensor:
    """Random observation mask ``(B, T)`` (True = observed) for imputation training.

    Every entry is kept independently with probability ``keep_prob``; the first ``context_steps``
    steps of every sequence are always kept. With probability ``open_loop_prob`` a sequence
    additionally loses *every* observation after a cut point drawn uniformly from
    ``[context_steps, T)``, so that long open-loop stretches (as in multi-step evaluation) are
    seen in training. Resample it for every batch.
    """
    if len(shape) != 2 or any(int(s) <= 0 for s in shape):
        raise ValueError(f"shape: expected (B, T) with positive sizes, got {tuple(shape)}")
    if not 0.0 <= keep_prob <= 1.0:
        raise ValueError(f"keep_prob: must be in [0, 1], got {keep_prob}")
    if context_steps < 0:
        raise ValueError(f"context_steps: must be >= 0, got {context_steps}")
    if not 0.0 <= open_loop_prob <= 1.0:
        raise ValueError(f"open_loop_prob: must be in [0, 1], got {open_loop_prob}")
    B, T = int(shape[0]), int(shape[1])
    mask = torch.rand(B, T, generator=generator) < keep_prob
    if open_loop_prob > 0 and context_steps < T:
        cut = torch.randint(context_steps, T, (B,), generator=generator)
        tail = torch.rand(B, generator=generator) < open_loop_prob
        after = torch.arange(T)[None, :] >= cut[:, None]
        mask &= ~(after & tail[:, None])
    mask[:, : min(context_steps, T)] = True
    return mask.to(device) if device is not None else mask


def _time_tensors(tensors: Sequence[Tensor]) -> tuple[int, list[bool]]:
    T = tensors[0].shape[1] if tensors[0].ndim >= 2 else None
    flags = [T is not None and t.ndim >= 2 and t.shape[1] == T for t in tensors]
    return T, flags


def random_crop(tensors: Sequence[Tensor], crop_len: int, generator: torch.Generator | None = None) -> tuple[Tensor, ...]:
    """Crop every sequence of a batch to a random window of ``crop_len`` steps.

    The time axis is axis 1 of the *first* tensor; every tensor with ``ndim >= 2`` and the same
    size on axis 1 is cropped with the same per-sequence start, the others (e.g. per-sequence
    parameters ``(B, k)``) pass unchanged.
    """
    T, flags = _time_tensors(tensors)
    if T is None:
        raise ValueError("tensors: the first tensor needs a time axis (B, T, ...)")
    if crop_len <= 0:
        raise ValueError(f"crop_len: must be positive, got {crop_len}")
    if crop_len >= T:
        return tuple(tensors)
    B = tensors[0].shape[0]
    start = torch.randint(0, T - crop_len + 1, (B,), generator=generator)
    idx = start[:, None] + torch.arange(crop_len)[None, :]
    rows = torch.arange(B)[:, None]
    return tuple(t[rows, idx] if f else t for t, f in zip(tensors, flags))


@dataclass
class FitHistory:
    """What :func:`fit` recorded: one entry per epoch, plus the total wall time (s)."""

    train_loss: list[float] = field(default_factory=list)
    valid_metric: list[float] = field(default_factory=list)
    epoch_time: list[float] = field(default_factory=list)
    wall_time: float = 0.0
    best_epoch: int | None = None

    @property
    def final_train_loss(self) -> float:
        return self.train_loss[-1] if self.train_loss else float("nan")


def fit(
    loss_fn: Callable[[tuple[Tensor, ...], torch.Generator], Tensor],
    params_or_model: nn.Module | Iterable[nn.Parameter],
    train_tensors: Sequence[Tensor],
    batch_size: int,
    epochs: int,
    lr: float = 3e-3,
    clip_norm: float | None = 5.0,
    seed: int = 0,
    valid_fn: Callable[[], float] | None = None,
    progress: bool = True,
    crop_len: int | None = None,
    weight_decay: float = 0.0,
    max_batches: int | None = None,
    keep_best: bool = False,
    desc: str = "train",
) -> FitHistory:
    """Minimize ``loss_fn`` with Adam over minibatches of ``train_tensors``.

    Args:
        loss_fn: ``loss_fn(batch, generator) -> scalar`` where ``batch`` is the tuple of the
            minibatch slices of ``train_tensors`` (after cropping) and ``generator`` a seeded
            ``torch.Generator`` for any randomness of the loss (e.g. :func:`imputation_mask`).
        params_or_model: an ``nn.Module`` (put in train mode while fitting, eval mode for
            ``valid_fn``) or an iterable of parameters.
        train_tensors: tensors sharing the first (sequence) axis.
        batch_size, epochs, lr, weight_decay: the usual; ``clip_norm`` clips the global gradient
            norm (``None``: no clipping).
        seed: seeds the shuffling, the crops and the generator passed to ``loss_fn``.
        valid_fn: called after every epoch under ``torch.no_grad()``; returns a float (lower is
            better) that is recorded in ``valid_metric``.
        crop_len: if given, every minibatch is cut to a random window of ``crop_len`` steps
            (:func:`random_crop`), which speeds up recurrent models a lot.
        max_batches: stop an epoch after this many minibatches (for quick runs).
        keep_best: with ``valid_fn`` and a module, restore the parameters of the best epoch.
    """
    if not train_tensors:
        raise ValueError("train_tensors: need at least one tensor")
    n = train_tensors[0].shape[0]
    for i, t in enumerate(train_tensors):
        if not isinstance(t, Tensor) or t.shape[0] != n:
            raise ValueError(f"train_tensors: tensor {i} must be a Tensor with {n} rows")
    if batch_size <= 0 or epochs < 0:
        raise ValueError(f"batch_size: need batch_size > 0 and epochs >= 0, got {batch_size}, {epochs}")
    if lr <= 0:
        raise ValueError(f"lr: must be positive, got {lr}")
    if clip_norm is not None and clip_norm <= 0:
        raise ValueError(f"clip_norm: must be positive or None, got {clip_norm}")
    if keep_best and (valid_fn is None or not isinstance(params_or_model, nn.Module)):
        raise ValueError("keep_best: needs valid_fn and a module")
    model = params_or_model if isinstance(params_or_model, nn.Module) else None
    params = [p for p in (model.parameters() if model is not None else params_or_model) if p.requires_grad]
    if not params:
        raise ValueError("params_or_model: no trainable parameters")
    opt = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)
    gen = torch.Generator().manual_seed(int(seed))
    hist = FitHistory()
    best, best_state = float("inf"), None
    n_batches = (n + batch_size - 1) // batch_size
    if max_batches is not None:
        n_batches = min(n_batches, max_batches)
    t_start = time.perf_counter()
    bar = tqdm(range(epochs), desc=desc, disable=not progress, leave=True)
    for _epoch in bar:
        t0 = time.perf_counter()
        if model is not None:
            model.train()
        perm = torch.randperm(n, generator=gen)
        total, count = 0.0, 0
        for b in range(n_batches):
            idx = perm[b * batch_size:(b + 1) * batch_size]
            batch = tuple(t[idx] for t in train_tensors)
            if crop_len is not None:
                batch = random_crop(batch, crop_len, gen)
            loss = loss_fn(batch, gen)
            if loss.ndim != 0:
                raise ValueError(f"loss_fn: must return a scalar, got shape {tuple(loss.shape)}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if clip_norm is not None:
                nn.utils.clip_grad_norm_(params, clip_norm)
            opt.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
        hist.train_loss.append(total / count)
        post = {"loss": f"{hist.train_loss[-1]:.4g}"}
        if valid_fn is not None:
            if model is not None:
                model.eval()
            with torch.no_grad():
                v = float(valid_fn())
            hist.valid_metric.append(v)
            post["valid"] = f"{v:.4g}"
            if v < best:
                best, hist.best_epoch = v, len(hist.valid_metric) - 1
                if keep_best and model is not None:
                    best_state = copy.deepcopy(model.state_dict())
        hist.epoch_time.append(time.perf_counter() - t0)
        bar.set_postfix(post)
    if model is not None:
        if keep_best and best_state is not None:
            model.load_state_dict(best_state)
        model.eval()
    hist.wall_time = time.perf_counter() - t_start
    return hist


def prediction_loss(
    model: Callable[..., tuple[Tensor, Tensor]],
    obs: Tensor,
    actions: Tensor,
    mask: Tensor | None = None,
    valid: Tensor | None = None,
    loss: str = "nll",
) -> Tensor:
    r"""Next-observation loss of a world model: outputs at ``t = 0..T-2`` against ``obs[:, 1:]``.

    ``loss="nll"``: :func:`pgm_wm.metrics.gaussian_nll` (Eq. metric-nll); ``"mse"``: mean squared
    error of the mean; ``"rmse"``: its square root (the thesis' deterministic objective). ``valid:
    (B, T)`` marks real (non-padding) steps; a target counts if it is valid. All targets count,
    observed or not, so with an imputation mask this trains multi-step prediction.
    """
    check_tensor("obs", obs, 3)
    if obs.shape[1] < 2:
        raise ValueError(f"obs: need at least 2 time steps, got {obs.shape[1]}")
    if loss not in ("nll", "mse", "rmse"):
        raise ValueError(f"loss: expected 'nll', 'mse' or 'rmse', got {loss!r}")
    mean, var = model(obs, actions, mask)
    target = obs[:, 1:]
    w = None if valid is None else check_mask("valid", valid, tuple(obs.shape[:2]))[:, 1:]
    if loss == "nll":
        return gaussian_nll(mean[:, :-1], var[:, :-1], target, w)
    r = rmse(mean[:, :-1], target, w)
    return r if loss == "rmse" else r * r


def imputation_loss_fn(
    model: Callable[..., tuple[Tensor, Tensor]],
    keep_prob: float = 0.25,
    context_steps: int = 5,
    loss: str = "nll",
    open_loop_prob: float = 0.0,
) -> Callable[[tuple[Tensor, ...], torch.Generator], Tensor]:
    """A ``loss_fn`` for :func:`fit` on batches ``(obs, actions[, valid])``: draws a fresh
    :func:`imputation_mask` per batch and returns :func:`prediction_loss`."""

    def loss_fn(batch: tuple[Tensor, ...], gen: torch.Generator) -> Tensor:
        obs, actions = batch[0], batch[1]
        valid = batch[2] if len(batch) > 2 else None
        mask = imputation_mask(obs.shape[:2], keep_prob, context_steps, gen, device=obs.device,
                               open_loop_prob=open_loop_prob)
        if valid is not None:
            mask = mask & valid.bool()
        return prediction_loss(model, obs, actions, mask, valid, loss)

    return loss_fn


def multistep_predict(
    model: Callable[..., tuple[Tensor, Tensor]],
    obs: Tensor,
    actions: Tensor,
    context_len: int,
    horizon: int | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Open-loop prediction after a context, Eq. (acrkn-multistep).

    The model sees ``obs[:, :context_len]`` and the actions ``actions[:, :context_len + horizon - 1]``;
    later observations are **not passed** to it (zeros and ``mask`` False are), so no future
    observation can leak. Returns ``(mean, var)`` of shape ``(B, horizon, do)`` where index
    ``k - 1`` is the :math:`k`-step-ahead prediction of ``obs[:, context_len - 1 + k]``.
    ``horizon`` defaults to ``T - context_len``.
    """
    check_tensor("obs", obs, 3)
    check_tensor("actions", actions, 3)
    B, T = obs.shape[:2]
    if tuple(actions.shape[:2]) != (B, T):
        raise ValueError(f"actions: expected leading shape {(B, T)}, got {tuple(actions.shape)}")
    if not 1 <= context_len < T:
        raise ValueError(f"context_len: must be in [1, T-1] = [1, {T - 1}], got {context_len}")
    if horizon is None:
        horizon = T - context_len
    if not 1 <= horizon <= T - context_len:
        raise ValueError(f"horizon: must be in [1, {T - context_len}], got {horizon}")
    L = context_len + horizon - 1  # inputs 0..L-1; output L-1 predicts obs[L]
    seen = torch.zeros_like(obs[:, :L])
    seen[:, :context_len] = obs[:, :context_len]
    mask = torch.zeros(B, L, dtype=torch.bool, device=obs.device)
    mask[:, :context_len] = True
    mean, var = model(seen, actions[:, :L], mask)
    return mean[:, context_len - 1:], var[:, context_len - 1:]


def sliding_windows(x: Tensor, length: int, stride: int) -> Tensor:
    """Cut ``x: (B, T, ...)`` (any dtype, e.g. a mask) into windows ``(B * n_windows, length, ...)``
    starting every ``stride`` steps (windows of sequence 0 first)."""
    if not isinstance(x, Tensor):
        raise ValueError(f"x: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 2:
        raise ValueError(f"x: expected (B, T, ...), got shape {tuple(x.shape)}")
    T = x.shape[1]
    if not 1 <= length <= T:
        raise ValueError(f"length: must be in [1, {T}], got {length}")
    if stride <= 0:
        raise ValueError(f"stride: must be positive, got {stride}")
    starts = range(0, T - length + 1, stride)
    w = torch.stack([x[:, s:s + length] for s in starts], dim=1)  # (B, n, length, ...)
    return w.reshape(-1, length, *x.shape[2:])


def multistep_metrics(
    model: Callable[..., tuple[Tensor, Tensor]],
    obs: Tensor,
    actions: Tensor,
    context_len: int,
    horizon: int,
    stride: int | None = None,
    obs_mean: Tensor | None = None,
    obs_std: Tensor | None = None,
    batch_size: int = 256,
) -> dict[str, Tensor]:
    """RMSE and NLL of :func:`multistep_predict` for every horizon ``1..horizon``.

    Sequences ``obs, actions: (B, T, ·)`` are cut into windows of ``context_len + horizon`` steps
    every ``stride`` steps (default: ``horizon``); each window gives a context and an open-loop
    stretch. With ``obs_mean``/``obs_std`` (training statistics) predictions and targets are
    mapped back to original units before scoring (:func:`pgm_wm.metrics.denormalize`).

    Returns ``{"rmse": (horizon,), "nll": (horizon,), "mean": (N, horizon, do), "var": ...,
    "target": ...}`` with ``N`` the number of windows (predictions in the scored units).
    """
    from .metrics import denormalize, denormalize_var

    L = context_len + horizon
    if (obs_mean is None) != (obs_std is None):
        raise ValueError("obs_std: give obs_mean and obs_std together")
    ow = sliding_windows(obs, L, stride or horizon)
    aw = sliding_windows(actions, L, stride or horizon)
    means, vars_ = [], []
    with torch.no_grad():
        for i in range(0, ow.shape[0], batch_size):
            mu, var = multistep_predict(model, ow[i:i + batch_size], aw[i:i + batch_size], context_len, horizon)
            means.append(mu)
            vars_.append(var)
    mean, var = torch.cat(means), torch.cat(vars_)
    target = ow[:, context_len:]
    if obs_std is not None:
        mean, var = denormalize(mean, obs_mean, obs_std), denormalize_var(var, obs_std)
        target = denormalize(target, obs_mean, obs_std)
    return {"rmse": rmse(mean, target, dim=(0, 2)), "nll": gaussian_nll(mean, var, target, dim=(0, 2)),
            "mean": mean, "var": var, "target": target}

r"""Training: seeding, observation masks, the one loss factory and the one fit loop.

* :func:`set_seed` — seed Python, numpy and torch; returns a seeded ``torch.Generator``.
* :func:`observation_mask` — the one random observation-mask generator (True = observed): a
  per-step keep probability, always-kept context steps, whole-window drops and open-loop cuts.
  Imputation training (Chapters 4–6) and the seeded evaluation masks of Chapter 5 are all
  special cases.
* :func:`prediction_loss` — the next-observation loss of any world model
  ``model(obs, actions, mask) -> (mean, var)`` whose index ``t`` predicts :math:`o_{t+1}`
  (or, for a filter ``model(obs, mask)``, the loss against per-step targets).
* :func:`imputation_loss_fn` — the one loss factory: "draw an :func:`observation_mask`, call
  :func:`prediction_loss`", for every chapter's batches.
* :func:`floor_variance` — wrap a model so its predictive variances are at least ``min_var``.
* :func:`fit` — the one minibatch loop: seeded, Adam with gradient-norm clipping, a compute
  budget in CPU seconds and/or an epoch cap, early stopping with patience and keep-best on a
  *validation* loss (after every epoch or every ``valid_every`` steps), a learning curve
  (:attr:`FitHistory.curve`), checkpoint/resume, a ``device``, and a hard stop (``ValueError``)
  at the first non-finite loss or gradient.

Multi-step / open-loop evaluation lives in :mod:`pgm_wm.evaluation`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import random
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, NoReturn, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from ._checks import NonFiniteError, check_mask, check_tensor
from .metrics import gaussian_nll, rmse

__all__ = [
    "set_seed",
    "observation_mask",
    "random_crop",
    "FitHistory",
    "fit",
    "show_progress",
    "prediction_loss",
    "floor_variance",
    "imputation_loss_fn",
]

WorldModel = Callable[..., tuple[Tensor, Tensor]]
LossFn = Callable[[Any, torch.Generator], Tensor]


def set_seed(seed: int) -> torch.Generator:
    """Seed ``random``, ``numpy`` and ``torch``; return a ``torch.Generator`` seeded with ``seed``."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    random.seed(int(seed))
    np.random.seed(int(seed) % 2**32)
    torch.manual_seed(int(seed))
    return torch.Generator().manual_seed(int(seed))


# ============================================================================= masks
def _check_prob(name: str, p: float) -> None:
    if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
        raise ValueError(f"{name}: must be in [0, 1], got {p!r}")


def observation_mask(
    shape: Sequence[int],
    keep_prob: float = 1.0,
    context_steps: int = 0,
    *,
    window: int | None = None,
    window_drop_prob: float = 0.0,
    open_loop_prob: float = 0.0,
    open_loop_start: int | None = None,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    r"""Random observation mask ``(B, T)``, True = the model may see the observation.

    Built in four steps, each optional:

    1. every step is kept independently with probability ``keep_prob``;
    2. with ``window`` = :math:`H`, every whole window of :math:`H` steps is dropped with
       probability ``window_drop_prob`` (imputation at the slow time scale, Chapter 6);
    3. with probability ``open_loop_prob`` a sequence loses *every* observation from a cut on
       (open-loop prediction from the actions alone): the cut is ``open_loop_start`` if given,
       otherwise uniform in ``[context_steps, T)``;
    4. the first ``context_steps`` steps are always kept.

    Special cases: imputation training (``keep_prob``, ``context_steps``, ``open_loop_prob``);
    window imputation (``window``, ``window_drop_prob``, ``context_steps = H``,
    ``open_loop_start = H``); the fixed evaluation masks of Chapter 5 (a seeded ``generator``,
    ``open_loop_prob=1``, ``open_loop_start = c``). Resample it for every batch.
    """
    if len(shape) != 2 or any(int(s) <= 0 for s in shape):
        raise ValueError(f"shape: expected (B, T) with positive sizes, got {tuple(shape)}")
    _check_prob("keep_prob", keep_prob)
    _check_prob("window_drop_prob", window_drop_prob)
    _check_prob("open_loop_prob", open_loop_prob)
    if not isinstance(context_steps, int) or context_steps < 0:
        raise ValueError(f"context_steps: must be an int >= 0, got {context_steps!r}")
    if window is not None and (not isinstance(window, int) or window <= 0):
        raise ValueError(f"window: must be a positive int or None, got {window!r}")
    if window is None and window_drop_prob > 0:
        raise ValueError("window_drop_prob: needs window")
    B, T = int(shape[0]), int(shape[1])
    if open_loop_start is not None and not (isinstance(open_loop_start, int) and 0 <= open_loop_start <= T):
        raise ValueError(f"open_loop_start: must be an int in [0, {T}] or None, got {open_loop_start!r}")
    mask = torch.rand(B, T, generator=generator) < keep_prob
    if window is not None and window_drop_prob > 0:
        n_win = -(-T // window)
        kept = torch.rand(B, n_win, generator=generator) >= window_drop_prob
        mask &= kept.repeat_interleave(window, dim=1)[:, :T]
    if open_loop_prob > 0:
        if open_loop_start is None:
            lo = min(context_steps, T - 1)
            cut = torch.randint(lo, T, (B,), generator=generator)
        else:
            cut = torch.full((B,), open_loop_start, dtype=torch.long)
        tail = torch.rand(B, generator=generator) < open_loop_prob
        mask &= ~((torch.arange(T)[None, :] >= cut[:, None]) & tail[:, None])
    mask[:, : min(context_steps, T)] = True
    return mask.to(device) if device is not None else mask


def _time_tensors(tensors: Sequence[Tensor]) -> tuple[int | None, list[bool]]:
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


# ============================================================================= losses
def prediction_loss(
    model: WorldModel,
    obs: Tensor,
    actions: Tensor | None,
    mask: Tensor | None = None,
    valid: Tensor | None = None,
    loss: str = "nll",
    *,
    targets: Tensor | None = None,
    extra: Sequence[Any] = (),
) -> Tensor:
    r"""The loss of a model's predictions, Eq. (metric-nll) / Eq. (metric-rmse).

    World model (``targets=None``): ``model(obs, actions, mask, *extra) -> (mean, var)``; outputs
    at ``t = 0..T-2`` are scored against ``obs[:, 1:]``. Filter (``actions=None`` and
    ``targets: (B, T, k)``): ``model(obs, mask, *extra)``; output ``t`` is scored against
    ``targets[:, t]``. ``loss="nll"``: :func:`pgm_wm.metrics.gaussian_nll`; ``"mse"``: mean squared
    error of the mean; ``"rmse"``: its square root. ``valid: (B, T)`` marks real (non-padding)
    steps; a target counts if it is valid. All targets count, observed or not, so with an
    imputation mask this trains multi-step prediction. Observations at valid steps must be finite.
    """
    check_tensor("obs", obs, 3)
    if loss not in ("nll", "mse", "rmse"):
        raise ValueError(f"loss: expected 'nll', 'mse' or 'rmse', got {loss!r}")
    v = None if valid is None else check_mask("valid", valid, tuple(obs.shape[:2]))
    bad = ~torch.isfinite(obs.detach())
    if bool((bad if v is None else bad & v[..., None]).any()):
        raise ValueError("obs: contains NaN or infinite values at valid steps")
    if targets is None:
        if obs.shape[1] < 2:
            raise ValueError(f"obs: need at least 2 time steps, got {obs.shape[1]}")
        if actions is None:
            raise ValueError("actions: a world model needs actions (give targets for a filter)")
        mean, var = model(obs, actions, mask, *extra)
        mean, var, target = mean[:, :-1], var[:, :-1], obs[:, 1:]
        w = None if v is None else v[:, 1:]
    else:
        check_tensor("targets", targets, 3)
        if tuple(targets.shape[:2]) != tuple(obs.shape[:2]):
            raise ValueError(f"targets: expected leading shape {tuple(obs.shape[:2])}, got {tuple(targets.shape)}")
        mean, var = model(obs, mask, *extra) if actions is None else model(obs, actions, mask, *extra)
        target, w = targets, v
    if loss == "nll":
        return gaussian_nll(mean, var, target, w)
    r = rmse(mean, target, w)
    return r if loss == "rmse" else r * r


def floor_variance(model: WorldModel, min_var: float = 1e-8) -> WorldModel:
    r"""Wrap a model so that its predictive variances are at least ``min_var``.

    Why: NLL training drives the variances of almost deterministic dimensions (angle differences
    given the velocity) towards 0, and one tiny variance makes the NLL explode. The floor (with
    zero gradient below it) acts only on those entries. ``wrapped(*args, **kw) -> (mean,
    var.clamp_min(min_var))``.
    """
    if not min_var > 0:
        raise ValueError(f"min_var: must be positive, got {min_var}")

    def wrapped(*args: Any, **kwargs: Any) -> tuple[Tensor, Tensor]:
        mean, var = model(*args, **kwargs)
        return mean, var.clamp_min(min_var)

    return wrapped


def imputation_loss_fn(
    model: WorldModel,
    keep_prob: float = 0.25,
    context_steps: int = 5,
    loss: str = "nll",
    open_loop_prob: float = 0.0,
    *,
    window: int | None = None,
    max_window_drop: float = 0.0,
    open_loop_start: int | None = None,
    min_var: float | None = None,
    filtering: bool = False,
) -> LossFn:
    r"""The one loss factory: a ``loss_fn(batch, generator)`` for :func:`fit` that draws a fresh
    :func:`observation_mask` per batch and returns :func:`prediction_loss`.

    Batches: a world model gets ``(obs, actions[, valid[, *extra]])`` (``extra``, e.g. the
    context set and its mask of a :class:`pgm_wm.hiprssm.HiPRSSM` window, is passed to the model
    after the mask); with ``filtering=True`` a filter ``model(obs, mask)`` gets ``(obs, valid,
    targets)``. The drawn mask is ANDed with ``valid``. With ``window``, each batch first draws a
    window-drop probability uniformly in ``[0, max_window_drop]`` (Chapter 6's two-scale
    imputation). ``min_var`` floors the predicted variances (:func:`floor_variance`).
    """
    _check_prob("keep_prob", keep_prob)
    _check_prob("max_window_drop", max_window_drop)
    _check_prob("open_loop_prob", open_loop_prob)
    if window is None and max_window_drop > 0:
        raise ValueError("max_window_drop: needs window")
    fn = model if min_var is None else floor_variance(model, min_var)

    def loss_fn(batch: Sequence[Tensor], gen: torch.Generator) -> Tensor:
        if filtering:
            obs, valid, targets = batch
            actions, extra = None, ()
        else:
            obs, actions = batch[0], batch[1]
            valid = batch[2] if len(batch) > 2 else None
            extra, targets = tuple(batch[3:]), None
        drop = float(torch.rand((), generator=gen)) * max_window_drop if max_window_drop > 0 else 0.0
        mask = observation_mask(obs.shape[:2], keep_prob, context_steps, window=window, window_drop_prob=drop,
                                open_loop_prob=open_loop_prob, open_loop_start=open_loop_start, generator=gen,
                                device=obs.device)
        if valid is not None:
            mask = mask & valid.bool()
        return prediction_loss(fn, obs, actions, mask, None if filtering else valid, loss,
                               targets=targets, extra=extra)

    return loss_fn


# ============================================================================= the fit loop
def show_progress(progress: bool | None) -> bool:
    """Whether to draw a progress bar: ``progress`` if given; else never when the environment
    variable ``PGM_WM_PROGRESS`` is ``0`` (the book build and the test command set it), always when
    it is ``1``, and otherwise only in interactive use (a terminal on stderr or a Jupyter kernel)."""
    if progress is not None:
        return bool(progress)
    env = os.environ.get("PGM_WM_PROGRESS", "").strip()
    if env == "0":
        return False
    if env == "1":
        return True
    if "ipykernel" in sys.modules:
        return True
    try:
        return sys.stderr is not None and sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


@dataclass
class FitHistory:
    """What :func:`fit` recorded.

    Per epoch (the last may be a partial epoch):

    * ``train_loss``: mean training loss of the epoch's batches.
    * ``steps``: optimizer steps done by the end of each epoch.
    * ``epoch_time``: wall seconds of each epoch.

    Per validation (after every epoch by default, every ``valid_every`` optimizer steps and at the
    end with ``valid_every``; empty without ``valid_fn``):

    * ``valid_loss``: the validation loss.
    * ``valid_steps``: optimizer steps done when it was computed.
    * ``curve``: the learning curve, one dict per validation with the keys ``step``, ``epoch``,
      ``cpu_s``, ``wall_s``, ``valid`` and ``train``; ``cpu_s`` / ``wall_s`` are CPU
      (``time.process_time``) and wall seconds from the first batch (validations included),
      ``train`` the mean training loss of the batches since the previous entry. Without
      ``valid_fn`` there is one entry per epoch with ``valid`` NaN.

    Totals:

    * ``best_epoch`` / ``best_step``: epoch index and optimizer step of the lowest validation loss
      (``None`` without one).
    * ``cpu_time`` / ``wall_time``: CPU seconds and wall seconds in total (setup included).
    * ``setup_cpu_s``: CPU seconds spent inside :func:`fit` before the first batch (checks,
      optimizer, loading a checkpoint).
    * ``stopped``: why the loop ended: ``"epochs"``, ``"budget"``, ``"patience"``, ``"interrupted"``
      or ``"diverged"`` (only with ``on_divergence="stop"``).
    * ``diverged``: with ``stopped == "diverged"``, what turned non-finite and where (else ``None``).
    * ``resumed_from_epoch``: the epoch a checkpoint resumed at (``None`` for a fresh run).
    """

    train_loss: list[float] = field(default_factory=list)
    valid_loss: list[float] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)
    epoch_time: list[float] = field(default_factory=list)
    valid_steps: list[int] = field(default_factory=list)
    curve: list[dict[str, float]] = field(default_factory=list)
    best_epoch: int | None = None
    best_step: int | None = None
    cpu_time: float = 0.0
    wall_time: float = 0.0
    setup_cpu_s: float = 0.0
    stopped: str = "epochs"
    resumed_from_epoch: int | None = None
    diverged: str | None = None

    @property
    def epochs(self) -> int:
        """Number of (possibly partial) epochs run."""
        return len(self.train_loss)

    @property
    def valid_metric(self) -> list[float]:
        """The name :attr:`valid_loss` had before the loops were merged (kept for old call sites)."""
        return self.valid_loss

    @property
    def best_valid_loss(self) -> float:
        return min(self.valid_loss) if self.valid_loss else float("nan")

    @property
    def final_train_loss(self) -> float:
        return self.train_loss[-1] if self.train_loss else float("nan")


def _batch_indices(batch: Any, idx: Tensor | None) -> list[int] | None:
    if idx is not None:
        return [int(i) for i in idx]
    seq = getattr(batch, "seq", None)
    return [int(i) for i in seq] if isinstance(seq, Tensor) else None


def _to_device(batch: Any, device: torch.device | None) -> Any:
    if device is None:
        return batch
    if isinstance(batch, Tensor):
        return batch.to(device)
    if isinstance(batch, tuple) and not hasattr(batch, "_fields"):
        return tuple(_to_device(b, device) for b in batch)
    if isinstance(batch, list):
        return [_to_device(b, device) for b in batch]
    if hasattr(batch, "_fields"):  # a NamedTuple of tensors
        return type(batch)(*(_to_device(b, device) for b in batch))
    return batch


def _resolve_device(device: torch.device | str | None) -> torch.device | None:
    if device is None:
        return None
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device: not a torch device: {device!r}") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: {device!r} requested but CUDA is not available here")
    return dev


_CHECKPOINT_FORMAT = "pgm_wm.fit checkpoint v1"


class _Diverged(Exception):
    """Raised inside :func:`fit` (and caught there) when a run diverges with ``on_divergence="stop"``."""


def fit(
    loss_fn: LossFn,
    params_or_model: nn.Module | Iterable[nn.Parameter],
    train_tensors: Sequence[Tensor] | Callable[[torch.Generator], Any],
    batch_size: int,
    epochs: int | None = None,
    lr: float = 3e-3,
    clip_norm: float | None = 5.0,
    seed: int = 0,
    valid_fn: Callable[[], float] | None = None,
    progress: bool | None = None,
    crop_len: int | None = None,
    weight_decay: float = 0.0,
    max_batches: int | None = None,
    keep_best: bool | None = None,
    desc: str = "train",
    *,
    budget_s: float | None = None,
    patience: int | None = None,
    valid_every: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    device: torch.device | str | None = None,
    max_steps: int | None = None,
    lr_patience: int | None = None,
    lr_factor: float = 0.5,
    lr_min: float = 0.0,
    on_divergence: str = "raise",
) -> FitHistory:
    """Minimize ``loss_fn`` with Adam over minibatches; the package's only training loop.

    Args:
        loss_fn: ``loss_fn(batch, generator) -> scalar``; ``batch`` is the tuple of minibatch
            slices of ``train_tensors`` (after cropping), ``generator`` a seeded
            ``torch.Generator`` for the loss' own randomness (e.g. :func:`imputation_loss_fn`).
        params_or_model: an ``nn.Module`` (train mode while fitting, eval mode for ``valid_fn``
            and at the end) or an iterable of parameters.
        train_tensors: tensors sharing the first (sequence) axis, shuffled each epoch; or a
            sampler ``sample(generator) -> batch`` (e.g. random context sets), called
            ``max_batches`` times per epoch. An empty training set is an error.
        batch_size, lr, weight_decay: the usual; ``clip_norm`` clips the global gradient norm
            (``None``: no clipping; the norm is still checked for NaN/inf).
        epochs: an epoch cap; ``budget_s``: a compute budget in **CPU seconds**
            (``time.process_time`` from the first batch on, validations included; the setup
            before it is ``FitHistory.setup_cpu_s``; checked after every batch, the epoch in
            progress ends there). At least one of the two is required. An epoch cap
            alone is reproducible; a budget is not across machines.
        seed: seeds the shuffling, the crops and the generator passed to ``loss_fn``.
        valid_fn: called under ``torch.no_grad()`` after every epoch (or every ``valid_every``
            steps); returns the validation loss (lower is better). Pass a *validation* split,
            never the test split.
        valid_every: validate every this many optimizer steps (and once more at the end if the
            last step was not validated) instead of after every epoch; ``patience`` and
            ``keep_best`` then count validations, not epochs.
        patience: stop when the validation loss has not improved for this many validations.
        keep_best: restore the parameters of the validation with the best loss (default:
            whenever ``valid_fn`` is given); also on Ctrl-C (``KeyboardInterrupt``, re-raised
            after the restore, with the history as its ``fit_history`` attribute).
        crop_len: cut every minibatch to a random window of ``crop_len`` steps (:func:`random_crop`).
        max_batches: at most this many minibatches per epoch (a positive int).
        progress: a per-batch ``tqdm`` bar with the time left (:func:`show_progress`: by default
            only in interactive use, never with ``PGM_WM_PROGRESS=0``).
        checkpoint: a file path. After every epoch the model (or parameters), the optimizer, the
            best state so far, the epoch, the step count, the CPU seconds used, the generator
            state and the history are written there (atomically); a later call with the same
            path resumes from it, so ``budget_s`` and ``epochs`` count the whole run. An existing
            file written for other parameters is an error.
        device: move the model and every batch to this device (``"auto"``: CUDA where present);
            ``None`` leaves everything where it is.
        max_steps: stop after this many optimizer steps (with or without a budget; an equal
            number of gradient steps for every model, instead of equal CPU seconds).
        lr_patience, lr_factor: multiply the learning rate by ``lr_factor`` whenever the
            validation loss has not improved for ``lr_patience`` validations in a row (a plateau
            schedule; ``None``: a constant learning rate). The learning rate of every validation
            is in the learning curve (``"lr"``).
        lr_min: the plateau schedule never lowers the learning rate below this value (a floor,
            ``0 <= lr_min <= lr``). Without one, halving after every ``lr_patience`` flat
            validations drives the rate to ``1e-10`` of its start within a long budget, and a run
            then looks converged only because it has stopped moving.
        on_divergence: what to do when training diverges after at least one optimizer step, i.e.
            the loss or the gradient norm is non-finite or ``loss_fn`` / ``valid_fn`` raises
            :class:`pgm_wm._checks.NonFiniteError` (a model output overflowed): ``"raise"``
            (default) raises ``ValueError``; ``"stop"`` ends the run there as if its budget were
            spent, with ``stopped = "diverged"`` and the message in :attr:`FitHistory.diverged`;
            the parameters are then the best validated ones (``keep_best``), else those before
            the failing step. A study that must not lose a whole run to one seed that blows up
            uses ``"stop"`` and reports the verdict. Non-finite values at the first step are
            always raised (nothing was trained; usually bad input).

    The learning curve (:attr:`FitHistory.curve`) records steps, epochs, CPU and wall seconds,
    and the training and validation losses at every validation.

    Raises ``ValueError`` naming the epoch, the batch and its sequence indices at the first
    non-finite loss or gradient norm (the parameters are then those before that step), unless
    ``on_divergence="stop"``.
    """
    cpu_enter, wall_enter = time.process_time(), time.perf_counter()
    sampler = callable(train_tensors) and not isinstance(train_tensors, (list, tuple))
    if max_batches is not None and (not isinstance(max_batches, int) or max_batches <= 0):
        raise ValueError(f"max_batches: must be a positive int or None, got {max_batches!r}")
    if sampler:
        if max_batches is None:
            raise ValueError("max_batches: a sampler needs a positive number of batches per epoch")
        n = 0
    else:
        if not train_tensors:
            raise ValueError("train_tensors: need at least one tensor")
        n = train_tensors[0].shape[0]
        for i, t in enumerate(train_tensors):
            if not isinstance(t, Tensor) or t.shape[0] != n:
                raise ValueError(f"train_tensors: tensor {i} must be a Tensor with {n} rows")
        if n == 0:
            raise ValueError("train_tensors: the training set is empty (0 sequences), so there is no batch to train on")
    if not isinstance(batch_size, int) or batch_size <= 0:
        raise ValueError(f"batch_size: must be a positive int, got {batch_size!r}")
    if epochs is None and budget_s is None and max_steps is None:
        raise ValueError("epochs: give an epoch cap, a CPU-second budget_s or max_steps")
    if epochs is not None and (not isinstance(epochs, int) or epochs < 0):
        raise ValueError(f"epochs: must be an int >= 0 or None, got {epochs!r}")
    if budget_s is not None and not (isinstance(budget_s, (int, float)) and math.isfinite(budget_s) and budget_s > 0):
        raise ValueError(f"budget_s: must be a positive finite number or None, got {budget_s!r}")
    if not lr > 0:
        raise ValueError(f"lr: must be positive, got {lr}")
    if clip_norm is not None and not clip_norm > 0:
        raise ValueError(f"clip_norm: must be positive or None, got {clip_norm}")
    if patience is not None and (valid_fn is None or not isinstance(patience, int) or patience <= 0):
        raise ValueError(f"patience: needs valid_fn and a positive int, got {patience!r}")
    if valid_every is not None and (valid_fn is None or not isinstance(valid_every, int) or valid_every <= 0):
        raise ValueError(f"valid_every: needs valid_fn and a positive int, got {valid_every!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps <= 0):
        raise ValueError(f"max_steps: must be a positive int or None, got {max_steps!r}")
    if lr_patience is not None and (valid_fn is None or not isinstance(lr_patience, int) or lr_patience <= 0):
        raise ValueError(f"lr_patience: needs valid_fn and a positive int, got {lr_patience!r}")
    if not 0 < lr_factor < 1:
        raise ValueError(f"lr_factor: must be in (0, 1), got {lr_factor!r}")
    if not (isinstance(lr_min, (int, float)) and 0 <= lr_min <= lr):
        raise ValueError(f"lr_min: must lie in [0, lr] = [0, {lr}], got {lr_min!r}")
    if on_divergence not in ("raise", "stop"):
        raise ValueError(f"on_divergence: expected 'raise' or 'stop', got {on_divergence!r}")
    if keep_best is None:
        keep_best = valid_fn is not None
    if keep_best and valid_fn is None:
        raise ValueError("keep_best: needs valid_fn")
    dev = _resolve_device(device)
    model = params_or_model if isinstance(params_or_model, nn.Module) else None
    if model is not None and dev is not None:
        model.to(dev)
    params = [p for p in (model.parameters() if model is not None else params_or_model) if p.requires_grad]
    if not params:
        raise ValueError("params_or_model: no trainable parameters")
    if dev is not None and any(p.device != dev for p in params):
        raise ValueError(f"device: the parameters are not on {dev}; pass a model (moved for you) or move them first")

    def snapshot() -> Any:
        if model is not None:
            return copy.deepcopy(model.state_dict())
        return [p.detach().clone() for p in params]

    def restore(state: Any) -> None:
        if model is not None:
            model.load_state_dict(state)
        else:
            with torch.no_grad():
                for p, s in zip(params, state):
                    p.copy_(s)

    # fused: one kernel for all parameters (~4x less time per step than the per-tensor loop for
    # the chapters' models, which have dozens of small parameter tensors); same algorithm
    opt = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay, fused=all(q.is_floating_point() for q in params))
    gen = torch.Generator().manual_seed(int(seed))
    hist = FitHistory()
    best, best_state, since_best, n_steps, epoch, used_before = float("inf"), None, 0, 0, 0, 0.0
    ckpt_path = None if checkpoint is None else Path(checkpoint)
    if ckpt_path is not None and ckpt_path.exists():
        state = _load_checkpoint(ckpt_path, snapshot(), lr, seed)
        restore(state["params"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        best, since_best, n_steps, epoch = state["best"], state["since_best"], state["steps"], state["epoch"]
        best_state, used_before = state["best_state"], state["cpu_used"]
        hist = FitHistory(**state["history"])
        hist.resumed_from_epoch, hist.stopped = epoch, "epochs"
    n_batches = max_batches if sampler else (n + batch_size - 1) // batch_size
    if max_batches is not None:
        n_batches = min(n_batches, max_batches)
    # CPU seconds of this run and of the runs a checkpoint resumed, counted from the end of the
    # setup (argument checks, optimizer, checkpoint loading: setup_cpu_s) on
    hist.setup_cpu_s = time.process_time() - cpu_enter
    cpu0, wall0 = time.process_time() - used_before, wall_enter
    # the progress bar counts batches (an epoch cap), CPU seconds (a budget) or steps (max_steps only)
    by_epochs, by_steps = epochs is not None, epochs is None and budget_s is None
    total = (epochs * n_batches) if by_epochs else max_steps if by_steps else round(float(budget_s), 1)
    bar = tqdm(total=total, initial=min(epoch * n_batches, total) if by_epochs else min(n_steps, total) if by_steps
               else 0, desc=desc, unit="batch" if by_epochs or by_steps else "cpu-s",
               disable=not show_progress(progress), leave=True)
    since_total, since_count = 0.0, 0  # training loss since the last curve entry
    since_lr = 0                       # validations without improvement since the last lr change

    def diverge(message: str, cause: Exception | None = None) -> NoReturn:
        """A non-finite loss, gradient norm or model output: raise, or end the run (``on_divergence``)."""
        if on_divergence == "raise" or n_steps == 0:
            raise ValueError(message) from cause
        raise _Diverged(message)

    def validate(epoch_now: int) -> bool:
        """One validation; returns True when patience ran out."""
        nonlocal best, best_state, since_best, since_total, since_count, since_lr
        v = math.nan
        if valid_fn is not None:
            if model is not None:
                model.eval()
            try:
                with torch.no_grad():
                    v = float(valid_fn())
            except NonFiniteError as err:
                diverge(f"valid_fn: failed after {n_steps} steps (epoch {epoch_now}): {err}", err)
            except ValueError as err:
                raise ValueError(f"valid_fn: failed after {n_steps} steps (epoch {epoch_now}): {err}") from err
            finally:
                if model is not None:
                    model.train()
            hist.valid_loss.append(v)
            hist.valid_steps.append(n_steps)
            if v < best:
                best, hist.best_epoch, hist.best_step, since_best, since_lr = v, epoch_now, n_steps, 0, 0
                if keep_best:
                    best_state = snapshot()
            else:
                since_best += 1
                since_lr += 1
        hist.curve.append({"step": n_steps, "epoch": epoch_now, "cpu_s": time.process_time() - cpu0,
                           "wall_s": time.perf_counter() - wall0, "valid": v,
                           "train": since_total / since_count if since_count else math.nan,
                           "lr": opt.param_groups[0]["lr"]})
        if lr_patience is not None and since_lr >= lr_patience:
            for group in opt.param_groups:
                group["lr"] = max(group["lr"] * lr_factor, lr_min)
            since_lr = 0
        since_total, since_count = 0.0, 0
        return patience is not None and since_best >= patience

    # a resumed run that had already used its budget or its patience does not train further
    out_of_budget = budget_s is not None and time.process_time() - cpu0 >= budget_s
    stop = patience is not None and since_best >= patience
    if stop:
        hist.stopped = "patience"
    try:
        while (epochs is None or epoch < epochs) and not out_of_budget and not stop:
            t0 = time.perf_counter()
            if model is not None:
                model.train()
            perm = None if sampler else torch.randperm(n, generator=gen)
            ep_total, ep_count = 0.0, 0
            for b in range(n_batches):
                idx = None
                if sampler:
                    batch = train_tensors(gen)
                else:
                    idx = perm[b * batch_size:(b + 1) * batch_size]
                    batch = tuple(t[idx] for t in train_tensors)
                    if crop_len is not None:
                        batch = random_crop(batch, crop_len, gen)
                batch = _to_device(batch, dev)
                where = lambda: f"at epoch {epoch}, batch {b} (sequence indices {_batch_indices(batch, idx)})"  # noqa: E731
                try:
                    loss = loss_fn(batch, gen)
                except NonFiniteError as err:
                    diverge(f"loss_fn: failed {where()}: {err}", err)
                except ValueError as err:
                    raise ValueError(f"loss_fn: failed {where()}: {err}") from err
                if not isinstance(loss, Tensor) or loss.ndim != 0:
                    raise ValueError(f"loss_fn: must return a scalar tensor, got {getattr(loss, 'shape', loss)!r}")
                value = float(loss.detach())
                if not math.isfinite(value):
                    diverge(f"loss_fn: non-finite loss {value} {where()}")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                grads = [p.grad for p in params if p.grad is not None]
                if clip_norm is not None:
                    norm = float(nn.utils.clip_grad_norm_(params, clip_norm))
                else:
                    norm = float(nn.utils.get_total_norm(grads)) if grads else 0.0
                if not math.isfinite(norm):
                    diverge(f"loss_fn: non-finite gradient norm {where()} (the loss {value:.4g} is "
                            f"finite; the parameters are those before this step)")
                opt.step()
                n_steps += 1
                size = len(idx) if idx is not None else 1
                ep_total, ep_count = ep_total + value * size, ep_count + size
                since_total, since_count = since_total + value * size, since_count + size
                used = time.process_time() - cpu0
                if by_epochs or by_steps:
                    bar.update(1)
                else:
                    bar.update(max(0.0, min(round(used, 1), total) - bar.n))
                if (budget_s is not None and used >= budget_s) or (max_steps is not None and n_steps >= max_steps):
                    out_of_budget = True
                if valid_every is not None and n_steps % valid_every == 0:
                    stop = validate(epoch)
                    bar.set_postfix({"epoch": epoch, "valid": f"{hist.valid_loss[-1]:.4g}"}, refresh=False)
                if out_of_budget or stop:
                    break
            hist.train_loss.append(ep_total / max(ep_count, 1))
            hist.steps.append(n_steps)
            post = {"epoch": epoch, "loss": f"{hist.train_loss[-1]:.4g}"}
            if valid_every is None:
                stop = validate(epoch)
                if valid_fn is not None:
                    post["valid"] = f"{hist.valid_loss[-1]:.4g}"
            hist.epoch_time.append(time.perf_counter() - t0)
            bar.set_postfix(post)
            epoch += 1
            if stop:
                hist.stopped = "patience"
            if ckpt_path is not None:
                _save_checkpoint(ckpt_path, snapshot(), opt, gen, best, best_state, since_best, n_steps, epoch,
                                 time.process_time() - cpu0, hist, lr, seed)
        if valid_every is not None and (not hist.valid_steps or hist.valid_steps[-1] != n_steps):
            validate(max(epoch - 1, 0))          # the final state is validated too
            if ckpt_path is not None:
                _save_checkpoint(ckpt_path, snapshot(), opt, gen, best, best_state, since_best, n_steps, epoch,
                                 time.process_time() - cpu0, hist, lr, seed)
        if out_of_budget and hist.stopped == "epochs":
            hist.stopped = "budget"
    except _Diverged as diverged:     # on_divergence="stop": the run ends at the last finite step
        hist.stopped, hist.diverged = "diverged", str(diverged)
    except KeyboardInterrupt as interrupt:
        hist.stopped = "interrupted"
        if keep_best and best_state is not None:
            restore(best_state)
        if model is not None:
            model.eval()
        bar.close()
        hist.cpu_time, hist.wall_time = time.process_time() - cpu0, time.perf_counter() - wall0
        interrupt.fit_history = hist  # type: ignore[attr-defined]
        raise
    bar.close()
    if keep_best and best_state is not None:
        restore(best_state)
    if model is not None:
        model.eval()
    hist.cpu_time, hist.wall_time = time.process_time() - cpu0, time.perf_counter() - wall0
    return hist


def _save_checkpoint(path: Path, params: Any, opt: torch.optim.Optimizer, gen: torch.Generator, best: float,
                     best_state: Any, since_best: int, steps: int, epoch: int, cpu_used: float, hist: FitHistory,
                     lr: float, seed: int) -> None:
    """Write the training state (see :func:`fit`'s ``checkpoint``) atomically: temp file + rename."""
    state = {"format": _CHECKPOINT_FORMAT, "params": params, "optimizer": opt.state_dict(),
             "generator": gen.get_state(), "best": best, "best_state": best_state, "since_best": since_best,
             "steps": steps, "epoch": epoch, "cpu_used": cpu_used, "history": dataclasses.asdict(hist),
             "lr": lr, "seed": seed}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def _load_checkpoint(path: Path, current: Any, lr: float, seed: int) -> dict[str, Any]:
    """Read a checkpoint of :func:`fit` and check that it belongs to these parameters."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # a damaged or foreign file: say which
        raise ValueError(f"checkpoint: {path} cannot be read as a fit checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(state, dict) or state.get("format") != _CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint: {path} is not a pgm_wm fit checkpoint")

    def shapes(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: tuple(v.shape) for k, v in x.items() if isinstance(v, Tensor)}
        return [tuple(v.shape) for v in x]

    if shapes(state["params"]) != shapes(current):
        raise ValueError(f"checkpoint: {path} was written for other parameters (names or shapes differ); "
                         f"use another path or delete it to start afresh")
    if state["seed"] != seed:
        raise ValueError(f"checkpoint: {path} was written with seed={state['seed']}, this call has seed={seed}")

    def to_like(saved: Any) -> Any:
        if isinstance(current, dict):
            return {k: v.to(current[k].device) if isinstance(v, Tensor) else v for k, v in saved.items()}
        return [v.to(c.device) for v, c in zip(saved, current)]

    state["params"] = to_like(state["params"])
    if state["best_state"] is not None:
        state["best_state"] = to_like(state["best_state"])
    return state

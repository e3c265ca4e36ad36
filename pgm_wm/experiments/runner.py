r"""Train every model of a chapter for several seeds under one protocol, score it, write a file.

The protocol is the same for every model of an experiment (the book's rules for results):

* **one budget**: every trained model gets the same number of CPU seconds
  (:func:`pgm_wm.training.fit` with ``budget_s``), measured per process, so runs in parallel
  processes get the same compute as runs one after another;
* **one warm-up**: training crops are ``context_len + horizon`` steps long, the first
  ``context_len`` steps are always observed (as at evaluation), and with probability
  ``open_loop_prob`` everything after them is hidden (pure open-loop, as at evaluation);
* **selection on validation**: :func:`pgm_wm.training.fit` keeps the epoch with the lowest
  open-loop validation RMSE; the test split is only touched by :func:`score`;
* **reference rows**: models that need no gradient training (repeat-last, training mean, a
  linear ARX model, a physics oracle) are fitted in closed form when built and scored on the
  same windows; being deterministic, they are scored once and repeated per seed.

:func:`score` returns, per horizon and per test window, the squared error averaged over the
observation dimensions (original units) and the Gaussian NLL per dimension; those arrays are
what :mod:`pgm_wm.experiments.stats` resamples.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..evaluation import multistep_predict, sliding_windows
from ..training import fit, imputation_loss_fn, set_seed
from .results import check_output_path, provenance, save_results

if TYPE_CHECKING:  # pragma: no cover
    from ..datasets import SequenceData

__all__ = ["Protocol", "Splits", "ModelSpec", "Experiment", "LearningCurve", "improvement_over_last_doubling",
           "CONVERGENCE_TOL", "model_path", "load_trained", "train_model", "validation_rmse", "test_windows", "score", "score_oracle",
           "run_experiment"]


@dataclass(frozen=True)
class Protocol:
    """Training and evaluation settings shared by every model of one experiment.

    The training mask (:func:`pgm_wm.training.observation_mask`) keeps each step with
    ``keep_prob``, always the first ``context_len`` steps, hides whole windows of ``mask_window``
    steps with a probability drawn in ``[0, max_window_drop]`` per batch, and with
    ``open_loop_prob`` hides everything after the context.

    ``horizons`` are the steps ``k`` reported (each ``<= horizon``); ``eval_stride`` the step
    between test windows; ``valid_stride`` between validation windows. ``score_dims`` are the
    observation dimensions that are scored and used for selection on validation (all if
    ``None``), e.g. the angles only when the observations mix angles and velocities, so that a
    reported RMSE has one unit; every model still trains on all dimensions.

    ``valid_every``: the open-loop validation RMSE is computed every this many optimizer steps
    (and at the end of the budget); the parameters with the lowest one are kept. With
    ``lr_patience`` the learning rate is halved whenever that many validations in a row brought
    no improvement (:func:`pgm_wm.training.fit`), never below ``lr_min_fraction`` times ``lr``
    (:meth:`lr_min`). At the CPU
    times ``curve_checkpoints_s`` the test RMSE is recorded too, for the learning-curve figure
    only (never for a choice).
    """

    context_len: int
    horizon: int
    horizons: tuple[int, ...]
    eval_stride: int
    valid_stride: int | None = None
    batch_size: int = 32
    keep_prob: float = 0.25
    open_loop_prob: float = 0.5
    mask_window: int | None = None
    max_window_drop: float = 0.0
    lr: float = 3e-3
    patience: int | None = None
    score_dims: tuple[int, ...] | None = None
    valid_every: int = 25
    lr_patience: int | None = None
    lr_min_fraction: float = 0.0
    curve_checkpoints_s: tuple[float, ...] = (2.5, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0, 1280.0)

    def __post_init__(self) -> None:
        if self.context_len < 1 or self.horizon < 1:
            raise ValueError("context_len: context_len and horizon must be >= 1")
        if not self.horizons or any(not 1 <= h <= self.horizon for h in self.horizons):
            raise ValueError(f"horizons: every horizon must lie in [1, {self.horizon}], got {self.horizons}")
        if self.score_dims is not None and (not self.score_dims or any(d < 0 for d in self.score_dims)
                                            or len(set(self.score_dims)) != len(self.score_dims)):
            raise ValueError(f"score_dims: need distinct non-negative dimensions, got {self.score_dims}")
        if not isinstance(self.valid_every, int) or self.valid_every < 1:
            raise ValueError(f"valid_every: need a positive int, got {self.valid_every!r}")
        if not 0 <= self.lr_min_fraction <= 1:
            raise ValueError(f"lr_min_fraction: need a fraction in [0, 1], got {self.lr_min_fraction!r}")

    @property
    def lr_min(self) -> float:
        """The floor of the learning-rate schedule, ``lr_min_fraction * lr`` (``lr_min`` of :func:`~pgm_wm.training.fit`)."""
        return self.lr_min_fraction * self.lr

    def scored(self, x: Tensor) -> Tensor:
        """The scored observation dimensions (``score_dims``) of ``x: (..., do)``."""
        if self.score_dims is None:
            return x
        if max(self.score_dims) >= x.shape[-1]:
            raise ValueError(f"score_dims: {self.score_dims} out of range for {x.shape[-1]} observation dimensions")
        return x[..., list(self.score_dims)]

    @property
    def window(self) -> int:
        return self.context_len + self.horizon


@dataclass(frozen=True)
class Splits:
    """Train / validation / test data of an experiment; statistics are the training split's."""

    train: "SequenceData"
    valid: "SequenceData"
    test: "SequenceData"

    def normalized(self, split: str) -> tuple[Tensor, Tensor, Tensor]:
        """``(obs, actions, valid)`` of ``split``, normalized with the training statistics."""
        d = getattr(self, split)
        return self.train.normalize_obs(d.obs), self.train.normalize_actions(d.actions), d.valid


@dataclass(frozen=True)
class ModelSpec:
    """How to build one model of an experiment.

    ``build(splits) -> model`` with the world-model interface ``model(obs, actions, mask)``.
    With ``trained=False`` the model is complete when built (a reference row fitted in closed
    form inside ``build``, e.g. :meth:`pgm_wm.baselines.LinearARX.fit`); it is deterministic and
    scored once. ``oracle(protocol, split="test") -> (mean, target)`` instead gives predictions
    directly, in original units, for the test (or validation) windows (the physics oracle of a simulated dataset,
    :func:`pgm_wm.datasets.oracles.oracle_windows`); it has no predictive variance, so no NLL.

    ``train(model, splits, protocol, seed, budget_s, valid_fn, max_steps=None) -> FitHistory`` replaces the
    generic training (crops of ``protocol.window`` steps, :func:`pgm_wm.training.imputation_loss_fn`)
    for a model that needs its own training data, e.g. the HiP-RSSM's windows with context sets;
    it must call :func:`pgm_wm.training.fit` with ``budget_s``, ``valid_fn`` (the same open-loop
    validation windows as every other model, and the learning curve), ``valid_every`` and
    ``max_steps`` so the budget, the selection and the curve stay the same.

    ``probe(model, splits, protocol, seed) -> dict`` is measured on the trained model after
    scoring and stored with its run (e.g. how well the HiP-RSSM's task latent reads the payload).
    """

    build: Callable[[Splits], nn.Module] | None = None
    trained: bool = True
    oracle: Callable[[Protocol], tuple[Tensor, Tensor]] | None = None
    train: Callable[..., Any] | None = None
    probe: Callable[..., dict[str, Any]] | None = None

    def __post_init__(self) -> None:
        if (self.build is None) == (self.oracle is None):
            raise ValueError("build: give exactly one of build and oracle")
        if self.oracle is not None:
            object.__setattr__(self, "trained", False)


@dataclass(frozen=True)
class Experiment:
    """A chapter's comparison: data, protocol, models, and how to report errors."""

    name: str
    title: str
    load: Callable[[], Splits]
    models: Mapping[str, ModelSpec]
    protocol: Protocol
    units: str = ""
    scale: float = 1.0
    notes: Mapping[str, Any] = field(default_factory=dict)


def _windows(obs: Tensor, actions: Tensor, valid: Tensor, length: int, stride: int) -> tuple[Tensor, Tensor]:
    """Evaluation windows of ``length`` steps in which every observation is valid."""
    wo, wa, wv = (sliding_windows(x, length, stride) for x in (obs, actions, valid))
    keep = wv.all(dim=1)
    if not bool(keep.any()):
        raise ValueError(f"length: no window of {length} fully valid steps in the data")
    return wo[keep], wa[keep]


@torch.no_grad()
def _open_loop(model: nn.Module, obs: Tensor, actions: Tensor, protocol: Protocol,
               batch: int = 256) -> tuple[Tensor, Tensor]:
    means, vars_ = [], []
    for s in range(0, obs.shape[0], batch):
        m, v = multistep_predict(model, obs[s:s + batch], actions[s:s + batch], protocol.context_len,
                                 protocol.horizon)
        means.append(m)
        vars_.append(v)
    return torch.cat(means), torch.cat(vars_)


def _valid_score(model: nn.Module, splits: Splits, protocol: Protocol) -> Callable[[], float]:
    obs, act, val = splits.normalized("valid")
    wo, wa = _windows(obs, act, val, protocol.window, protocol.valid_stride or protocol.horizon)
    target = protocol.scored(wo[:, protocol.context_len:])

    def valid_fn() -> float:
        mean, _ = _open_loop(model, wo, wa, protocol)
        err = (protocol.scored(mean) - target).square().mean()
        return float(err.sqrt()) if bool(torch.isfinite(err)) else math.inf

    return valid_fn


def validation_rmse(model: nn.Module, splits: Splits, protocol: Protocol) -> float:
    """Open-loop RMSE (normalized units) of ``model`` on the validation windows."""
    return _valid_score(model, splits, protocol)()


class LearningCurve:
    """The validation function handed to :func:`pgm_wm.training.fit`, which also records the
    learning curve: every call computes the open-loop validation RMSE (normalized units); the
    first call after each CPU time of ``checkpoints`` (seconds since ``start``) computes the test
    RMSE as well (for the figure only: it is never returned, so it can never select anything)."""

    def __init__(self, valid_fn: Callable[[], float], test_fn: Callable[[], float], checkpoints: Sequence[float],
                 start: float) -> None:
        self.valid_fn, self.test_fn, self.start = valid_fn, test_fn, start
        self.pending = sorted(float(c) for c in checkpoints)
        self.calls: list[dict[str, float]] = []

    def __call__(self) -> float:
        cpu = time.process_time() - self.start
        valid = self.valid_fn()
        entry = {"cpu_s": cpu, "valid": valid}
        if self.pending and cpu >= self.pending[0]:
            while self.pending and cpu >= self.pending[0]:
                self.pending.pop(0)
            entry["test"] = self.test_fn()
        self.calls.append(entry)
        return valid


def improvement_over_last_doubling(curve: Sequence[Mapping[str, float]], budget_s: float) -> float:
    r"""The stopping rule's statistic: the relative improvement of the best validation RMSE over
    the last doubling of the budget, :math:`(v^*_{B/2} - v^*_B) / v^*_{B/2}`, with :math:`v^*_c`
    the lowest validation RMSE recorded at CPU time :math:`\le c`: ``inf`` (not converged) when
    nothing finite was recorded by :math:`B/2` but something was by :math:`B`, ``nan`` when
    nothing finite was recorded at all."""
    def best(upto: float) -> float:
        vals = [e["valid"] for e in curve if e["cpu_s"] <= upto and math.isfinite(e["valid"])]
        return min(vals) if vals else math.nan

    half, full = best(budget_s / 2), best(budget_s)
    if math.isnan(half):
        return math.nan if math.isnan(full) else math.inf
    return (half - full) / half


def final_lr_fraction(run: Mapping[str, Any]) -> float:
    """The learning rate at the end of a trained run relative to its start: the ``lr`` of the last
    entry of the run's learning curve over that of the first (the first validation comes before
    the schedule can lower the rate). Far below the protocol's ``lr_min_fraction`` only in files
    made before the schedule had a floor; a run whose rate has fallen to ``1e-6`` of its start has
    stopped moving, whatever the stopping rule says."""
    curve = run.get("curve") or []
    if not curve or "lr" not in curve[0] or "lr" not in curve[-1]:
        raise ValueError("run: needs a learning curve whose entries record 'lr'")
    return float(curve[-1]["lr"]) / float(curve[0]["lr"])


CONVERGENCE_TOL = 0.02
"""A run has converged when its best validation RMSE improved by less than this fraction over
the last doubling of its budget (:func:`improvement_over_last_doubling`)."""


def _thin(curve: Sequence[Mapping[str, float]], n: int = 64) -> list[dict[str, float]]:
    """At most about ``n`` entries of a learning curve, spaced evenly in log(step), always keeping
    the first and last entries, every entry with a test RMSE and every new best validation."""
    if len(curve) <= n:
        return [dict(e) for e in curve]
    keep, best, next_step = [], math.inf, 0.0
    last_step = max(1.0, float(curve[-1]["step"]))
    ratio = last_step ** (1.0 / n)
    for i, e in enumerate(curve):
        new_best = e["valid"] < best
        best = min(best, e["valid"])
        if i in (0, len(curve) - 1) or "test" in e or new_best or e["step"] >= next_step:
            keep.append(dict(e))
            next_step = max(e["step"], 1.0) * ratio
    return keep


def _warm_up(model: nn.Module, splits: Splits, protocol: Protocol) -> float:
    """One forward (and, where it has a graph, backward) pass on two validation windows, before the budget starts:
    compiled loops compile (or load their cache) here, not inside a model's training budget.
    Returns the CPU seconds it took; the gradients are discarded."""
    t0 = time.process_time()
    obs, act, val = splits.normalized("valid")
    wo, wa = _windows(obs, act, val, protocol.window, protocol.valid_stride or protocol.horizon)
    mask = torch.zeros(wo[:2].shape[:2], dtype=torch.bool)
    mask[:, :protocol.context_len] = True
    mean, var = model(wo[:2], wa[:2], mask)
    if mean.requires_grad:          # an evaluation-only wrapper (the HiP-RSSM window model) has no graph
        (mean.sum() + var.sum()).backward()
        model.zero_grad(set_to_none=True)
    return time.process_time() - t0


def _test_rmse(model: nn.Module, splits: Splits, protocol: Protocol) -> Callable[[], float]:
    wo, wa = test_windows(splits, protocol)
    target = protocol.scored(wo[:, protocol.context_len:])

    def test_fn() -> float:
        mean, _ = _open_loop(model, wo, wa, protocol)
        err = (protocol.scored(mean) - target).square().mean()
        return float(err.sqrt()) if bool(torch.isfinite(err)) else math.inf

    return test_fn


def train_model(exp: Experiment, name: str, seed: int, budget_s: float,
                max_steps: int | None = None) -> tuple[nn.Module, dict[str, Any]]:
    """Build model ``name`` with ``seed`` and train it for ``budget_s`` CPU seconds (reference
    rows: build only). ``max_steps`` caps the optimizer steps as well (the equal-steps check).

    Before the budget starts, one warm-up pass compiles what needs compiling. During training
    the validation RMSE is computed every ``protocol.valid_every`` steps (keep-best selects on
    it) and a :class:`LearningCurve` records it. Returns the model with the best validation
    parameters and ``info``: CPU seconds, optimizer steps, epochs, the best validation RMSE and
    its step, the learning curve (thinned; ``step``, ``epoch``, ``cpu_s``, ``valid``, ``train``
    and, at the checkpoints, ``test``), and the stopping rule's statistic and verdict
    (:data:`CONVERGENCE_TOL`)."""
    spec = exp.models[name]
    splits = exp.load()
    set_seed(seed)
    model = spec.build(splits)
    start = time.process_time()
    if not spec.trained:     # a reference row: its validation RMSE is a line in the learning-curve figure
        return model.eval(), {"cpu_s": round(time.process_time() - start, 2), "epochs": 0, "steps": 0,
                              "best_valid": validation_rmse(model.eval(), splits, exp.protocol)}
    p = exp.protocol
    warm = _warm_up(model, splits, p)
    set_seed(seed)                     # the warm-up drew no random numbers; reseed all the same
    tracker = LearningCurve(_valid_score(model, splits, p), _test_rmse(model, splits, p), p.curve_checkpoints_s,
                            time.process_time())
    if spec.train is not None:
        hist = spec.train(model, splits, p, seed, budget_s, tracker, max_steps=max_steps)
    else:
        obs, act, val = splits.normalized("train")
        loss_fn = imputation_loss_fn(model, p.keep_prob, p.context_len, "nll", p.open_loop_prob,
                                     window=p.mask_window, max_window_drop=p.max_window_drop)
        hist = fit(loss_fn, model, (obs, act, val), p.batch_size, lr=p.lr, seed=seed, valid_fn=tracker,
                   progress=False, crop_len=p.window, budget_s=budget_s, patience=p.patience, desc=name,
                   valid_every=p.valid_every, max_steps=max_steps, lr_patience=p.lr_patience,
                   lr_min=p.lr_min, on_divergence="stop")
    if len(tracker.calls) != len(hist.curve):
        raise RuntimeError("train: the learning curve and fit's history disagree (a custom trainer must pass "
                           "valid_fn to fit)")
    curve = [{"step": c["step"], "epoch": c["epoch"], "cpu_s": round(t["cpu_s"], 3), "valid": t["valid"],
              "train": c["train"], "lr": c.get("lr"), **({"test": t["test"]} if "test" in t else {})}
             for c, t in zip(hist.curve, tracker.calls)]
    stat = improvement_over_last_doubling(curve, budget_s)
    return model.eval(), {
        "cpu_s": round(time.process_time() - start, 2), "warm_up_cpu_s": round(warm, 2),
        "steps": hist.curve[-1]["step"] if hist.curve else 0, "epochs": hist.epochs,
        "best_valid": hist.best_valid_loss, "best_step": hist.best_step, "stopped": hist.stopped,
        "improvement_last_doubling": stat,
        # a run that diverged ended early: its curve flattening is no evidence of convergence
        "converged": bool(stat < CONVERGENCE_TOL) if math.isfinite(stat) and hist.stopped != "diverged" else False,
        **({"diverged": hist.diverged} if hist.stopped == "diverged" else {}),
        "curve": _thin(curve)}


def test_windows(splits: Splits, protocol: Protocol) -> tuple[Tensor, Tensor]:
    """The normalized test windows ``(obs, actions)`` every model is scored on."""
    obs, act, val = splits.normalized("test")
    return _windows(obs, act, val, protocol.window, protocol.eval_stride)


def oracle_validation_rmse(spec: ModelSpec, splits: Splits, protocol: Protocol) -> float | None:
    """An oracle row's open-loop RMSE on the validation windows, in the normalized units of
    :func:`validation_rmse` (``None`` if its ``oracle`` takes no split)."""
    assert spec.oracle is not None
    try:
        mean, target = spec.oracle(protocol, "valid")
    except TypeError:
        return None
    std = splits.train.stats["obs_std"].to(target.dtype)
    err = protocol.scored((mean.to(target.dtype) - target) / std)
    return float(err.square().mean().sqrt())


def score_oracle(spec: ModelSpec, splits: Splits, protocol: Protocol) -> np.ndarray:
    """Squared errors ``(len(horizons), n_windows)`` of an oracle row, on the same windows and
    targets as :func:`score` (checked)."""
    assert spec.oracle is not None
    mean, target = spec.oracle(protocol)
    wo, _ = test_windows(splits, protocol)
    ours = splits.train.denormalize_obs(wo[:, protocol.context_len:])
    if tuple(target.shape) != tuple(ours.shape) or not torch.allclose(target.to(ours.dtype), ours, atol=1e-4):
        raise ValueError("oracle: its targets differ from the runner's test windows")
    idx = [h - 1 for h in protocol.horizons]
    err = protocol.scored(mean.to(ours.dtype) - ours)[:, idx]
    return err.square().mean(-1).T.double().numpy()


def score(model: nn.Module, splits: Splits, protocol: Protocol) -> tuple[np.ndarray, np.ndarray]:
    """Per horizon and test window: squared error (mean over the scored dims, original units) and NLL.

    Returns two ``(len(horizons), n_windows)`` arrays. A diverged prediction (non-finite mean or
    a variance that is not positive and finite) is replaced by the training mean with unit
    variance (normalized units) before scoring, so it is penalised but stays finite."""
    p = protocol
    wo, wa = test_windows(splits, p)
    mean, var = _open_loop(model, wo, wa, p)
    ok = torch.isfinite(mean) & torch.isfinite(var) & (var > 0)
    mean = torch.where(ok, mean, torch.zeros_like(mean))
    var = torch.where(ok, var, torch.ones_like(var))
    std = splits.train.stats["obs_std"].to(mean.dtype)
    idx = [h - 1 for h in p.horizons]
    err = p.scored((mean - wo[:, p.context_len:]) * std)[:, idx]         # (W, H, scored dims), original units
    v = p.scored(var * std.square())[:, idx]
    sq = err.square().mean(-1).T                                          # (H, W)
    nll = (0.5 * (torch.log(2 * math.pi * v) + err.square() / v)).mean(-1).T
    return sq.double().numpy(), nll.double().numpy()


_FORKED_EXPERIMENT: Experiment | None = None  # set before forking workers (lambdas do not pickle)


def model_path(folder: str | os.PathLike, experiment: str, name: str, seed: int) -> Path:
    """Where :func:`run_experiment` stores a trained model's parameters: ``folder/experiment/<name>
    seed <seed>.pt`` (the model name with characters that do not belong in a file name replaced)."""
    safe = "".join(c if c.isalnum() or c in "-_.()" else "_" for c in name)
    return Path(folder) / experiment / f"{safe}__seed{seed}.pt"


def load_trained(exp: Experiment, name: str, seed: int, folder: str | os.PathLike) -> nn.Module:
    """Model ``name`` of ``exp`` with the parameters a study stored for ``seed`` (built by its
    :class:`ModelSpec` exactly as in the study, then the state dict loaded; eval mode)."""
    path = model_path(folder, exp.name, name, seed)
    if not path.is_file():
        raise ValueError(f"name: no stored parameters for {name!r}, seed {seed} at {path}")
    set_seed(seed)
    model = exp.models[name].build(exp.load())
    model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return model.eval()


def _run_one(task: tuple[str, int, float, int | None, str | None], exp: Experiment | None = None
             ) -> tuple[str, int, np.ndarray, np.ndarray | None, dict]:
    name, seed, budget_s, max_steps, save_dir = task
    exp = _FORKED_EXPERIMENT if exp is None else exp
    assert exp is not None
    torch.set_num_threads(1)
    if exp.models[name].oracle is not None:
        return name, seed, score_oracle(exp.models[name], exp.load(), exp.protocol), None, {
            "oracle": True, "best_valid": oracle_validation_rmse(exp.models[name], exp.load(), exp.protocol)}
    model, info = train_model(exp, name, seed, budget_s, max_steps=max_steps)
    sq, nll = score(model, exp.load(), exp.protocol)
    if save_dir is not None and exp.models[name].trained:
        path = model_path(save_dir, exp.name, name, seed)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(model.state_dict(), path)
    if exp.models[name].probe is not None:
        info["probe"] = exp.models[name].probe(model, exp.load(), exp.protocol, seed)
    return name, seed, sq, nll, info


def _log_line(name: str, seed: int, info: Mapping[str, Any]) -> str:
    if info.get("oracle"):
        return f"{name:>36} (oracle)"
    if "curve" not in info:
        return f"{name:>36} (fitted in closed form)"
    return (f"{name:>36} seed {seed}: {info['cpu_s']:.0f} CPU s, {info['steps']} steps, {info['epochs']} epochs, "
            f"best valid {info['best_valid']:.4g} at step {info['best_step']}, last doubling "
            f"{100 * info['improvement_last_doubling']:.1f} % ({'converged' if info['converged'] else 'NOT converged'})")


def run_experiment(exp: Experiment, seeds: Sequence[int], budget_s: float, out_path: str | None = None,
                   jobs: int = 1, models: Sequence[str] | None = None, log: Callable[[str], None] = print,
                   max_steps: int | None = None, save_models: str | os.PathLike | None = None) -> dict[str, Any]:
    """Train and score every model for every seed; return (and optionally save) the results.

    ``jobs > 1`` runs (model, seed) pairs in that many processes; each gets ``budget_s`` CPU
    seconds and one thread either way. ``max_steps`` also caps every model's optimizer steps
    (the equal-steps comparison: give a budget large enough that no model runs out of it).
    ``save_models``: a folder where every trained model's parameters are stored
    (:func:`model_path`; read them back with :func:`load_trained`)."""
    if len(seeds) < 1:
        raise ValueError("seeds: need at least one seed")
    if len(set(seeds)) != len(seeds) or any(not isinstance(s, int) or s < 0 for s in seeds):
        raise ValueError(f"seeds: need distinct non-negative ints, got {list(seeds)}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 1):
        raise ValueError(f"max_steps: must be a positive int or None, got {max_steps!r}")
    if not (isinstance(budget_s, (int, float)) and math.isfinite(budget_s) and budget_s > 0):
        raise ValueError(f"budget_s: must be a positive finite number of CPU seconds, got {budget_s!r}")
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
        raise ValueError(f"jobs: must be an int >= 1, got {jobs!r}")
    names = list(exp.models) if models is None else list(models)
    if not names:
        raise ValueError("models: need at least one model")
    for n in names:
        if n not in exp.models:
            raise ValueError(f"models: unknown model {n!r} (known: {', '.join(exp.models)})")
    if out_path is not None:  # before any training: a path that cannot be written fails now
        check_output_path(out_path, force=True)
    save_dir = None if save_models is None else str(save_models)
    tasks = [(n, s, budget_s, max_steps, save_dir) for n in names
             for s in (seeds if exp.models[n].trained else seeds[:1])]
    t0 = time.perf_counter()
    # commit, date and machine are recorded when the run starts; the wall time when it ends
    started = provenance(budget_cpu_s=budget_s, seeds=list(seeds), jobs=jobs, max_steps=max_steps,
                         convergence_tol=CONVERGENCE_TOL)
    if jobs > 1:
        import multiprocessing as mp

        global _FORKED_EXPERIMENT
        _FORKED_EXPERIMENT = exp
        with mp.get_context("fork").Pool(jobs) as pool:
            outs = []
            for out in pool.imap_unordered(_run_one, tasks):
                log(_log_line(out[0], out[1], out[4]))
                outs.append(out)
    else:
        outs = []
        for task in tasks:
            out = _run_one(task, exp)
            log(_log_line(out[0], out[1], out[4]))
            outs.append(out)
    per: dict[str, dict[int, tuple[np.ndarray, np.ndarray | None, dict]]] = {n: {} for n in names}
    for name, seed, sq, nll, info in outs:
        per[name][seed] = (sq, nll, info)
    model_entries: dict[str, Any] = {}
    for n in names:
        runs = [per[n][s] for s in (seeds if exp.models[n].trained else seeds[:1])]
        if not exp.models[n].trained:     # deterministic: the same numbers for every seed
            runs = runs * len(seeds)
        model_entries[n] = {
            "sq_err": np.stack([r[0] for r in runs]),
            "nll": None if runs[0][1] is None else np.stack([r[1] for r in runs]),
            "trained": exp.models[n].trained,
            "runs": [r[2] for r in runs],
        }
    results = {
        "experiment": exp.name, "title": exp.title, "units": exp.units, "scale": exp.scale,
        "horizons": list(exp.protocol.horizons),
        "protocol": {k: getattr(exp.protocol, k) for k in exp.protocol.__dataclass_fields__},
        "notes": dict(exp.notes),
        "provenance": {**started, "wall_s": round(time.perf_counter() - t0, 1)},
        "models": model_entries,
    }
    if out_path is not None:
        save_results(out_path, results)
    return results

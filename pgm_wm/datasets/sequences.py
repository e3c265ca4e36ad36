"""``SequenceData``: a set of equally long sequences, plus the public API to build, split and normalise one.

Shapes (``n`` sequences of ``T`` steps):

- ``obs``: ``(n, T, d_obs)``; entries at missing steps are 0 and must be ignored;
- ``actions``: ``(n, T, d_act)`` or ``None``; ``actions[:, t]`` is applied between
  ``obs[:, t]`` and ``obs[:, t + 1]`` (so ``actions[:, -1]`` has no observed effect);
- ``valid``: bool ``(n, T)``, ``False`` where the observation is missing (or the
  step is padding after the end of a shorter sequence);
- ``targets``: ``(n, T, d_tgt)`` or ``None``;
- ``hidden``: dict of tensors with leading dims ``(n, T)``, never to be fed to a model;
- ``stats``: normalisation statistics of the *training* split (:func:`compute_stats`).

Users build one from their own arrays with :meth:`SequenceData.from_arrays`, split it
by sequence with :func:`split_sequences` (seeded) and get training statistics with
:func:`compute_stats`; :func:`pgm_wm.datasets.load` returns the same type for the
bundled datasets.
"""

from __future__ import annotations

import collections
import keyword
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from .._checks import check_last_dims

__all__ = ["SequenceData", "SequenceSplits", "compute_stats", "stats_numpy", "split_sequences", "STD_FLOOR"]

#: Standard deviations below this are raised to it, so normalising never divides by zero.
STD_FLOOR = 1e-6

_STAT_KEYS = {"obs": ("obs_mean", "obs_std"), "act": ("act_mean", "act_std"), "diff": ("diff_mean", "diff_std")}


# --------------------------------------------------------------------------- input checks


def _as_array(argname: str, x: Any, ndim: int, floating: bool = True) -> np.ndarray:
    """``x`` (numpy or torch) as a numpy array with ``ndim`` dims; floating unless ``floating=False``."""
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    if not isinstance(x, np.ndarray):
        raise ValueError(f"{argname}: expected a numpy array or torch tensor, got {type(x).__name__}")
    if x.ndim != ndim:
        raise ValueError(f"{argname}: expected {ndim} dimensions, got shape {tuple(x.shape)}")
    if floating and not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"{argname}: expected a floating dtype, got {x.dtype}")
    return x


def _check_valid(valid: Any, n: int, T: int) -> np.ndarray:
    if valid is None:
        return np.ones((n, T), dtype=bool)
    v = _as_array("valid", valid, 2, floating=False)
    if v.shape != (n, T):
        raise ValueError(f"valid: expected shape {(n, T)} (the first two dims of obs), got {tuple(v.shape)}")
    if v.dtype != bool:
        raise ValueError(f"valid: expected a boolean mask, got dtype {v.dtype}")
    return v


def _check_obs_actions(obs: Any, actions: Any, valid: Any) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    o = _as_array("obs", obs, 3)
    n, T, d = o.shape
    if n == 0 or T == 0 or d == 0:
        raise ValueError(f"obs: expected shape (n, T, d_obs) with n, T, d_obs >= 1, got {tuple(o.shape)}")
    v = _check_valid(valid, n, T)
    if not np.isfinite(o[v]).all():
        raise ValueError("obs: contains NaN or infinite values at valid steps (mark them invalid in `valid`)")
    a = None
    if actions is not None:
        a = _as_array("actions", actions, 3)
        if a.shape[:2] != (n, T) or a.shape[2] == 0:
            raise ValueError(f"actions: expected shape ({n}, {T}, d_act) like obs, got {tuple(a.shape)}")
        if not np.isfinite(a).all():
            raise ValueError("actions: contains NaN or infinite values")
    return o, a, v


def _masked_mean_std(x: np.ndarray, mask: np.ndarray, argname: str, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (population) std over the rows of ``x (N, d)`` where ``mask (N,)``; float64, two passes."""
    w = np.asarray(mask, dtype=np.float64)
    count = w.sum()
    if count == 0:
        raise ValueError(f"{argname}: no valid entries to compute statistics from")
    total = np.zeros(x.shape[1])
    for start in range(0, x.shape[0], chunk):
        rows = np.where(w[start:start + chunk, None] > 0, x[start:start + chunk], 0.0)
        total += w[start:start + chunk] @ rows.astype(np.float64)
    mean = total / count
    sq = np.zeros(x.shape[1])
    for start in range(0, x.shape[0], chunk):
        dev = np.where(w[start:start + chunk, None] > 0, x[start:start + chunk], mean).astype(np.float64)
        dev -= mean
        dev *= dev
        sq += w[start:start + chunk] @ dev
    return mean, np.sqrt(sq / count)


def stats_numpy(obs: np.ndarray, actions: np.ndarray | None, valid: np.ndarray,
                 with_diff: bool) -> dict[str, np.ndarray]:
    """:func:`compute_stats` on checked numpy arrays; float64 results."""
    n, T, d = obs.shape
    stats = {}
    flat_valid = valid.reshape(-1)
    stats["obs_mean"], std = _masked_mean_std(obs.reshape(n * T, d), flat_valid, "valid")
    stats["obs_std"] = np.maximum(std, STD_FLOOR)
    if actions is not None:
        stats["act_mean"], std = _masked_mean_std(actions.reshape(n * T, -1), flat_valid, "valid")
        stats["act_std"] = np.maximum(std, STD_FLOOR)
    if with_diff:
        if T < 2:
            raise ValueError(f"obs: difference statistics need T >= 2 steps, got T = {T}")
        pair = (valid[:, 1:] & valid[:, :-1]).reshape(-1)
        diff = (obs[:, 1:].astype(np.float64) - obs[:, :-1]).reshape(n * (T - 1), d)
        stats["diff_mean"], std = _masked_mean_std(diff, pair, "valid (pairs of consecutive valid steps)")
        stats["diff_std"] = np.maximum(std, STD_FLOOR)
    return stats


def compute_stats(obs: Tensor | np.ndarray, actions: Tensor | np.ndarray | None = None,
                  valid: Tensor | np.ndarray | None = None, *, with_diff: bool = True,
                  dtype: torch.dtype = torch.float64) -> dict[str, Tensor]:
    """Normalisation statistics of a (training) set of sequences, ignoring invalid steps.

    Args:
        obs: ``(n, T, d_obs)`` floating; entries where ``valid`` is False are ignored
            (they may be NaN).
        actions: ``(n, T, d_act)`` floating and finite, or ``None``.
        valid: bool ``(n, T)`` or ``None`` (all valid).
        with_diff: also the statistics of ``o_{t+1} - o_t`` over pairs of valid steps.
        dtype: floating dtype of the returned tensors.

    Returns:
        ``obs_mean, obs_std (d_obs,)`` over valid steps; ``act_mean, act_std (d_act,)``
        over the same steps (padding after a short sequence's end is left out);
        ``diff_mean, diff_std (d_obs,)`` if ``with_diff``. Population standard
        deviations (divide by the count), computed in float64 and floored at
        :data:`STD_FLOOR`.

    Raises:
        ValueError: naming ``obs``, ``actions`` or ``valid`` for a wrong shape or dtype,
            NaN/inf at a valid step (or anywhere in the actions), or no valid step.
    """
    o, a, v = _check_obs_actions(obs, actions, valid)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating torch dtype, got {dtype!r}")
    return {k: torch.tensor(val, dtype=dtype) for k, val in stats_numpy(o, a, v, with_diff).items()}


def _check_stats(stats: Mapping[str, Any], d_obs: int, d_act: int) -> dict[str, np.ndarray]:
    if not isinstance(stats, Mapping):
        raise ValueError(f"stats: expected a dict of statistics, got {type(stats).__name__}")
    sizes = {"obs": d_obs, "act": d_act, "diff": d_obs}
    out = {}
    for key in stats:
        if not any(key in pair for pair in _STAT_KEYS.values()):
            raise ValueError(f"stats: unknown key {key!r}; expected obs_/act_/diff_ + mean/std")
    for group, (mean_key, std_key) in _STAT_KEYS.items():
        if (mean_key in stats) != (std_key in stats):
            raise ValueError(f"stats: {mean_key!r} and {std_key!r} must be given together")
        if mean_key not in stats:
            continue
        for key in (mean_key, std_key):
            val = _as_array(f"stats[{key!r}]", stats[key], 1)
            if val.shape != (sizes[group],):
                raise ValueError(f"stats[{key!r}]: expected shape ({sizes[group]},), got {tuple(val.shape)}")
            if not np.isfinite(val).all():
                raise ValueError(f"stats[{key!r}]: contains NaN or infinite values")
            out[key] = val.astype(np.float64)
        if not (out[std_key] > 0).all():
            raise ValueError(f"stats[{std_key!r}]: standard deviations must be strictly positive")
    if "obs_mean" not in out:
        raise ValueError("stats: needs at least 'obs_mean' and 'obs_std'")
    return out


# --------------------------------------------------------------------------- the container


@dataclass(repr=False)
class SequenceData:
    """One split of one dataset (``n`` sequences of ``T`` steps).

    Fields:
        name, split: what was loaded.
        obs: ``(n, T, d_obs)``; 0 at missing steps (see ``valid``).
        actions: ``(n, T, d_act)`` or ``None``; ``actions[:, t]`` acts between
            ``obs[:, t]`` and ``obs[:, t + 1]``.
        valid: bool ``(n, T)``; ``False`` = observation missing.
        targets: ``(n, T, d_tgt)`` or ``None`` (pendulum ``(sin, cos)``; tracking clean positions).
        hidden: evaluation-only tensors, leading dims ``(n, T)`` (e.g. ``payload (n, T)`` in kg).
        meta: ``dt``, ``units``, ``obs_names``, ``action_names``, ``generator`` (name,
            version, seeds, params), ``seed``, ``description``, ... (JSON-like dict).
        stats: training-split statistics ``obs_mean/obs_std (d_obs,)``,
            ``act_mean/act_std (d_act,)``, ``diff_mean/diff_std (d_obs,)`` (no diff
            statistics for the pendulum's images); see :func:`compute_stats`.

    Build one from your own arrays with :meth:`from_arrays`; split it with
    :func:`split_sequences`. The normalisation helpers take tensors whose last
    dimension is the feature dimension (any leading dims) and use ``stats``:
    ``x_norm = (x - mean) / std``.
    """

    name: str
    split: str
    obs: Tensor
    actions: Tensor | None
    valid: Tensor
    targets: Tensor | None
    hidden: dict[str, Tensor]
    meta: dict[str, Any]
    stats: dict[str, Tensor] = field(default_factory=dict)

    @classmethod
    def from_arrays(cls, obs: Tensor | np.ndarray, actions: Tensor | np.ndarray | None = None,
                    valid: Tensor | np.ndarray | None = None,
                    hidden: Mapping[str, Tensor | np.ndarray] | None = None,
                    stats: Mapping[str, Tensor | np.ndarray] | None = None, *,
                    targets: Tensor | np.ndarray | None = None, name: str = "custom",
                    split: str = "train", meta: Mapping[str, Any] | None = None,
                    dtype: torch.dtype = torch.float32) -> "SequenceData":
        """Wrap your own sequences (numpy arrays or tensors) in a checked :class:`SequenceData`.

        Args:
            obs: ``(n, T, d_obs)`` floating; may hold NaN where ``valid`` is False
                (those entries are set to 0, as in the bundled data).
            actions: ``(n, T, d_act)`` floating and finite, or ``None``.
            valid: bool ``(n, T)`` or ``None`` (every step observed). Mark padding
                after the end of a shorter sequence as invalid.
            hidden: evaluation-only arrays, each with leading dims ``(n, T)``.
            stats: normalisation statistics (keys as :func:`compute_stats`); ``None``
                computes them from these arrays, i.e. treats them as the training set.
            targets: ``(n, T, d_tgt)`` floating, or ``None``.
            name, split, meta: labels stored on the result (``meta`` is copied).
            dtype: floating dtype of the returned tensors (``valid`` is bool).

        Raises:
            ValueError: the message starts with the offending argument's name (wrong
                number of dims, mismatched ``(n, T)``, non-floating dtype, non-bool
                ``valid``, NaN/inf at a valid step, bad statistics).
        """
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(f"dtype: expected a floating torch dtype, got {dtype!r}")
        o, a, v = _check_obs_actions(obs, actions, valid)
        n, T, d = o.shape
        o = np.where(v[..., None], o, 0.0).astype(o.dtype)
        tg = None
        if targets is not None:
            tg = _as_array("targets", targets, 3)
            if tg.shape[:2] != (n, T):
                raise ValueError(f"targets: expected leading dims ({n}, {T}), got {tuple(tg.shape)}")
        hid = {}
        if hidden is not None:
            if not isinstance(hidden, Mapping):
                raise ValueError(f"hidden: expected a dict of arrays, got {type(hidden).__name__}")
            for key, val in hidden.items():
                arr = val.detach().cpu().numpy() if isinstance(val, Tensor) else np.asarray(val)
                if arr.shape[:2] != (n, T):
                    raise ValueError(f"hidden[{key!r}]: expected leading dims ({n}, {T}), got {tuple(arr.shape)}")
                hid[key] = arr
        d_act = 0 if a is None else a.shape[2]
        stats_np = stats_numpy(o, a, v, with_diff=T >= 2) if stats is None else _check_stats(stats, d, d_act)
        if a is not None and "act_mean" not in stats_np:
            raise ValueError("stats: actions were given but 'act_mean'/'act_std' are missing")

        def tens(x: np.ndarray | None) -> Tensor | None:
            if x is None:
                return None
            t = torch.from_numpy(np.ascontiguousarray(x))
            return t.bool() if t.dtype == torch.bool else t.to(dtype)

        return cls(name=name, split=split, obs=tens(o), actions=tens(a), valid=torch.from_numpy(v.copy()),
                   targets=tens(tg), hidden={k: tens(x) for k, x in hid.items()},
                   meta=dict(meta or {}),
                   stats={k: torch.tensor(x, dtype=dtype) for k, x in stats_np.items()})

    def subset(self, index: Sequence[int] | np.ndarray | Tensor, split: str | None = None) -> "SequenceData":
        """The sequences ``index`` (in that order), with the same statistics and metadata."""
        idx = torch.as_tensor(np.asarray(index, dtype=np.int64).reshape(-1))
        if len(idx) == 0:
            raise ValueError("index: need at least one sequence")
        if bool((idx < 0).any()) or bool((idx >= self.n_sequences).any()):
            raise ValueError(f"index: entries must lie in [0, {self.n_sequences}), got {idx.tolist()[:10]}")

        def take(x: Tensor | None) -> Tensor | None:
            return None if x is None else x[idx]

        return replace(self, split=self.split if split is None else split, obs=self.obs[idx],
                       actions=take(self.actions), valid=self.valid[idx], targets=take(self.targets),
                       hidden={k: v[idx] for k, v in self.hidden.items()}, meta=dict(self.meta),
                       stats=dict(self.stats))

    def with_stats(self, stats: Mapping[str, Tensor | np.ndarray]) -> "SequenceData":
        """A copy that normalises with ``stats`` (checked like :meth:`from_arrays`' argument)."""
        dtype = self.obs.dtype
        checked = _check_stats(stats, self.obs_dim, self.action_dim)
        return replace(self, stats={k: torch.tensor(v, dtype=dtype) for k, v in checked.items()})

    @property
    def n_sequences(self) -> int:
        return int(self.obs.shape[0])

    @property
    def seq_len(self) -> int:
        return int(self.obs.shape[1])

    @property
    def obs_dim(self) -> int:
        return int(self.obs.shape[2])

    @property
    def action_dim(self) -> int:
        return 0 if self.actions is None else int(self.actions.shape[2])

    def _stat(self, key: str, like: Tensor) -> Tensor:
        if key not in self.stats:
            raise ValueError(f"{key}: no such statistic for dataset {self.name!r}")
        return self.stats[key].to(dtype=like.dtype, device=like.device)

    def _check(self, argname: str, x: Tensor, dim: int) -> Tensor:
        return check_last_dims(argname, x, (dim,))

    def normalize_obs(self, obs: Tensor) -> Tensor:
        """``(..., d_obs) -> (..., d_obs)``: ``(obs - obs_mean) / obs_std``."""
        self._check("obs", obs, self.obs_dim)
        return (obs - self._stat("obs_mean", obs)) / self._stat("obs_std", obs)

    def denormalize_obs(self, obs_norm: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_obs`, ``(..., d_obs)``."""
        self._check("obs_norm", obs_norm, self.obs_dim)
        return obs_norm * self._stat("obs_std", obs_norm) + self._stat("obs_mean", obs_norm)

    def denormalize_obs_var(self, var_norm: Tensor) -> Tensor:
        """A predicted variance of normalized observations in original units, ``(..., d_obs)``:
        ``var_norm * obs_std**2`` (the variance of :meth:`denormalize_obs` of the prediction)."""
        self._check("var_norm", var_norm, self.obs_dim)
        return var_norm * self._stat("obs_std", var_norm).square()

    def normalize_actions(self, actions: Tensor) -> Tensor:
        """``(..., d_act) -> (..., d_act)``: ``(actions - act_mean) / act_std``."""
        self._check("actions", actions, self.action_dim)
        return (actions - self._stat("act_mean", actions)) / self._stat("act_std", actions)

    def denormalize_actions(self, actions_norm: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_actions`, ``(..., d_act)``."""
        self._check("actions_norm", actions_norm, self.action_dim)
        return actions_norm * self._stat("act_std", actions_norm) + self._stat("act_mean", actions_norm)

    def normalize_diff(self, diff: Tensor) -> Tensor:
        """``(..., d_obs) -> (..., d_obs)`` for ``diff = o_{t+1} - o_t``: ``(diff - diff_mean) / diff_std``."""
        self._check("diff", diff, self.obs_dim)
        return (diff - self._stat("diff_mean", diff)) / self._stat("diff_std", diff)

    def denormalize_diff(self, diff_norm: Tensor) -> Tensor:
        """Inverse of :meth:`normalize_diff`, ``(..., d_obs)``."""
        self._check("diff_norm", diff_norm, self.obs_dim)
        return diff_norm * self._stat("diff_std", diff_norm) + self._stat("diff_mean", diff_norm)

    def denormalize_diff_var(self, var_norm: Tensor) -> Tensor:
        """A predicted variance of normalized differences in original units, ``(..., d_obs)``:
        ``var_norm * diff_std**2``."""
        self._check("var_norm", var_norm, self.obs_dim)
        return var_norm * self._stat("diff_std", var_norm).square()

    def __repr__(self) -> str:
        def shape(t: Tensor | None) -> str:
            return "None" if t is None else str(tuple(t.shape))

        hidden = ", ".join(f"{k}: {tuple(v.shape)}" for k, v in self.hidden.items())
        return (
            f"SequenceData(name={self.name!r}, split={self.split!r}, obs={shape(self.obs)}, "
            f"actions={shape(self.actions)}, valid={shape(self.valid)}, targets={shape(self.targets)}, "
            f"hidden={{{hidden}}}, dt={self.meta.get('dt')}, stats={sorted(self.stats)})"
        )


# --------------------------------------------------------------------------- splitting


def _check_fractions(fractions: Sequence[float]) -> np.ndarray:
    try:
        fr = np.asarray(fractions, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"fractions: expected a sequence of numbers, got {fractions!r}") from err
    if fr.ndim != 1 or len(fr) < 1 or not np.isfinite(fr).all() or (fr <= 0).any():
        raise ValueError(f"fractions: expected positive finite numbers, got {list(fractions)}")
    if abs(fr.sum() - 1.0) > 1e-9:
        raise ValueError(f"fractions: must sum to 1, got {fr.sum():.6g}")
    return fr


def split_indices(n: int, fractions: Sequence[float], seed: int) -> list[np.ndarray]:
    """Disjoint, covering index sets of sizes ``≈ fractions * n`` from a seeded permutation of ``range(n)``.

    Sizes: ``floor(f_i n)`` each, the remainder given one by one to the first parts;
    every part gets at least one sequence. Each part is sorted.
    """
    fr = _check_fractions(fractions)
    if n < len(fr):
        raise ValueError(f"data: {n} sequences cannot fill {len(fr)} non-empty parts")
    sizes = np.maximum(np.floor(fr * n).astype(int), 1)
    for i in range(n - sizes.sum()):
        sizes[i % len(sizes)] += 1
    while sizes.sum() > n:  # only when the floor of 1 pushed the total over n
        sizes[int(np.argmax(sizes))] -= 1
    perm = np.random.default_rng(seed).permutation(n)
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    return [np.sort(perm[bounds[i]:bounds[i + 1]]) for i in range(len(sizes))]


class _ByName:
    """Dict-style access on a named tuple of splits: ``parts["train"]``, ``keys()``, ``values()``,
    ``items()`` (what :func:`split_sequences` returned before it returned a named tuple)."""

    __slots__ = ()

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, str):
            if key not in self._fields:  # type: ignore[attr-defined]
                raise KeyError(key)
            return getattr(self, key)
        return tuple.__getitem__(self, key)  # type: ignore[arg-type]

    def keys(self) -> tuple[str, ...]:
        return tuple(self._fields)  # type: ignore[attr-defined]

    def values(self) -> tuple[SequenceData, ...]:
        return tuple(self)  # type: ignore[arg-type]

    def items(self) -> tuple[tuple[str, SequenceData], ...]:
        return tuple(zip(self._fields, self))  # type: ignore[attr-defined, call-overload]


class _TrainValidTest(NamedTuple):
    train: SequenceData
    valid: SequenceData
    test: SequenceData


class SequenceSplits(_ByName, _TrainValidTest):
    """``(train, valid, test)`` from :func:`split_sequences`: unpack it
    (``train, valid, test = split_sequences(data)``), use the fields (``parts.valid``) or the
    names (``parts["valid"]``)."""

    __slots__ = ()


def _splits_type(names: Sequence[str]) -> type:
    if tuple(names) == SequenceSplits._fields:
        return SequenceSplits
    base = collections.namedtuple("SequenceParts", names)  # type: ignore[misc]
    return type("SequenceParts", (_ByName, base), {"__slots__": (), "__module__": __name__})


def split_sequences(data: SequenceData, fractions: Sequence[float] = (0.7, 0.15, 0.15), seed: int = 0,
                    names: Sequence[str] = ("train", "valid", "test")) -> SequenceSplits:
    """Split ``data`` by sequence into seeded, disjoint parts that together cover it.

    Returns a named tuple in the order of ``names``: with the default names a
    :class:`SequenceSplits` ``(train, valid, test)``, so ``train, valid, test =
    split_sequences(data)`` unpacks the parts; ``parts["valid"]`` and ``parts.items()`` work too.

    The first part is the training split: every part gets the statistics of the
    first part (:func:`compute_stats` over its valid steps), so nothing of the
    held-out sequences leaks into the normalisation. ``meta["split_info"]`` of
    each part records ``seed``, ``fractions`` and the original ``indices``.

    Raises:
        ValueError: ``data`` is not a :class:`SequenceData`, ``fractions`` are not
            positive and summing to 1, ``names`` do not match ``fractions``, repeat or are not
            Python identifiers, or there are fewer sequences than parts.
    """
    if not isinstance(data, SequenceData):
        raise ValueError(f"data: expected a SequenceData, got {type(data).__name__}")
    _check_fractions(fractions)
    names = list(names)
    if len(names) != len(fractions) or len(set(names)) != len(names):
        raise ValueError(f"names: expected {len(fractions)} distinct names (one per fraction), got {names}")
    if not all(isinstance(n, str) and n.isidentifier() and not n.startswith("_") and not keyword.iskeyword(n)
               for n in names):
        raise ValueError(f"names: each name must be a Python identifier not starting with '_', got {names}")
    if not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed: expected an int, got {type(seed).__name__}")
    parts = split_indices(data.n_sequences, fractions, int(seed))
    train = parts[0]
    actions = None if data.actions is None else data.actions[train].double().numpy()
    with_diff = "diff_mean" in data.stats or not data.stats
    stats = stats_numpy(data.obs[train].double().numpy(), actions, data.valid[train].numpy(),
                         with_diff=with_diff and data.seq_len >= 2)
    stats_t = {k: torch.tensor(v, dtype=data.obs.dtype) for k, v in stats.items()}
    out = []
    for name, idx in zip(names, parts):
        part = replace(data.subset(idx, split=name), stats=stats_t)
        part.meta["split_info"] = {"n": int(len(idx)), "T": data.seq_len, "seed": int(seed),
                                   "fractions": [float(f) for f in fractions], "indices": idx.tolist()}
        out.append(part)
    return _splits_type(names)(*out)

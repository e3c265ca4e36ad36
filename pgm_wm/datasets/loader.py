"""``load(name, split)``: the bundled datasets as torch tensors plus training-split statistics.

Every dataset is a set of equally long sequences. Shapes (``n`` sequences of
``T`` steps):

- ``obs``: ``(n, T, d_obs)``; entries at missing steps are 0 and must be ignored;
- ``actions``: ``(n, T, d_act)`` or ``None``; ``actions[:, t]`` is applied between
  ``obs[:, t]`` and ``obs[:, t + 1]`` (so ``actions[:, -1]`` has no observed effect);
- ``valid``: bool ``(n, T)``, ``False`` where the observation is missing;
- ``targets``: ``(n, T, d_tgt)`` or ``None`` (pendulum: ``(sin, cos)`` of the true
  angle; tracking: the noise-free positions);
- ``hidden``: dict of tensors never to be fed to a model (e.g. ``payload (n, T)`` in kg,
  true velocities, noise factors), for evaluation and plots;
- ``stats``: normalisation statistics of the *training* split, whatever split was
  loaded: ``obs_mean, obs_std (d_obs,)``, ``act_mean, act_std (d_act,)``,
  ``diff_mean, diff_std (d_obs,)`` for ``o_{t+1} - o_t`` (not for images).
  Missing observations (and differences touching them) are excluded.
"""

from __future__ import annotations

import json
import os
import tokenize
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .._checks import check_last_dims
from . import nile as _nile
from ._io import META_KEY, SEP, DataFileError, verify_file
from .pendulum import render_pendulum

__all__ = ["DATASET_NAMES", "SPLITS", "ACTION_OPTIONS", "SequenceData", "load", "data_dir"]

DATASET_NAMES: tuple[str, ...] = (
    "nile", "tracking", "pendulum", "hysteresis_arm", "payload_arm", "drift_arm",
)

SPLITS: dict[str, tuple[str, ...]] = {
    "nile": ("train",),
    "tracking": ("train", "test"),
    "pendulum": ("train", "valid", "test"),
    "hysteresis_arm": ("train", "valid", "test"),
    "payload_arm": ("train", "valid", "test", "interp", "extrap", "switching"),
    "drift_arm": ("train", "valid", "test"),
}

ACTION_OPTIONS: dict[str, tuple[str, ...]] = {
    "payload_arm": ("pd_target", "torque"),
    "drift_arm": ("pd_target", "torque"),
}

FILENAMES: dict[str, str] = {name: f"{name}.npz" for name in DATASET_NAMES}
FILENAMES["nile"] = "nile.csv"


def data_dir() -> Path:
    """Folder holding the bundled files: ``$PGM_WM_DATA`` if set, else ``<repo>/data``."""
    env = os.environ.get("PGM_WM_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent.parent / "data"


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
            statistics for the pendulum's images).

    The normalisation helpers take tensors whose last dimension is the feature
    dimension (any leading dims) and use ``stats``: ``x_norm = (x - mean) / std``.
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

    def __repr__(self) -> str:
        def shape(t: Tensor | None) -> str:
            return "None" if t is None else str(tuple(t.shape))

        hidden = ", ".join(f"{k}: {tuple(v.shape)}" for k, v in self.hidden.items())
        return (
            f"SequenceData(name={self.name!r}, split={self.split!r}, obs={shape(self.obs)}, "
            f"actions={shape(self.actions)}, valid={shape(self.valid)}, targets={shape(self.targets)}, "
            f"hidden={{{hidden}}}, dt={self.meta.get('dt')}, stats={sorted(self.stats)})"
        )


# --------------------------------------------------------------------------- reading


def _check_name_split(name: str, split: str, action: str | None) -> None:
    if name not in DATASET_NAMES:
        raise ValueError(f"name: unknown dataset {name!r}; valid names: {', '.join(DATASET_NAMES)}")
    if split not in SPLITS[name]:
        raise ValueError(
            f"split: unknown split {split!r} for dataset {name!r}; valid splits: {', '.join(SPLITS[name])}"
        )
    if name in ACTION_OPTIONS:
        if action is not None and action not in ACTION_OPTIONS[name]:
            raise ValueError(
                f"action: unknown action {action!r} for dataset {name!r}; "
                f"valid actions: {', '.join(ACTION_OPTIONS[name])}"
            )
    elif action is not None:
        raise ValueError(f"action: dataset {name!r} has a single action type; leave action=None")


def restore_command(name: str) -> str:
    """The shell command that rewrites the bundled file of dataset ``name``."""
    return f"python -m pgm_wm.datasets build --only {name}"


def _path(name: str) -> Path:
    """Path of the file of ``name``, verified against ``SHA256SUMS`` (cached by size and mtime)."""
    return verify_file(data_dir() / FILENAMES[name], restore_command(name))


# Everything numpy, zipfile, zlib and json raise on a damaged file.
_READ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error,
                tokenize.TokenError, SyntaxError, UnicodeDecodeError)


def _unreadable(path: Path, name: str, err: Exception) -> DataFileError:
    return DataFileError(f"{path}: cannot be read ({type(err).__name__}: {err}); "
                         f"restore it with `{restore_command(name)}`")


def _read_split_npz(path: Path, split: str, name: str) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays of one split (keys without the ``<split>__`` prefix) and the file's metadata."""
    prefix = split + SEP
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data[META_KEY][()]))
            arrays = {key[len(prefix):]: data[key] for key in data.files if key.startswith(prefix)}
    except _READ_ERRORS as err:
        raise _unreadable(path, name, err) from err
    return arrays, meta


def _assemble_numpy(name: str, split: str, action: str | None) -> tuple[dict[str, Any], dict]:
    """Numpy pieces of a split: obs, actions, valid, targets, hidden; plus metadata."""
    if name == "nile":
        path = _path(name)
        try:
            years, volume = _nile.read_nile_csv(path)
        except _READ_ERRORS as err:
            raise _unreadable(path, name, err) from err
        meta = {
            "dt": 1.0,
            "units": {"obs": "10^8 m^3 per year"},
            "obs_names": ["volume"],
            "action_names": [],
            "target_names": [],
            "years": years.tolist(),
            "generator": {"name": "real data (no generator)", "version": "n/a", "seed": None,
                          "params": {}},
            "source": "Cobb (1978), Biometrika 65(2); Durbin & Koopman; public domain",
            "description": "Annual flow volume of the Nile at Aswan, 1871-1970.",
            "splits": {"train": {"n": 1, "T": int(len(volume)), "seed": None}},
            "split_info": {"n": 1, "T": int(len(volume)), "seed": None},
            "seed": None,
        }
        obs = volume[None, :, None]
        pieces = {"obs": obs, "actions": None, "valid": np.ones(obs.shape[:2], dtype=bool),
                  "targets": None, "hidden": {}}
        return pieces, meta

    arrays, meta = _read_split_npz(_path(name), split, name)
    hidden = {key[len("hidden" + SEP):]: val for key, val in arrays.items() if key.startswith("hidden" + SEP)}
    meta = dict(meta)
    meta["split_info"] = meta["splits"][split]
    meta["seed"] = meta["split_info"]["seed"]
    actions = arrays.get("actions")
    if name in ACTION_OPTIONS:
        chosen = action or meta["default_action"]
        for option in ACTION_OPTIONS[name]:
            arr = arrays["action_options" + SEP + option]
            if option == chosen:
                actions = arr
            else:
                hidden[option] = arr
        meta["action"] = chosen
        meta["action_names"] = meta["action_options"][chosen]
        meta["units"] = {**meta["units"], "actions": meta["units"][chosen]}
    valid = arrays.get("valid")
    if name == "pendulum":
        info = meta["splits"][split]
        obs = render_pendulum(hidden["angle"], hidden["noise_factor"], seed=int(info["render_seed"]))
        obs[~valid] = 0.0
        angle = hidden["angle"]
        targets = np.stack([np.sin(angle), np.cos(angle)], axis=-1)
    else:
        obs = arrays["obs"]
        targets = arrays.get("targets")
    if valid is None:
        valid = np.ones(obs.shape[:2], dtype=bool)
    pieces = {"obs": obs, "actions": actions, "valid": valid, "targets": targets, "hidden": hidden}
    return pieces, meta


def _masked_mean_std(x: np.ndarray, mask: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (population) std over the rows of ``x (N, d)`` where ``mask (N,)``; float64, two passes."""
    w = np.asarray(mask, dtype=np.float64)
    count = w.sum()
    if count == 0:
        raise ValueError("mask: no valid entries to compute statistics from")
    total = np.zeros(x.shape[1])
    for start in range(0, x.shape[0], chunk):
        total += w[start:start + chunk] @ x[start:start + chunk].astype(np.float64)
    mean = total / count
    sq = np.zeros(x.shape[1])
    for start in range(0, x.shape[0], chunk):
        dev = x[start:start + chunk].astype(np.float64)
        dev -= mean
        dev *= dev
        sq += w[start:start + chunk] @ dev
    return mean, np.sqrt(sq / count)


def _compute_stats(pieces: dict[str, Any], with_diff: bool) -> dict[str, np.ndarray]:
    """Per-feature mean and std (float64) over valid steps; differences over valid pairs.

    Standard deviations are floored at 1e-6 so that normalising never divides by zero.
    """
    obs = np.asarray(pieces["obs"])
    valid = np.asarray(pieces["valid"], dtype=bool)
    n, T, d = obs.shape
    stats = {}
    stats["obs_mean"], std = _masked_mean_std(obs.reshape(n * T, d), valid.reshape(-1))
    stats["obs_std"] = np.maximum(std, 1e-6)
    if pieces["actions"] is not None:
        a = np.asarray(pieces["actions"])
        stats["act_mean"], std = _masked_mean_std(a.reshape(n * T, -1), np.ones(n * T, dtype=bool))
        stats["act_std"] = np.maximum(std, 1e-6)
    if with_diff:
        pair = (valid[:, 1:] & valid[:, :-1]).reshape(-1)
        diff = (obs[:, 1:].astype(np.float64) - obs[:, :-1]).reshape(n * (T - 1), d)
        stats["diff_mean"], std = _masked_mean_std(diff, pair)
        stats["diff_std"] = np.maximum(std, 1e-6)
    return stats


_STATS_CACHE: dict[tuple, dict[str, np.ndarray]] = {}


def _train_stats(name: str, action: str | None, train_pieces: dict[str, Any] | None) -> dict[str, np.ndarray]:
    path = _path(name)
    key = (name, action, str(path), path.stat().st_mtime_ns, path.stat().st_size)
    if key not in _STATS_CACHE:
        if train_pieces is None:
            train_pieces, _ = _assemble_numpy(name, "train", action)
        _STATS_CACHE[key] = _compute_stats(train_pieces, with_diff=name != "pendulum")
    return _STATS_CACHE[key]


def load(name: str, split: str = "train", dtype: torch.dtype = torch.float32,
         action: str | None = None) -> SequenceData:
    """Load one split of a bundled dataset (offline, from ``data/``).

    Args:
        name: one of :data:`DATASET_NAMES`.
        split: one of ``SPLITS[name]`` (e.g. ``"train"``, ``"valid"``, ``"test"``).
        dtype: floating dtype of the returned tensors (``valid`` is always bool).
        action: ``payload_arm``/``drift_arm`` only: ``"pd_target"`` (default) or
            ``"torque"``; the other action type is returned in ``hidden``.

    Returns:
        :class:`SequenceData` with tensors of shape ``(n, T, d)`` (see module docstring)
        and ``stats`` computed on the training split only.

    Raises:
        ValueError: unknown ``name``, ``split`` or ``action`` (the message lists the valid ones)
            or a non-floating ``dtype``.
        DataFileError: (a ``ValueError``) the file does not match ``data/SHA256SUMS`` or cannot
            be read; the message names the file and the command that restores it.
        FileNotFoundError: the file is missing (the message names the restoring command).

    Every file is checked against ``SHA256SUMS`` before use; the verdict is cached by the
    file's size and modification time, so only the first load of a file pays for hashing.
    """
    _check_name_split(name, split, action)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating torch dtype, got {dtype!r}")
    pieces, meta = _assemble_numpy(name, split, action)
    stats_np = _train_stats(name, action, pieces if split == "train" else None)

    def tens(x: np.ndarray | None) -> Tensor | None:
        return None if x is None else torch.from_numpy(np.ascontiguousarray(x)).to(dtype)

    return SequenceData(
        name=name,
        split=split,
        obs=tens(pieces["obs"]),
        actions=tens(pieces["actions"]),
        valid=torch.from_numpy(np.ascontiguousarray(pieces["valid"])).bool(),
        targets=tens(pieces["targets"]),
        hidden={key: tens(val) for key, val in pieces["hidden"].items()},
        meta=meta,
        stats={key: torch.tensor(val, dtype=dtype) for key, val in stats_np.items()},
    )

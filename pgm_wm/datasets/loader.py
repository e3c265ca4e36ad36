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
from importlib import resources
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from . import nile as _nile
from . import pam_arm as _pam_arm
from ._io import META_KEY, SEP, DataFileError, verify_file
from .pendulum import render_pendulum
from .sequences import SequenceData, stats_numpy

__all__ = ["DATASET_NAMES", "SPLITS", "ACTION_OPTIONS", "SequenceData", "load", "data_dir"]

DATASET_NAMES: tuple[str, ...] = (
    "nile", "tracking", "pendulum", "hysteresis_arm", "payload_arm", "drift_arm", "pam_arm",
    "memory_arm", "hidden_payload_arm", "slow_payload_arm",
)

SPLITS: dict[str, tuple[str, ...]] = {
    "nile": ("train",),
    "tracking": ("train", "test"),
    "pendulum": ("train", "valid", "test"),
    "hysteresis_arm": ("train", "valid", "test"),
    "payload_arm": ("train", "valid", "test", "interp", "extrap", "switching"),
    "drift_arm": ("train", "valid", "test"),
    "pam_arm": ("train", "valid", "test"),
    "memory_arm": ("train", "valid", "test"),
    "hidden_payload_arm": ("train", "valid", "test"),
    "slow_payload_arm": ("train", "valid", "test"),
}

#: Real data: rebuilt from a source file outside the repository, not by a generator.
REAL_DATASETS: tuple[str, ...] = ("nile", "pam_arm")

ACTION_OPTIONS: dict[str, tuple[str, ...]] = {
    "payload_arm": ("pd_target", "torque"),
    "drift_arm": ("pd_target", "torque"),
    "pam_arm": ("command", "increment"),
    "hidden_payload_arm": ("pd_target", "torque"),
}

FILENAMES: dict[str, str] = {name: f"{name}.npz" for name in DATASET_NAMES}
FILENAMES["nile"] = "nile.csv"


def _package_data_dir() -> Path | None:
    """``<package>/data`` of an installed wheel (the build copies ``data/`` there), else ``None``."""
    folder = resources.files("pgm_wm") / "data"
    if isinstance(folder, Path) and (folder / "SHA256SUMS").is_file():
        return folder
    return None


def _clone_data_dir() -> Path:
    """``<repo>/data`` next to the package folder of a clone (editable install or ``PYTHONPATH``)."""
    return Path(__file__).resolve().parent.parent.parent / "data"


def data_dir() -> Path:
    """Folder holding the bundled files: ``$PGM_WM_DATA`` if set; else the package's own ``data``
    folder (read with :mod:`importlib.resources`; present after ``pip install``); else the
    ``data/`` folder of the clone the package is imported from."""
    env = os.environ.get("PGM_WM_DATA")
    if env:
        return Path(env)
    packaged = _package_data_dir()
    if packaged is not None:
        return packaged
    return _clone_data_dir()


def _data_origin() -> str:
    """Where :func:`data_dir` points: ``"env"``, ``"package"`` or ``"clone"``."""
    if os.environ.get("PGM_WM_DATA"):
        return "env"
    return "package" if _package_data_dir() is not None else "clone"


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
    """The command that restores the bundled file of dataset ``name`` where :func:`data_dir` points.

    Simulated datasets and the Nile CSV are rewritten by ``python -m pgm_wm.datasets build``;
    the real ``pam_arm`` recordings only come back from a clone (``git checkout``) or by
    reinstalling the package (the wheel carries the file)."""
    build = f"python -m pgm_wm.datasets build --only {name}"
    origin = _data_origin()
    if name == "pam_arm":  # real data: converted only from its source archive (see data/README.md)
        if origin == "clone":
            return f"git checkout -- data/{FILENAMES[name]}"
        reinstall = "pip install --force-reinstall --no-deps pgm_wm  (the wheel carries data/pam_arm.npz)"
        if origin == "env":
            return (f"copy pam_arm.npz and its SHA256SUMS line from a pgm_wm clone's data/ folder into "
                    f"$PGM_WM_DATA, or unset PGM_WM_DATA to use the package's copy; or {reinstall}")
        return reinstall
    if origin == "env":
        return f"PGM_WM_DATA={data_dir()} {build}"
    return build


def _path(name: str) -> Path:
    """Path of the file of ``name``, verified against ``SHA256SUMS`` (cached while the file is unchanged)."""
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

    if name == "pam_arm":
        path = _path(name)
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files if key != META_KEY}
                meta = json.loads(str(data[META_KEY][()]))
            pieces = _pam_arm.assemble(arrays, meta, split, action or meta["default_action"])
        except _READ_ERRORS as err:
            raise _unreadable(path, name, err) from err
        meta["split_info"] = {**meta["splits"][split], "indices": pieces.pop("episode_index").tolist()}
        meta["seed"] = meta["split_info"]["seed"]
        meta["action"] = action or meta["default_action"]
        meta["action_names"] = meta["action_options"][meta["action"]]
        meta["units"] = {**meta["units"], "actions": meta["units"][meta["action"]]}
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


def _compute_stats(pieces: dict[str, Any], with_diff: bool) -> dict[str, np.ndarray]:
    """:func:`~pgm_wm.datasets.sequences.compute_stats` of the numpy pieces of a split (float64)."""
    actions = None if pieces["actions"] is None else np.asarray(pieces["actions"])
    return stats_numpy(np.asarray(pieces["obs"]), actions, np.asarray(pieces["valid"], dtype=bool), with_diff)


_STATS_CACHE: dict[tuple, dict[str, np.ndarray]] = {}


def _train_stats(name: str, action: str | None, train_pieces: dict[str, Any] | None) -> dict[str, np.ndarray]:
    path = _path(name)
    st = path.stat()
    key = (name, action, str(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
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

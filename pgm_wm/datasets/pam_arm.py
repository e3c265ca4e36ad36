r"""Real data of the four-joint pneumatic-artificial-muscle (PAM) arm (chapter 4).

Source: the public repository ``ALRhub/action-conditional-rkn`` (MIT licence,
"Copyright (c) 2021 vaisakh-shaj"), commit ``7a8ae18``, folder
``data/PAMData/Data2/``: 3076 JSON episodes. The project's subset
``pam_arm_subset.npz`` keeps every 5th episode in name order (616 episodes,
86-146 steps, 66,686 steps); :func:`convert` turns it into ``data/pam_arm.npz``.
Cite: V. Shaj, P. Becker, D. Büchler, H. Pandya, N. van Duijkeren, C. J. Taylor,
M. Hanheide, G. Neumann, "Action-Conditional Recurrent Kalman Networks for
Forward and Inverse Dynamics Learning", CoRL 2020.

What is stored (only the true-length steps, episodes concatenated):

- ``angle`` ``(66686, 4)`` float32: the four joint angles (rad), the observations;
- ``increment`` ``(66686, 8)`` float32: the recorded ``action``, about N(0, 1) per
  channel, an increment of the eight muscles' pressure commands;
- ``pressure_counts`` ``(66686, 8)`` int16 and ``pressure_scale`` ``(8,)``: the eight
  measured pressures are exactly ``float32(counts / scale)`` (the recorded values
  are averaged sensor counts), which stores them losslessly in half the bytes;
- ``length``, ``episode`` (original file names), ``split__<name>`` (episode indices).

Left out: the recorded columns 4-7 (velocity-like, zero at the first step) and,
already in the subset, columns 16-23 (command-like and constant columns).

Action representation (chosen by :func:`action_representation_check`; numbers in
``data/README.md``): the default ``action="command"`` is the running sum over time
of the increments within each episode,

.. math:: c_t = \sum_{s \le t} a_s,

i.e. the pressure command level (``c`` correlates 0.38-0.78 with the measured
pressure, ``a`` at most 0.53, and only two to three steps later); ``action="increment"``
gives the raw ``a_t``. The measured pressures are outputs of the arm, not inputs
one can choose, so they are returned in ``hidden["pressure"]``, never as actions.

Split: one seeded permutation of the 616 episodes (:func:`~pgm_wm.datasets.sequences.split_indices`,
seed :data:`SPLIT_SEED`, fractions 70/15/15 %), drawn once at conversion and stored
in the file, so the split does not depend on the numpy version.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .sequences import SequenceData, split_indices

__all__ = ["VERSION", "SPLIT_SEED", "SPLIT_FRACTIONS", "SOURCE_NAME", "find_source", "convert",
           "assemble", "action_representation_check"]

VERSION = "1.0"
SPLIT_SEED = 20
SPLIT_FRACTIONS = (0.7, 0.15, 0.15)
SPLIT_NAMES = ("train", "valid", "test")
SOURCE_NAME = "pam_arm_subset.npz"
N_ANGLES = 4
PRESSURE_COLUMNS = slice(8, 16)

LICENCE = """MIT License

Copyright (c) 2021 vaisakh-shaj

Permission is hereby granted, free of charge, to any person obtaining a copy
of this software and associated documentation files (the "Software"), to deal
in the Software without restriction, including without limitation the rights
to use, copy, modify, merge, publish, distribute, sublicense, and/or sell
copies of the Software, and to permit persons to whom the Software is
furnished to do so, subject to the following conditions:

The above copyright notice and this permission notice shall be included in all
copies or substantial portions of the Software.

THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND, EXPRESS OR
IMPLIED, INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY,
FITNESS FOR A PARTICULAR PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE
AUTHORS OR COPYRIGHT HOLDERS BE LIABLE FOR ANY CLAIM, DAMAGES OR OTHER
LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR OTHERWISE, ARISING FROM,
OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER DEALINGS IN THE
SOFTWARE.
"""
CITATION = ("V. Shaj, P. Becker, D. Buechler, H. Pandya, N. van Duijkeren, C. J. Taylor, M. Hanheide, "
            "G. Neumann. Action-Conditional Recurrent Kalman Networks for Forward and Inverse Dynamics "
            "Learning. Conference on Robot Learning (CoRL), 2020.")


def find_source(explicit: str | os.PathLike | None = None) -> Path | None:
    """The source subset: ``explicit``, ``$PGM_WM_PAM_SOURCE``, or ``shared/data/`` next to or above the repo."""
    if explicit is not None:
        return Path(explicit)
    env = os.environ.get("PGM_WM_PAM_SOURCE")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parent.parent.parent
    for base in (repo, repo.parent, repo.parent.parent):
        cand = base / "shared" / "data" / SOURCE_NAME
        if cand.exists():
            return cand
    return None


def _pressure_scale(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer counts ``(N, 8)`` and per-channel scales with ``float32(counts / scale) == p`` exactly."""
    counts, scales = [], []
    for c in range(p.shape[1]):
        x = p[:, c]
        for scale in range(100, 20001, 100):
            k = np.round(x.astype(np.float64) * scale)
            if np.abs(k).max() < 2**15 and np.array_equal((k / scale).astype(np.float32), x):
                counts.append(k.astype(np.int16))
                scales.append(float(scale))
                break
        else:
            raise ValueError(f"source: pressure column {c} is not a ratio of int16 counts")
    return np.stack(counts, axis=1), np.asarray(scales)


def convert(source: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays and metadata of ``data/pam_arm.npz`` from the source subset (see module docstring)."""
    with np.load(source, allow_pickle=False) as src:
        ob, act, length, episode = src["ob"], src["action"], src["length"], src["episode"]
    n, T, _ = ob.shape
    if act.shape[:2] != (n, T) or length.shape != (n,) or length.max() > T:
        raise ValueError(f"source: unexpected shapes ob {ob.shape}, action {act.shape}, length {length.shape}")
    mask = np.arange(T)[None, :] < length[:, None]
    counts, scale = _pressure_scale(ob[mask][:, PRESSURE_COLUMNS])
    arrays: dict[str, np.ndarray] = {
        "angle": ob[mask][:, :N_ANGLES].astype(np.float32),
        "increment": act[mask].astype(np.float32),
        "pressure_counts": counts,
        "pressure_scale": scale,
        "length": length.astype(np.int32),
        "episode": episode.astype("<U15"),
    }
    parts = split_indices(n, SPLIT_FRACTIONS, SPLIT_SEED)
    for name, idx in zip(SPLIT_NAMES, parts):
        arrays[f"split__{name}"] = idx.astype(np.int64)
    meta = {
        "generator": {"name": "pgm_wm.datasets.pam_arm.convert (real data, no simulation)",
                      "version": VERSION, "params": {"split_seed": SPLIT_SEED,
                                                     "split_fractions": list(SPLIT_FRACTIONS)}},
        "splits": {name: {"n": int(len(idx)), "T": int(T), "seed": SPLIT_SEED}
                   for name, idx in zip(SPLIT_NAMES, parts)},
        "dt": None,
        "dt_note": "the sampling period is not stated in the source; episode start times "
                   "(the file names) lie 3-4 s apart for at most 146 steps",
        "units": {"obs": "rad", "command": "running sum of the increments (pressure-command units)",
                  "increment": "recorded action (pressure-command increment, about N(0, 1))",
                  "pressure": "measured muscle pressure (normalised, about [-0.2, 1.3])"},
        "obs_names": [f"joint{j + 1}" for j in range(N_ANGLES)],
        "action_options": {"command": [f"command{m + 1}" for m in range(8)],
                           "increment": [f"increment{m + 1}" for m in range(8)]},
        "default_action": "command",
        "target_names": [],
        "source": "github.com/ALRhub/action-conditional-rkn, commit 7a8ae18, data/PAMData/Data2/ "
                  "(every 5th of 3076 JSON episodes in name order)",
        "licence": LICENCE,
        "citation": CITATION,
        "left_out": "recorded ob columns 4-7 (velocity-like) and 16-23 (command-like / constant)",
        "description": "Real four-joint pneumatic-muscle arm: 616 episodes of 86-146 steps; joint "
                       "angles observed, eight pressure-command increments as actions, measured "
                       "pressures hidden. Zero-padded to 146 steps; valid marks the true length.",
    }
    return arrays, meta


def assemble(arrays: dict[str, np.ndarray], meta: dict, split: str, action: str) -> dict[str, Any]:
    """Padded numpy pieces (``obs, actions, valid, targets, hidden``) of one split of the file."""
    length = arrays["length"].astype(np.int64)
    offsets = np.concatenate([[0], np.cumsum(length)])
    idx = arrays[f"split__{split}"]
    T = int(length.max())
    n = len(idx)
    valid = np.arange(T)[None, :] < length[idx][:, None]
    pressure_all = (arrays["pressure_counts"] / arrays["pressure_scale"]).astype(np.float32)
    out = {key: np.zeros((n, T, width), dtype=np.float32)
           for key, width in (("angle", N_ANGLES), ("increment", 8), ("pressure", 8))}
    for row, ep in enumerate(idx):
        steps = slice(offsets[ep], offsets[ep + 1])
        out["angle"][row, :length[ep]] = arrays["angle"][steps]
        out["increment"][row, :length[ep]] = arrays["increment"][steps]
        out["pressure"][row, :length[ep]] = pressure_all[steps]
    command = np.cumsum(out["increment"].astype(np.float64), axis=1).astype(np.float32) * valid[..., None]
    options = {"command": command, "increment": out["increment"]}
    hidden = {"pressure": out["pressure"]}
    hidden.update({key: val for key, val in options.items() if key != action})
    return {"obs": out["angle"], "actions": options[action], "valid": valid, "targets": None,
            "hidden": hidden, "episode_index": idx}


def _ridge_pairs(data: SequenceData, inputs: np.ndarray, history: int, horizon: int,
                 stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Features: last ``history`` angles and inputs ``[t-history+1, t+horizon-1]``; target angle change."""
    obs = data.obs.double().numpy()
    lengths = data.valid.sum(1).numpy()
    X, Y = [], []
    for i in range(obs.shape[0]):
        for t in range(history - 1, int(lengths[i]) - horizon, stride):
            X.append(np.concatenate([obs[i, t - history + 1:t + 1].ravel(),
                                     inputs[i, t - history + 1:t + horizon].ravel()]))
            Y.append(obs[i, t + horizon] - obs[i, t])
    return np.asarray(X), np.asarray(Y)


def action_representation_check(train: SequenceData, valid: SequenceData, horizons: tuple[int, ...] = (1, 10, 25, 50),
                                history: int = 10, stride: int = 3, lam: float = 1e-3) -> dict[str, dict[int, float]]:
    """Validation RMSE (rad) of ridge predictors of the ``h``-step angle change, per input representation.

    Each predictor sees the last ``history`` angles and one input sequence over
    ``[t - history + 1, t + h - 1]`` (past and future): ``increment`` (raw actions),
    ``command`` (their running sum), ``pressure`` (the *measured* pressures, future
    ones included, i.e. an upper bound no controller input can reach) or ``none``;
    ``repeat_last`` predicts no change. ``train``/``valid`` are :func:`load` splits
    with ``action="command"``; fitted on ``train``, scored on ``valid``.
    """
    from .regression import ridge_rmse

    def inputs(data: SequenceData) -> dict[str, np.ndarray]:
        cmd = data.actions.double().numpy()
        return {"increment": data.hidden["increment"].double().numpy(), "command": cmd,
                "pressure": data.hidden["pressure"].double().numpy(), "none": cmd[..., :0]}

    tr, va = inputs(train), inputs(valid)
    out: dict[str, dict[int, float]] = {key: {} for key in ("repeat_last", *tr)}
    for h in horizons:
        for key in tr:
            Xt, Yt = _ridge_pairs(train, tr[key], history, h, stride)
            Xv, Yv = _ridge_pairs(valid, va[key], history, h, stride)
            out[key][h] = ridge_rmse(Xt, Yt, Xv, Yv, lam=lam)
        out["repeat_last"][h] = float(np.sqrt((Yv ** 2).mean()))
    return out

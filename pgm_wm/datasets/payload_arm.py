r"""Payload arm (chapters 2 and 5): the 2-link arm of :mod:`.two_link_arm` with a tip payload.

Dynamics, controller and observation model: see :mod:`pgm_wm.datasets.two_link_arm`
(Eq. (arm-dynamics), Eq. (arm-pd)); frames every :math:`\Delta = 0.02` s.

Payload schedules (kg), one value per sequence unless stated:

- ``train``/``valid``/``test``: :math:`m_p \sim U([0, 0.5] \cup [0.75, 1.75])`
  (uniform over the union, i.e. interval chosen with probability proportional to its length);
- ``interp``: :math:`m_p \sim U(0.5, 0.75)`, the gap left out of training;
- ``extrap``: :math:`m_p \sim U(2.0, 2.5)`, heavier than anything in training;
- ``switching``: piecewise constant, a new value from the training distribution
  every :math:`U(2, 6)` s (15 s sequences).

Observations: joint angles and velocities ``(q1, q2, qd1, qd2)``; both
velocities and angles are needed for the state to be Markov given the torque.
Actions: ``pd_target`` (default) or ``torque``; the other one is in ``hidden``.
"""

from __future__ import annotations

import numpy as np

from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import VERSION as ARM_VERSION
from .two_link_arm import ARM_META, arm_splits

__all__ = [
    "VERSION", "DEFAULT_PARAMS", "SPLITS", "TRAIN_PAYLOAD_RANGES", "sample_train_payloads",
    "payload_schedule", "split_schedule", "generate",
]

VERSION = "1.0"
TRAIN_PAYLOAD_RANGES: list[tuple[float, float]] = [(0.0, 0.5), (0.75, 1.75)]

DEFAULT_PARAMS: dict = {**ARM_PARAMS, "dt": 0.02, "n_substeps": 10, "switch_hold": [2.0, 6.0]}

# split -> (n_sequences, T, seed, schedule kind, payload range or None)
SPLITS: dict[str, tuple[int, int, int, str, list[float] | None]] = {
    "train": (256, 200, 5101, "constant", None),
    "valid": (32, 200, 5102, "constant", None),
    "test": (64, 200, 5103, "constant", None),
    "interp": (48, 200, 5104, "constant", [0.5, 0.75]),
    "extrap": (48, 200, 5105, "constant", [2.0, 2.5]),
    "switching": (48, 750, 5106, "switching", None),
}


def sample_train_payloads(rng: np.random.Generator, size: int | tuple[int, ...]) -> np.ndarray:
    """Uniform draws over the union of :data:`TRAIN_PAYLOAD_RANGES` (kg)."""
    lengths = np.array([hi - lo for lo, hi in TRAIN_PAYLOAD_RANGES])
    u = rng.uniform(0.0, lengths.sum(), size=size)
    out = np.empty_like(u)
    start = 0.0
    for (lo, hi), length in zip(TRAIN_PAYLOAD_RANGES, lengths):
        sel = (u >= start) & (u < start + length)
        out[sel] = lo + (u[sel] - start)
        start += length
    out[u >= start] = TRAIN_PAYLOAD_RANGES[-1][1]
    return out


def payload_schedule(
    rng: np.random.Generator, n: int, T: int, kind: str, value_range: list[float] | None, p: dict
) -> np.ndarray:
    """Payload per frame ``(n, T)`` in kg for a ``constant`` or ``switching`` schedule."""
    if kind == "constant":
        if value_range is None:
            mp = sample_train_payloads(rng, n)
        else:
            mp = rng.uniform(value_range[0], value_range[1], size=n)
        return np.repeat(mp[:, None], T, axis=1)
    if kind == "switching":
        lo, hi = p["switch_hold"]
        n_max = int(np.ceil(T * p["dt"] / lo)) + 2
        levels = sample_train_payloads(rng, (n, n_max))
        switch = np.floor(np.cumsum(rng.uniform(lo, hi, size=(n, n_max)), axis=1) / p["dt"])
        idx = (switch[:, None, :] <= np.arange(T)[None, :, None]).sum(axis=2)
        return levels[np.arange(n)[:, None], idx]
    raise ValueError(f"kind: expected 'constant' or 'switching', got {kind!r}")


def split_schedule(split: str, params: dict | None = None) -> dict[str, np.ndarray]:
    """``{"payload": (n, T)}`` in kg of one split, drawn from its seed (:func:`payload_schedule`)."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    n, T, seed, kind, value_range = SPLITS[split]
    return {"payload": payload_schedule(np.random.default_rng(seed), n, T, kind, value_range, p)}


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays, splits_meta = arm_splits({split: spec[2] for split, spec in SPLITS.items()}, split_schedule, p)
    for split, (_, _, _, kind, value_range) in SPLITS.items():
        splits_meta[split].update({"payload_schedule": kind,
                                   "payload_range": value_range if value_range is not None
                                   else [list(r) for r in TRAIN_PAYLOAD_RANGES]})
    meta = {
        "generator": {"name": "pgm_wm.datasets.two_link_arm.simulate_two_link_arm",
                      "version": f"{VERSION}+arm{ARM_VERSION}", "params": p,
                      "schedule": "pgm_wm.datasets.payload_arm.payload_schedule"},
        "splits": splits_meta,
        "dt": p["dt"],
        **ARM_META,
        "train_payload_ranges": [list(r) for r in TRAIN_PAYLOAD_RANGES],
        "description": "PD-controlled planar 2-link arm (3 kg and 2 kg links of 0.5 m) with a tip "
                       "payload of 0-2.5 kg; gravity compensation ignores the payload, so the arm "
                       "sags and slows down with load. Splits: train payload ranges, held-out "
                       "interpolation (0.5-0.75 kg) and extrapolation (2-2.5 kg) payloads, and "
                       "sequences whose payload switches every 2-6 s.",
    }
    return arrays, meta

r"""Drift arm (chapter 6): the 2-link arm with a slowly drifting payload over long episodes.

Dynamics, controller and observation model: see :mod:`pgm_wm.datasets.two_link_arm`
(Eq. (arm-dynamics), Eq. (arm-pd)); frames every :math:`\Delta = 0.04` s (25 Hz,
controller at the same rate, 10 substeps of 4 ms), episodes of 1000 frames (40 s),
so a window of 25 frames is 1 s and a 2-4 s open-loop horizon is 50-100 frames.

Payload (kg), per episode, a smooth slow drift inside (0, 2.5):

.. math::

    m_p(t) = 1.25\,\bigl(1 + \tanh s(t)\bigr),\qquad
    s(t) = \sum_{k=1}^{3} a_k \sin(2\pi t / P_k + \varphi_k),

with periods :math:`P_k \sim U(10, 60)` s, amplitudes :math:`a_k \sim U(0.3, 0.6)`
and phases :math:`\varphi_k \sim U(0, 2\pi)`.

Observations ``(q1, q2, qd1, qd2)``; actions ``pd_target`` (default) or ``torque``.
"""

from __future__ import annotations

import numpy as np

from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import VERSION as ARM_VERSION
from .two_link_arm import ARM_META, arm_splits

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "drifting_payload", "split_schedule", "generate"]

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    **ARM_PARAMS,
    "dt": 0.04,
    "n_substeps": 10,
    "drift_periods": [10.0, 60.0],
    "drift_amplitudes": [0.3, 0.6],
    "drift_n_sines": 3,
    "payload_max": 2.5,
}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (48, 1000, 6101),
    "valid": (12, 1000, 6102),
    "test": (24, 1000, 6103),
}


def drifting_payload(rng: np.random.Generator, n: int, T: int, p: dict) -> np.ndarray:
    """Payload per frame ``(n, T)`` in kg following the slow drift in the module docstring."""
    k = int(p["drift_n_sines"])
    periods = rng.uniform(*p["drift_periods"], size=(n, k, 1))
    amps = rng.uniform(*p["drift_amplitudes"], size=(n, k, 1))
    phases = rng.uniform(0.0, 2.0 * np.pi, size=(n, k, 1))
    t = np.arange(T) * p["dt"]
    s = (amps * np.sin(2.0 * np.pi * t / periods + phases)).sum(axis=1)
    return 0.5 * p["payload_max"] * (1.0 + np.tanh(s))


def split_schedule(split: str, params: dict | None = None) -> dict[str, np.ndarray]:
    """``{"payload": (n, T)}`` in kg of one split, drawn from its seed (:func:`drifting_payload`)."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    n, T, seed = SPLITS[split]
    return {"payload": drifting_payload(np.random.default_rng(seed), n, T, p)}


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays, splits_meta = arm_splits({split: seed for split, (_, _, seed) in SPLITS.items()}, split_schedule, p)
    meta = {
        "generator": {"name": "pgm_wm.datasets.two_link_arm.simulate_two_link_arm",
                      "version": f"{VERSION}+arm{ARM_VERSION}", "params": p,
                      "schedule": "pgm_wm.datasets.drift_arm.drifting_payload"},
        "splits": splits_meta,
        "dt": p["dt"],
        **ARM_META,
        "description": "The payload arm at 25 Hz over 40 s episodes whose tip payload drifts "
                       "slowly inside (0, 2.5) kg (sum of sines with periods of 10-60 s).",
    }
    return arrays, meta

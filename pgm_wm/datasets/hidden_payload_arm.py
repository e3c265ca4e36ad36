r"""Hidden-payload arm (chapter 5): a payload that matters for the prediction but is not readable from a short window.

The PD-controlled 2-link arm of :mod:`.two_link_arm` (Eq. (arm-dynamics), Eq. (arm-pd)),
here moving in the **horizontal plane** (:math:`g = 0`): the tip payload
:math:`m_p \sim U(0, 3)` kg (one value per sequence) leaves no static trace (no sag)
and acts only through the inertia :math:`M(q, m_p)` and the Coriolis terms, i.e. only
while the arm accelerates. PD targets are smoothed random waypoints (new one every
0.3-1.0 s, smoothing 0.05 s), so every second holds several transients whose shape
depends on the payload. Torque noise (OU, std 0.5 N m, 0.1 s) and velocity noise
(0.05 rad/s) make a short stretch of data a poor witness of the payload, while a
context of one or two previous windows identifies it.

Frames every :math:`\Delta = 0.02` s; observations ``(q1, q2, qd1, qd2)``; actions
``pd_target`` (default) or ``torque`` (the other one in ``hidden``);
``hidden["payload"] (n, T)`` in kg. The structure diagnostic
(:func:`pgm_wm.datasets.structure.hidden_payload_checks`) compares a physics oracle
with the true and with the nominal payload and a physics identifier fed with the
target window's first steps or with the context.
"""

from __future__ import annotations

import numpy as np

from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import VERSION as ARM_VERSION
from .two_link_arm import ARM_META, arm_splits

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "PAYLOAD_RANGE", "split_schedule", "generate"]

VERSION = "1.0"
PAYLOAD_RANGE = (0.0, 3.0)

DEFAULT_PARAMS: dict = {**ARM_PARAMS, "dt": 0.02, "n_substeps": 10, "g": 0.0, "target_hold": [0.3, 1.0],
                        "target_smoothing": 0.05, "torque_noise": 0.5, "qd_obs_noise": 0.05}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (192, 250, 8101),
    "valid": (32, 250, 8102),
    "test": (64, 250, 8103),
}


def split_schedule(split: str, params: dict | None = None) -> dict[str, np.ndarray]:
    """``{"payload": (n, T)}`` in kg of one split, drawn from its seed (one value per sequence)."""
    n, T, seed = SPLITS[split]
    rng = np.random.default_rng(seed)
    return {"payload": np.repeat(rng.uniform(*PAYLOAD_RANGE, size=n)[:, None], T, axis=1)}


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays, splits_meta = arm_splits({split: seed for split, (_, _, seed) in SPLITS.items()}, split_schedule, p)
    for info in splits_meta.values():
        info["payload_range"] = list(PAYLOAD_RANGE)
    meta = {
        "generator": {"name": "pgm_wm.datasets.two_link_arm.simulate_two_link_arm",
                      "version": f"{VERSION}+arm{ARM_VERSION}", "params": p,
                      "schedule": "constant payload per sequence, U(0, 3) kg"},
        "splits": splits_meta,
        "dt": p["dt"],
        **ARM_META,
        "nominal_payload": float(np.mean(PAYLOAD_RANGE)),
        "description": "PD-controlled 2-link arm in the horizontal plane with a hidden tip payload of "
                       "0-3 kg that acts only through inertia: it changes every transient but leaves "
                       "no static trace, so a short window does not reveal it and a context does.",
    }
    return arrays, meta

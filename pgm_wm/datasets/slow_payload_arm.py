r"""Slow-payload arm (chapter 6): a slow factor caused by the actions, predictable over 8 s, positions only.

The PD-controlled vertical 2-link arm of :mod:`.two_link_arm` (Eq. (arm-dynamics),
Eq. (arm-pd), gravity compensation of the nominal arm, so the payload makes it sag)
at 25 Hz (:math:`\Delta = 0.04` s) over 60-s episodes (1500 frames). The tip payload
is a tank filled and drained by a third, slow action, the pump command
:math:`u^\text{pump}_t \in [-1, 1]` (random levels held 2-6 s):

.. math::

    s_{t+1} = s_t + \kappa\,\Delta\,u^\text{pump}_t,\qquad
    m_p(t) = m_\text{max}\,\sigma(s_t),\qquad s_0 \sim N(0, 1),

with :math:`\kappa = 0.15\ \text{s}^{-1}` and :math:`m_\text{max} = 2.5` kg, so the
payload moves by at most about 0.5 kg per 8 s and is a deterministic, learnable
function of the past actions. Observations: the two joint angles only (noise 0.001
rad); actions ``(q1_target, q2_target, pump)``; ``hidden``: ``payload`` (kg)
(velocities and torques are left out of the file; the simulator returns them). A 1-s window is 25 frames and the 8-s
horizon 200 frames; a 300-frame training crop holds twelve windows.
"""

from __future__ import annotations

import numpy as np

from .signals import random_steps
from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import VERSION as ARM_VERSION
from .two_link_arm import SIM_SEED_OFFSET, simulate_two_link_arm

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "pump_actions", "tank_payload", "split_schedule", "generate"]

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    **ARM_PARAMS,
    "dt": 0.04,
    "n_substeps": 10,
    "pump_hold": [2.0, 6.0],   # s
    "pump_rate": 0.15,         # kappa, 1/s
    "payload_max": 2.5,        # kg
    "s0_std": 1.0,
}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (32, 1500, 9101),
    "valid": (8, 1500, 9102),
    "test": (16, 1500, 9103),
}


def pump_actions(rng: np.random.Generator, n: int, T: int, p: dict) -> np.ndarray:
    """Pump commands ``(n, T)``: random levels in [-1, 1] held ``pump_hold`` seconds."""
    return random_steps(rng, n, T, p["dt"], tuple(p["pump_hold"]), -1.0, 1.0)


def tank_payload(s0: np.ndarray, pump: np.ndarray, p: dict) -> tuple[np.ndarray, np.ndarray]:
    """Tank level ``s (n, T)`` and payload ``m_p (n, T)`` in kg from ``s0 (n,)`` and ``pump (n, T)``."""
    s = s0[:, None] + p["pump_rate"] * p["dt"] * np.concatenate(
        [np.zeros((len(s0), 1)), np.cumsum(pump[:, :-1], axis=1)], axis=1)
    return s, p["payload_max"] / (1.0 + np.exp(-s))


def split_schedule(split: str, params: dict | None = None) -> dict[str, np.ndarray]:
    """``{"pump": (n, T), "payload": (n, T)}`` of one split, drawn from its seed (:func:`tank_payload`)."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    n, T, seed = SPLITS[split]
    rng = np.random.default_rng(seed)
    pump = pump_actions(rng, n, T, p)
    _, payload = tank_payload(p["s0_std"] * rng.standard_normal(n), pump, p)
    return {"pump": pump, "payload": payload}


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arm_p = {key: p[key] for key in ARM_PARAMS}
    arrays: dict[str, np.ndarray] = {}
    splits_meta = {}
    for split, (n, T, seed) in SPLITS.items():
        sched = split_schedule(split, p)
        pump, payload = sched["pump"], sched["payload"]
        out = simulate_two_link_arm(seed + SIM_SEED_OFFSET, payload, arm_p)
        arrays[f"{split}__obs"] = out["obs"][..., :2].astype(np.float32)
        arrays[f"{split}__actions"] = np.concatenate([out["pd_target"], pump[..., None]], -1).astype(np.float32)
        arrays[f"{split}__hidden__payload"] = payload.astype(np.float32)
        splits_meta[split] = {"n": n, "T": T, "seed": seed, "sim_seed": seed + SIM_SEED_OFFSET}
    meta = {
        "generator": {"name": "pgm_wm.datasets.two_link_arm.simulate_two_link_arm",
                      "version": f"{VERSION}+arm{ARM_VERSION}", "params": p,
                      "schedule": "pgm_wm.datasets.slow_payload_arm.tank_payload"},
        "splits": splits_meta,
        "dt": p["dt"],
        "units": {"obs": "rad", "actions": "rad, rad, pump command in [-1, 1]", "payload": "kg"},
        "obs_names": ["q1", "q2"],
        "action_names": ["q1_target", "q2_target", "pump"],
        "target_names": [],
        "description": "The payload arm at 25 Hz over 60 s episodes, angles only; the tip payload is a "
                       "tank filled and drained by a slow pump action, so it changes slowly, "
                       "predictably and because of the actions.",
    }
    return arrays, meta

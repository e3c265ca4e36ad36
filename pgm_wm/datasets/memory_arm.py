r"""Long-memory hysteresis arm (chapter 4): two pneumatic-muscle-like joints whose past matters for seconds.

Each joint :math:`j \in \{1, 2\}` is driven by a valve command :math:`u_j \in [-1, 1]`
(held over a frame of :math:`\Delta = 0.02` s, ``n_substeps`` substeps of :math:`h`).
Only the joint angles :math:`\theta_j` are observed (noise ``obs_noise``).

Pressure with an asymmetric lag (fills fast, vents slowly), exact per substep:

.. math::

    p \leftarrow u + (p - u)\,e^{-h/\tau},\qquad
    \tau = \tau_\text{fill}\ \text{if}\ (u - p)\,p \ge 0,\ \text{else}\ \tau_\text{vent}.

Prandtl-Ishlinskii hysteresis: play operators of radii :math:`r_i`, weights :math:`w_i`,

.. math::

    y_i \leftarrow \min\bigl(\max(y_i,\ p - r_i),\ p + r_i\bigr),\qquad H = \sum_i w_i\, y_i .

A play operator keeps its state until the pressure leaves its band, so the wide ones
remember the last large excursion indefinitely (rate-independent, long memory).

Creep and creep recovery (two first-order relaxations of the muscle, fast and slow):

.. math::

    \dot c_k = (H - c_k)/\tau_k,\ k = 1, 2,\qquad
    \theta^\star_j = g_j\,\bigl(H + a\,(c_1 - c_2)\bigr),

so after a change of :math:`H` the joint overshoots and relaxes back over
:math:`\tau_2` (seconds); how far it still has to go is a function of the past that
the last few angles do not reveal (they show :math:`c_1 - c_2`, not each).

Joint: a damped second-order response to the equilibrium :math:`\theta^\star`,

.. math::

    \ddot\theta_j = \omega_n^2 (\theta^\star_j - \theta_j) - 2\zeta\omega_n\,\dot\theta_j,

semi-implicit Euler (velocity first). Actions: per joint a smoothed random step level
in [-0.9, 0.9] held 0.5-2 s plus two small sines (0.3-1.5 Hz), clipped to [-1, 1];
``burn_in`` frames are simulated and dropped. Stored hidden (evaluation only): the
hysteresis output :math:`H`; velocity, pressure and creep states are left out of the
file to keep it small (:func:`simulate_memory_arm` returns them).
"""

from __future__ import annotations

import numpy as np

from .signals import drop_burn_in, lowpass, random_steps, sum_of_sines

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "memory_actions", "simulate_memory_arm", "generate"]

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    "dt": 0.02,
    "n_substeps": 5,
    "tau_fill": 0.08,          # s
    "tau_vent": 0.2,           # s
    "play_radii": [0.02, 0.05, 0.1, 0.15, 0.2],
    "play_weights": [0.3, 0.3, 0.3, 0.3, 0.3],
    "creep_taus": [0.3, 3.0],  # s, fast and slow relaxation
    "creep_gain": 1.0,         # a
    "joint_gain": [0.5, 0.4],  # g_j, rad per unit of H
    "omega_n": 12.0,           # rad/s
    "zeta": 0.4,
    "obs_noise": 0.0005,       # rad
    "burn_in": 150,            # frames (3 s) simulated and dropped
    "step_hold": [0.5, 2.0],   # s
    "step_level": 0.9,
    "step_smoothing": 0.1,     # s
    "n_sines": 2,
    "sine_freq": [0.3, 1.5],
    "sine_amp": [0.05, 0.2],
}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (192, 300, 7101),
    "valid": (32, 300, 7102),
    "test": (64, 300, 7103),
}


def memory_actions(rng: np.random.Generator, n: int, T: int, p: dict) -> np.ndarray:
    """Valve commands ``(n, T, 2)``: smoothed random steps plus small sines, clipped to [-1, 1]."""
    acts = []
    for _ in range(2):
        level = random_steps(rng, n, T, p["dt"], tuple(p["step_hold"]), -p["step_level"], p["step_level"])
        s = lowpass(level, p["dt"], p["step_smoothing"], order=2)
        s += sum_of_sines(rng, n, T, p["dt"], p["n_sines"], tuple(p["sine_freq"]), tuple(p["sine_amp"]))
        acts.append(s)
    return np.clip(np.stack(acts, axis=-1), -1.0, 1.0)


def initial_state(n: int, p: dict) -> dict[str, np.ndarray]:
    """All-zero state: ``angle, velocity, pressure (n, 2)``, ``play (n, 2, n_play)``, ``creep (n, 2, 2)``."""
    return {"angle": np.zeros((n, 2)), "velocity": np.zeros((n, 2)), "pressure": np.zeros((n, 2)),
            "play": np.zeros((n, 2, len(p["play_radii"]))), "creep": np.zeros((n, 2, len(p["creep_taus"])))}


def rollout_memory_arm(u: np.ndarray, state: dict[str, np.ndarray], params: dict | None = None
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Integrate the module's equations for actions ``u (n, T, 2)`` from ``state``.

    Returns ``(record, final_state)``: ``record`` holds ``angle, velocity, pressure,
    hysteresis (n, T, 2)``, ``creep (n, T, 2, 2)`` and ``play (n, T, 2, n_play)`` at the
    start of every frame (with ``play`` and ``creep`` the full state of :func:`initial_state`).
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    n, T, _ = u.shape
    k = int(p["n_substeps"])
    h = p["dt"] / k
    radii = np.asarray(p["play_radii"])
    weights = np.asarray(p["play_weights"])
    decay_fill = np.exp(-h / p["tau_fill"])
    decay_vent = np.exp(-h / p["tau_vent"])
    decay_creep = np.exp(-h / np.asarray(p["creep_taus"]))
    gain = np.asarray(p["joint_gain"])
    wn, zeta, a = p["omega_n"], p["zeta"], p["creep_gain"]
    th, om, pr = state["angle"].copy(), state["velocity"].copy(), state["pressure"].copy()
    y, c = state["play"].copy(), state["creep"].copy()
    rec = {key: np.empty((n, T, 2)) for key in ("angle", "velocity", "pressure", "hysteresis")}
    rec["creep"] = np.empty((n, T, 2, c.shape[-1]))
    rec["play"] = np.empty((n, T, 2, y.shape[-1]))
    for t in range(T):
        H = (y * weights).sum(-1)
        rec["angle"][:, t], rec["velocity"][:, t], rec["pressure"][:, t] = th, om, pr
        rec["hysteresis"][:, t], rec["creep"][:, t], rec["play"][:, t] = H, c, y
        v = u[:, t]
        for _ in range(k):
            pr = v + (pr - v) * np.where((v - pr) * pr >= 0.0, decay_fill, decay_vent)
            y = np.clip(y, pr[..., None] - radii, pr[..., None] + radii)
            H = (y * weights).sum(-1)
            c = H[..., None] + (c - H[..., None]) * decay_creep
            target = gain * (H + a * (c[..., 0] - c[..., 1]))
            om = om + h * (wn**2 * (target - th) - 2.0 * zeta * wn * om)
            th = th + h * om
    final = {"angle": th, "velocity": om, "pressure": pr, "play": y, "creep": c}
    return rec, final


def simulate_memory_arm(seed: int, n: int, T: int, params: dict | None = None) -> dict[str, np.ndarray]:
    """``n`` sequences of ``T`` frames after a burn-in; pure function of its arguments.

    Returns float64 ``actions, obs, angle, velocity, pressure, hysteresis (n, T, 2)``,
    ``creep (n, T, 2, 2)`` and ``play (n, T, 2, n_play)``.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    rng = np.random.default_rng(seed)
    burn = int(p["burn_in"])
    u = memory_actions(rng, n, T + burn, p)
    rec, _ = rollout_memory_arm(u, initial_state(n, p), p)
    return drop_burn_in(rng, rec, u, burn, p["obs_noise"])


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays: dict[str, np.ndarray] = {}
    splits_meta = {}
    for split, (n, T, seed) in SPLITS.items():
        out = simulate_memory_arm(seed, n, T, p)
        arrays[f"{split}__obs"] = out["obs"].astype(np.float32)
        arrays[f"{split}__actions"] = out["actions"].astype(np.float32)
        arrays[f"{split}__hidden__hysteresis"] = out["hysteresis"].astype(np.float32)
        splits_meta[split] = {"n": n, "T": T, "seed": seed}
    meta = {
        "generator": {"name": "pgm_wm.datasets.memory_arm.simulate_memory_arm", "version": VERSION, "params": p},
        "splits": splits_meta,
        "dt": p["dt"],
        "units": {"obs": "rad", "actions": "valve command in [-1, 1]",
                  "hysteresis": "H (rad before the joint gain)"},
        "obs_names": ["theta1", "theta2"],
        "action_names": ["valve1", "valve2"],
        "target_names": [],
        "description": "Two pneumatic-muscle-like joints with long memory: Prandtl-Ishlinskii play "
                       "hysteresis (remembers the last large excursion) plus fast and slow creep "
                       "(overshoot and recovery over seconds); only noisy joint angles are observed.",
    }
    return arrays, meta

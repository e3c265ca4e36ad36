r"""Two joints driven by pneumatic-muscle-like actuators (chapter 4): a non-Markov system.

Each joint :math:`j \in \{1, 2\}` has angle :math:`\theta_j` (rad, 0 = hanging
down), velocity :math:`\omega_j`, a normalised pressure difference
:math:`p_j \in [-1, 1]` and a Bouc-Wen hysteresis state :math:`z_j` (rad). The
action :math:`u_j \in [-1, 1]` is a valve command, held constant over a frame.

Valve dead-zone:
:math:`v_j = \operatorname{sign}(u_j)\max(|u_j| - \delta, 0) / (1 - \delta)`.

Asymmetric pressure lag (fills fast, vents slowly):

.. math::

    \dot p_j = \frac{v_j - p_j}{\tau_j},\qquad
    \tau_j = \begin{cases}\tau_\text{fill} & (v_j - p_j)\,p_j \ge 0\\
    \tau_\text{vent} & \text{otherwise,}\end{cases}

integrated exactly over each substep, :math:`p \leftarrow v + (p - v)e^{-h/\tau}`.

Bouc-Wen hysteresis (exponent 1):
:math:`\dot z_j = A\,\omega_j - \beta\,|\omega_j|\,z_j - \gamma\,\omega_j\,|z_j|`,
bounded by :math:`|z_j| \le A / (\beta + \gamma)`.

Joint dynamics (diagonal inertia, coupled through gravity):

.. math::

    J_j \dot\omega_j = K_{m,j}\, p_j - k_s\theta_j - k_h z_j - b\,\omega_j
        - F_c \tanh(\omega_j/\varepsilon) - G_j(\theta) - L_j(\theta_j, \omega_j),

.. math::

    G_1 = g\,[m_1 c_1 \sin\theta_1 + m_2 (l_1\sin\theta_1 + c_2\sin(\theta_1+\theta_2))],\quad
    G_2 = g\, m_2 c_2 \sin(\theta_1 + \theta_2),

with soft limits :math:`L_j = k_\text{lim}\,\phi_j + b_\text{lim}\,\omega_j\,[\phi_j \ne 0]`,
:math:`\phi_j = \max(\theta_j - \theta_\text{lim}, 0) + \min(\theta_j + \theta_\text{lim}, 0)`.
Integration: semi-implicit Euler (:math:`\omega` first, then :math:`\theta`, then
:math:`z`) on ``n_substeps`` substeps per frame of ``dt``.

Actions: per joint a random multisine (3 sines, 0.1-1.2 Hz) plus random steps
(held 0.3-1.5 s), clipped to [-1, 1]. A burn-in of ``burn_in`` frames is
simulated and dropped so that sequences start mid-motion. Only the angles are
observed, with Gaussian noise of standard deviation ``obs_noise``; pressure,
hysteresis state and velocity are hidden.
"""

from __future__ import annotations

import numpy as np

from .signals import drop_burn_in, random_steps, sum_of_sines

__all__ = ["VERSION", "DEFAULT_PARAMS", "SPLITS", "hysteresis_actions", "initial_state", "rollout_hysteresis_arm",
           "simulate_hysteresis_arm", "generate"]

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    "dt": 0.02,            # s per frame
    "n_substeps": 10,
    "dead_zone": 0.1,      # valve dead-zone delta
    "tau_fill": 0.08,      # s
    "tau_vent": 0.25,      # s
    "K_m": [6.0, 4.8],     # N m at full pressure difference, per joint
    "k_s": 4.0,            # N m / rad, passive spring
    "k_h": 3.0,            # N m / rad, hysteretic stiffness
    "bw_A": 1.0,           # Bouc-Wen A
    "bw_beta": 4.0,        # Bouc-Wen beta (1/rad)
    "bw_gamma": 2.67,      # Bouc-Wen gamma (1/rad)
    "J": [0.05, 0.02],     # kg m^2
    "b": 0.3,              # N m s / rad
    "F_c": 0.3,            # N m, Coulomb friction
    "eps_friction": 0.05,  # rad/s, tanh smoothing of the Coulomb term
    "g": 9.81,
    "m": [0.8, 0.5],       # kg
    "l1": 0.3,             # m
    "c": [0.15, 0.15],     # m, centre-of-mass distances
    "theta_lim": 1.0,      # rad
    "k_lim": 50.0,         # N m / rad
    "b_lim": 1.0,          # N m s / rad
    "obs_noise": 0.0005,   # rad
    "burn_in": 50,         # frames simulated and dropped
    "n_sines": 3,
    "sine_freq": [0.1, 1.2],
    "sine_amp": [0.15, 0.4],
    "step_hold": [0.3, 1.5],
    "step_level": 0.6,
}

# split -> (n_sequences, T, seed)
SPLITS: dict[str, tuple[int, int, int]] = {
    "train": (192, 300, 4101),
    "valid": (32, 300, 4102),
    "test": (64, 300, 4103),
}


def hysteresis_actions(rng: np.random.Generator, n: int, T: int, p: dict) -> np.ndarray:
    """Valve commands ``(n, T, 2)`` in [-1, 1]: multisine plus random steps, clipped."""
    acts = []
    for _ in range(2):
        s = sum_of_sines(rng, n, T, p["dt"], p["n_sines"], tuple(p["sine_freq"]), tuple(p["sine_amp"]))
        s += random_steps(rng, n, T, p["dt"], tuple(p["step_hold"]), -p["step_level"], p["step_level"])
        acts.append(s)
    return np.clip(np.stack(acts, axis=-1), -1.0, 1.0)


def initial_state(n: int) -> dict[str, np.ndarray]:
    """All-zero state: ``angle, velocity, pressure, hysteresis (n, 2)``."""
    return {key: np.zeros((n, 2)) for key in ("angle", "velocity", "pressure", "hysteresis")}


def rollout_hysteresis_arm(u_all: np.ndarray, state: dict[str, np.ndarray], params: dict | None = None
                           ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Integrate the module's equations for valve commands ``u_all (n, T, 2)`` from ``state``.

    ``state``: ``angle, velocity, pressure, hysteresis (n, 2)`` (theta, omega, p, z),
    the full state of the arm. Returns ``(record, final_state)``: ``record`` holds the four
    states ``(n, T, 2)`` at the start of every frame, ``final_state`` the state after the
    last frame. Used by :func:`simulate_hysteresis_arm` and by the physics oracle
    (:mod:`pgm_wm.datasets.oracles`).
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    n, T, _ = u_all.shape
    k = int(p["n_substeps"])
    h = p["dt"] / k
    J = np.asarray(p["J"])
    m1, m2 = p["m"]
    c1, c2 = p["c"]
    g, l1 = p["g"], p["l1"]
    A, beta, gamma = p["bw_A"], p["bw_beta"], p["bw_gamma"]
    dz = p["dead_zone"]
    decay_fill = np.exp(-h / p["tau_fill"])
    decay_vent = np.exp(-h / p["tau_vent"])
    lim = p["theta_lim"]

    th = state["angle"].astype(np.float64, copy=True)
    om = state["velocity"].astype(np.float64, copy=True)
    pr = state["pressure"].astype(np.float64, copy=True)
    z = state["hysteresis"].astype(np.float64, copy=True)
    rec = {key: np.empty((n, T, 2)) for key in ("angle", "velocity", "pressure", "hysteresis")}
    for t in range(T):
        rec["angle"][:, t] = th
        rec["velocity"][:, t] = om
        rec["pressure"][:, t] = pr
        rec["hysteresis"][:, t] = z
        u = u_all[:, t]
        v = np.sign(u) * np.maximum(np.abs(u) - dz, 0.0) / (1.0 - dz)
        for _ in range(k):
            decay = np.where((v - pr) * pr >= 0.0, decay_fill, decay_vent)
            pr = v + (pr - v) * decay
            s12 = np.sin(th[:, 0] + th[:, 1])
            G = np.stack([g * (m1 * c1 * np.sin(th[:, 0]) + m2 * (l1 * np.sin(th[:, 0]) + c2 * s12)),
                          g * m2 * c2 * s12], axis=-1)
            phi = np.maximum(th - lim, 0.0) + np.minimum(th + lim, 0.0)
            L = p["k_lim"] * phi + p["b_lim"] * om * (phi != 0.0)
            torque = (np.asarray(p["K_m"]) * pr - p["k_s"] * th - p["k_h"] * z - p["b"] * om
                      - p["F_c"] * np.tanh(om / p["eps_friction"]) - G - L)
            om = om + h * torque / J
            th = th + h * om
            z = z + h * (A * om - beta * np.abs(om) * z - gamma * om * np.abs(z))
    return rec, {"angle": th, "velocity": om, "pressure": pr, "hysteresis": z}


def simulate_hysteresis_arm(seed: int, n: int, T: int, params: dict | None = None) -> dict[str, np.ndarray]:
    """Simulate ``n`` sequences of ``T`` frames; pure function of its arguments.

    Returns float64 arrays ``actions (n, T, 2)``, ``angle (n, T, 2)`` (noise-free),
    ``obs (n, T, 2)`` (noisy angles), ``velocity``, ``pressure``, ``hysteresis``
    (each ``(n, T, 2)``). ``actions[:, t]`` acts between frames ``t`` and ``t+1``.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    rng = np.random.default_rng(seed)
    burn = int(p["burn_in"])
    u_all = hysteresis_actions(rng, n, T + burn, p)
    rec, _ = rollout_hysteresis_arm(u_all, initial_state(n), p)
    return drop_burn_in(rng, rec, u_all, burn, p["obs_noise"])


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays: dict[str, np.ndarray] = {}
    splits_meta = {}
    for split, (n, T, seed) in SPLITS.items():
        out = simulate_hysteresis_arm(seed, n, T, p)
        arrays[f"{split}__obs"] = out["obs"].astype(np.float32)
        arrays[f"{split}__actions"] = out["actions"].astype(np.float32)
        for key in ("velocity", "pressure", "hysteresis"):
            arrays[f"{split}__hidden__{key}"] = out[key].astype(np.float32)
        splits_meta[split] = {"n": n, "T": T, "seed": seed}
    meta = {
        "generator": {"name": "pgm_wm.datasets.hysteresis_arm.simulate_hysteresis_arm",
                      "version": VERSION, "params": p},
        "splits": splits_meta,
        "dt": p["dt"],
        "units": {"obs": "rad", "actions": "valve command in [-1, 1]", "velocity": "rad/s",
                  "pressure": "normalised pressure difference", "hysteresis": "rad"},
        "obs_names": ["theta1", "theta2"],
        "action_names": ["valve1", "valve2"],
        "target_names": [],
        "hidden_names": {key: ["joint1", "joint2"] for key in ("velocity", "pressure", "hysteresis")},
        "description": "Two joints with pneumatic-muscle-like actuation (valve dead-zone, asymmetric "
                       "pressure lag, Bouc-Wen hysteresis, friction, gravity, soft limits); "
                       "only noisy joint angles are observed.",
    }
    return arrays, meta

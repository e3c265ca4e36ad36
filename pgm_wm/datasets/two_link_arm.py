r"""A PD-controlled planar 2-link arm carrying a tip payload (chapters 2, 5 and 6).

Joint angles :math:`q = (q_1, q_2)` (rad; :math:`q_1` from the horizontal,
:math:`q_2` relative to link 1), vertical plane, gravity along :math:`-y`.
Links: masses :math:`m_1, m_2`, lengths :math:`l_1, l_2`, uniform rods
(centre of mass at mid-length, inertia :math:`m l^2/12`); a point payload
:math:`m_p` at the tip of link 2; motor armature :math:`J_a` on each joint.
Link 2 plus payload has mass :math:`\bar m = m_2 + m_p`, centre of mass
:math:`\bar c = (m_2 l_2/2 + m_p l_2)/\bar m` and inertia about it
:math:`\bar I = m_2 l_2^2/12 + m_2 (l_2/2 - \bar c)^2 + m_p (l_2 - \bar c)^2`.

Rigid-body dynamics (Eq. (arm-dynamics)):

.. math::

    M(q)\,\ddot q + c(q, \dot q) + G(q) + b\,\dot q = \tau,

.. math::

    M_{11} = J_a + \tfrac{m_1 l_1^2}{3} + \bar I + \bar m (l_1^2 + \bar c^2 + 2 l_1 \bar c \cos q_2),\quad
    M_{12} = \bar I + \bar m(\bar c^2 + l_1 \bar c \cos q_2),\quad
    M_{22} = J_a + \bar I + \bar m \bar c^2,

.. math::

    c = \bar m\, l_1 \bar c \sin q_2 \begin{pmatrix} -\dot q_2 (2\dot q_1 + \dot q_2) \\ \dot q_1^2 \end{pmatrix},\quad
    G = g\begin{pmatrix} (m_1 l_1/2 + \bar m l_1)\cos q_1 + \bar m \bar c \cos(q_1 + q_2) \\
    \bar m \bar c \cos(q_1 + q_2)\end{pmatrix}.

Controller (Eq. (arm-pd)), evaluated once per frame and held over the frame
(zero-order hold), so the stored torque is exactly the torque applied:

.. math::

    \tau_t = K_p (r_t - q_t) - K_d \dot q_t + G_0(q_t) + \xi_t,

with :math:`r_t` the PD target (smoothed random waypoints), :math:`G_0` the
gravity of the arm *without* payload (so a payload makes the arm sag by about
:math:`K_p^{-1}` times its gravity torque) and :math:`\xi_t` Ornstein-Uhlenbeck
torque noise. Integration: semi-implicit Euler on ``n_substeps`` substeps
per frame. Observation: :math:`o_t = (q_t, \dot q_t) + \text{noise}`.

Both action options are returned: ``torque`` (:math:`\tau_t`, N m; the state
is Markov given :math:`(o_t, \tau_t, m_p)`) and ``pd_target`` (:math:`r_t`,
rad; the closed loop is stable, so long open-loop predictions are feasible).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .signals import lowpass, ou_process, random_steps

__all__ = [
    "VERSION",
    "DEFAULT_PARAMS",
    "arm_terms",
    "pd_targets",
    "simulate_two_link_arm",
    "rollout_two_link_arm",
    "SIM_SEED_OFFSET",
    "ARM_META",
    "arm_split_arrays",
    "arm_splits",
]

#: The simulation seed of a split is its schedule seed plus this offset.
SIM_SEED_OFFSET = 100_000

#: Metadata shared by the payload-arm datasets (observations and both action options).
ARM_META: dict = {
    "units": {"obs": "rad, rad, rad/s, rad/s", "pd_target": "rad", "torque": "N m", "payload": "kg"},
    "obs_names": ["q1", "q2", "qd1", "qd2"],
    "action_options": {"pd_target": ["q1_target", "q2_target"], "torque": ["tau1", "tau2"]},
    "default_action": "pd_target",
    "target_names": [],
}

VERSION = "1.0"

DEFAULT_PARAMS: dict = {
    "dt": 0.02,                 # s per frame (controller period)
    "n_substeps": 10,
    "m": [3.0, 2.0],            # kg, link masses
    "l": [0.5, 0.5],            # m, link lengths
    "armature": 0.1,            # kg m^2 per joint
    "g": 9.81,
    "b": 0.2,                   # N m s / rad, viscous joint friction
    "Kp": [60.0, 30.0],         # N m / rad
    "Kd": [10.0, 4.0],          # N m s / rad
    "torque_noise": 0.5,        # N m, stationary std of the OU torque noise
    "torque_noise_tau": 0.1,    # s
    "q_obs_noise": 0.001,       # rad
    "qd_obs_noise": 0.01,       # rad / s
    "target_low": [-0.6, -1.0],   # rad, waypoint range of (q1, q2)
    "target_high": [0.6, 1.0],
    "target_hold": [0.5, 1.5],  # s between waypoints
    "target_smoothing": 0.15,   # s, time constant of the two-stage low-pass
    "burn_in_s": 1.0,           # s simulated and dropped at the start
    "gravity_compensation": 1.0,  # factor on G_0 in the controller (0 switches it off)
}


def arm_terms(q: np.ndarray, qd: np.ndarray, payload: np.ndarray, p: dict) -> tuple[np.ndarray, ...]:
    """Entries of Eq. (arm-dynamics): ``M11, M12, M22, c1, c2, G1, G2``, each ``(n,)``.

    ``q, qd: (n, 2)``, ``payload: (n,)`` in kg (0 gives the nominal arm).
    """
    m1, m2 = p["m"]
    l1, l2 = p["l"]
    g = p["g"]
    mb = m2 + payload
    cb = (m2 * l2 / 2 + payload * l2) / mb
    Ib = m2 * l2**2 / 12 + m2 * (l2 / 2 - cb) ** 2 + payload * (l2 - cb) ** 2
    c2 = np.cos(q[:, 1])
    s2 = np.sin(q[:, 1])
    M11 = p["armature"] + m1 * l1**2 / 3 + Ib + mb * (l1**2 + cb**2 + 2 * l1 * cb * c2)
    M12 = Ib + mb * (cb**2 + l1 * cb * c2)
    M22 = p["armature"] + Ib + mb * cb**2
    hh = mb * l1 * cb * s2
    cor1 = -hh * qd[:, 1] * (2 * qd[:, 0] + qd[:, 1])
    cor2 = hh * qd[:, 0] ** 2
    c12 = np.cos(q[:, 0] + q[:, 1])
    G2 = g * mb * cb * c12
    G1 = g * (m1 * l1 / 2 + mb * l1) * np.cos(q[:, 0]) + G2
    return M11, M12, M22, cor1, cor2, G1, G2


def pd_targets(rng: np.random.Generator, n: int, T: int, p: dict) -> np.ndarray:
    """Smoothed random waypoints ``(n, T, 2)``: random steps, then a two-stage low-pass."""
    steps = random_steps(rng, n, T, p["dt"], tuple(p["target_hold"]),
                         np.asarray(p["target_low"]), np.asarray(p["target_high"]), d=2)
    return lowpass(steps, p["dt"], p["target_smoothing"], order=2, axis=1)


def simulate_two_link_arm(seed: int, payload: np.ndarray, params: dict | None = None) -> dict[str, np.ndarray]:
    """Simulate the closed loop for a payload schedule ``payload (n, T)`` in kg (pure function).

    ``payload[:, t]`` is the payload during frame ``t`` (from time ``t dt`` to
    ``(t+1) dt``); a burn-in of ``burn_in_s`` seconds with the first payload
    value is simulated and dropped. Returns float64 arrays ``obs (n, T, 4)``
    (noisy ``q1, q2, qd1, qd2``), ``state (n, T, 4)`` (noise-free),
    ``torque (n, T, 2)``, ``pd_target (n, T, 2)`` and ``torque_noise (n, T, 2)`` (the OU
    noise xi_t inside ``torque``); ``torque[:, t]`` and ``pd_target[:, t]`` act
    between frames ``t`` and ``t+1``.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    payload = np.asarray(payload, dtype=np.float64)
    if payload.ndim != 2:
        raise ValueError(f"payload: expected shape (n, T), got {payload.shape}")
    if (payload < 0).any():
        raise ValueError("payload: must be non-negative")
    n, T = payload.shape
    rng = np.random.default_rng(seed)
    dt = p["dt"]
    burn = int(round(p["burn_in_s"] / dt))
    Ttot = T + burn
    ref = pd_targets(rng, n, Ttot, p)
    noise = ou_process(rng, (n, Ttot, 2), dt, p["torque_noise_tau"], p["torque_noise"])
    mp_all = np.concatenate([np.repeat(payload[:, :1], burn, axis=1), payload], axis=1)
    start = np.stack([ref[:, 0, 0], ref[:, 0, 1], np.zeros(n), np.zeros(n)], axis=-1)
    state, torque = rollout_two_link_arm(start, ref, noise, mp_all, p)
    state = state[:, burn:]
    obs_noise = np.array([p["q_obs_noise"]] * 2 + [p["qd_obs_noise"]] * 2)
    obs = state + obs_noise * rng.standard_normal((n, T, 4))
    return {"obs": obs, "state": state, "torque": torque[:, burn:], "pd_target": ref[:, burn:],
            "torque_noise": noise[:, burn:]}


def rollout_two_link_arm(state0: np.ndarray, ref: np.ndarray, noise: np.ndarray, payload: np.ndarray,
                         params: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed loop of Eq. (arm-dynamics) and Eq. (arm-pd) from a given state (pure function).

    ``state0 (n, 4)`` = ``(q1, q2, qd1, qd2)`` at frame 0; ``ref (n, T, 2)`` PD targets,
    ``noise (n, T, 2)`` torque noise (zeros for a noise-free rollout), ``payload (n, T)``
    in kg, all per frame. Returns the states ``(n, T, 4)`` at the start of each frame
    and the torques ``(n, T, 2)`` applied during it. Used by :func:`simulate_two_link_arm`
    and by the physics oracles of the diagnostics (true vs nominal payload).
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    mp_all = np.asarray(payload, dtype=np.float64)
    n, Ttot = mp_all.shape
    Kp1, Kp2 = p["Kp"]
    Kd1, Kd2 = p["Kd"]
    bf = p["b"]
    g = p["g"]
    m1, m2 = p["m"]
    l1, l2 = p["l"]
    k = int(p["n_substeps"])
    h = p["dt"] / k
    # payload-dependent constants of Eq. (arm-dynamics), one value per frame: (n, Ttot)
    mb = m2 + mp_all
    cb = (m2 * l2 / 2 + mp_all * l2) / mb
    Ib = m2 * l2**2 / 12 + m2 * (l2 / 2 - cb) ** 2 + mp_all * (l2 - cb) ** 2
    a11 = p["armature"] + m1 * l1**2 / 3 + Ib + mb * (l1**2 + cb**2)   # M11 = a11 + 2 a12 cos q2
    a12 = mb * l1 * cb                                                 # M12 = a22 + a12 cos q2
    a22 = Ib + mb * cb**2                                              # M22 = armature + a22
    g1 = g * (m1 * l1 / 2 + mb * l1)
    g2 = g * mb * cb
    # nominal (payload-free) gravity constants for the controller's compensation
    g1n = p["gravity_compensation"] * g * (m1 * l1 / 2 + m2 * l1)
    g2n = p["gravity_compensation"] * g * m2 * l2 / 2
    q1 = state0[:, 0].astype(np.float64, copy=True)
    q2 = state0[:, 1].astype(np.float64, copy=True)
    w1 = state0[:, 2].astype(np.float64, copy=True)
    w2 = state0[:, 3].astype(np.float64, copy=True)
    state = np.empty((n, Ttot, 4))
    torque = np.empty((n, Ttot, 2))
    for t in range(Ttot):
        state[:, t] = np.stack([q1, q2, w1, w2], axis=-1)
        c12 = np.cos(q1 + q2)
        tau1 = Kp1 * (ref[:, t, 0] - q1) - Kd1 * w1 + g1n * np.cos(q1) + g2n * c12 + noise[:, t, 0]
        tau2 = Kp2 * (ref[:, t, 1] - q2) - Kd2 * w2 + g2n * c12 + noise[:, t, 1]
        torque[:, t, 0] = tau1
        torque[:, t, 1] = tau2
        A11, A12, A22, G1c, G2c = a11[:, t], a12[:, t], a22[:, t], g1[:, t], g2[:, t]
        M22 = p["armature"] + A22
        for _ in range(k):
            cq2 = np.cos(q2)
            hh = A12 * np.sin(q2)
            M11 = A11 + 2.0 * A12 * cq2
            M12 = A22 + A12 * cq2
            G2 = G2c * np.cos(q1 + q2)
            r1 = tau1 + hh * w2 * (2.0 * w1 + w2) - G1c * np.cos(q1) - G2 - bf * w1
            r2 = tau2 - hh * w1 * w1 - G2 - bf * w2
            det = M11 * M22 - M12 * M12
            w1 = w1 + h * (M22 * r1 - M12 * r2) / det
            w2 = w2 + h * (M11 * r2 - M12 * r1) / det
            q1 = q1 + h * w1
            q2 = q2 + h * w2
    return state, torque


def arm_split_arrays(split: str, seed: int, payload: np.ndarray, params: dict) -> tuple[dict[str, np.ndarray], dict]:
    """Simulate one split for ``payload (n, T)`` and name its arrays as the loader expects.

    Returns ``({"<split>__obs", "<split>__action_options__pd_target", ..._torque,
    "<split>__hidden__payload"}: float32, split metadata {n, T, seed, sim_seed})``; the
    simulation seed is ``seed + SIM_SEED_OFFSET``.
    """
    out = simulate_two_link_arm(seed + SIM_SEED_OFFSET, payload, params)
    arrays = {f"{split}__obs": out["obs"].astype(np.float32),
              f"{split}__action_options__pd_target": out["pd_target"].astype(np.float32),
              f"{split}__action_options__torque": out["torque"].astype(np.float32),
              f"{split}__hidden__payload": np.asarray(payload).astype(np.float32)}
    n, T = payload.shape
    return arrays, {"n": n, "T": T, "seed": seed, "sim_seed": seed + SIM_SEED_OFFSET}


def arm_splits(seeds: dict[str, int], schedule: Callable[[str, dict], dict[str, np.ndarray]], params: dict
               ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
    """All splits of a payload-arm dataset: :func:`arm_split_arrays` of ``schedule(split, params)["payload"]``.

    ``seeds``: ``{split: schedule seed}`` in file order; ``params``: the dataset's parameters
    (the arm's entries of :data:`DEFAULT_PARAMS` are passed to the simulator). Returns
    ``(arrays, {split: split metadata})``.
    """
    arm_p = {key: params[key] for key in DEFAULT_PARAMS}
    arrays: dict[str, np.ndarray] = {}
    splits_meta: dict[str, dict] = {}
    for split, seed in seeds.items():
        split_arrays, splits_meta[split] = arm_split_arrays(split, seed, schedule(split, params)["payload"], arm_p)
        arrays.update(split_arrays)
    return arrays, splits_meta

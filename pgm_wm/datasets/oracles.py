r"""Physics oracles: the true simulator, started from the true state, predicting the evaluation windows.

Issue 12 asks every results table on simulated data for two reference rows, "the physics
oracle with true and with nominal parameters". :func:`oracle_windows` gives both, on exactly
the windows the experiment runner scores (:func:`pgm_wm.evaluation.sliding_windows`, then only
windows in which every step is valid):

- the split is re-simulated from the seed and parameters stored in the file (the generators
  are pure functions; the re-simulation is checked against the file's observations and
  actions), which gives the simulator's **full** state at every frame: angles and velocities,
  and for ``memory_arm`` the pressures, play-operator and creep states, for ``hysteresis_arm``
  the pressures and the Bouc-Wen state;
- in window :math:`w` starting at :math:`s_w` the simulator starts from the true state at
  frame :math:`t_0 = s_w + c - 1` (:math:`c` = ``context_len``), applies the recorded
  actions :math:`a_{t_0}, \dots, a_{t_0 + H - 2}` open loop and returns the noise-free
  observations :math:`\hat o_{t_0 + k}`, :math:`k = 1, \dots, H` (``horizon`` :math:`H`),
  i.e. the same steps as the :math:`k`-step-ahead predictions of Eq. (acrkn-multistep);
- the arms driven by PD targets (``payload_arm``, ``drift_arm``, ``hidden_payload_arm``,
  ``slow_payload_arm``) get no torque noise :math:`\xi_t` in Eq. (arm-pd) (a model cannot
  know it; ``replay_noise=True`` replays the generator's own noise, a check under which the
  oracle reproduces the noise-free trajectory exactly).

Parameters (``params``):

- ``"true"``: each sequence's true payload schedule over the window (constant per sequence,
  switching, drifting, or the tank filled by the recorded pump actions);
- ``"nominal"``: a constant payload, everything else identical: ``meta["nominal_payload"]``
  where the dataset documents one (``hidden_payload_arm``: 1.5 kg, the middle of its range),
  else the mean training-split payload (``payload_arm``, ``drift_arm``, ``slow_payload_arm``;
  the "training-mean payload" of data/README.md);
- ``memory_arm`` and ``hysteresis_arm`` have no per-sequence parameter (every sequence uses
  the documented parameters), so ``"nominal"`` equals ``"true"`` there.

``target`` is the recorded (noisy) observation at the predicted steps, so
``((mean - target) ** 2).mean()`` is the oracle's mean squared error including the
observation noise, in original units, as the runner scores the models.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from . import drift_arm, hidden_payload_arm, payload_arm, slow_payload_arm
from .hysteresis_arm import rollout_hysteresis_arm, simulate_hysteresis_arm
from .loader import SPLITS, load
from .sequences import SequenceData
from .memory_arm import rollout_memory_arm, simulate_memory_arm
from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import rollout_two_link_arm, simulate_two_link_arm

__all__ = ["ORACLE_DATASETS", "PARAMS_OPTIONS", "oracle_windows", "window_starts"]

#: Datasets with a physics oracle.
ORACLE_DATASETS: tuple[str, ...] = ("memory_arm", "hidden_payload_arm", "slow_payload_arm",
                                    "hysteresis_arm", "payload_arm", "drift_arm")
PARAMS_OPTIONS: tuple[str, ...] = ("true", "nominal")

_ARM_SCHEDULES: dict[str, Callable[[str, dict], dict[str, np.ndarray]]] = {
    "hidden_payload_arm": hidden_payload_arm.split_schedule,
    "payload_arm": payload_arm.split_schedule,
    "drift_arm": drift_arm.split_schedule,
    "slow_payload_arm": slow_payload_arm.split_schedule,
}

# (name, split) -> re-simulated split (pure functions of the stored seeds and parameters)
_SIM_CACHE: dict[tuple[str, str], dict[str, Any]] = {}


def _check_int(argname: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{argname}: must be an int >= {low}, got {value!r}")
    return int(value)


def window_starts(valid: np.ndarray | Tensor, length: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Sequence index and start of every fully valid window, in :func:`sliding_windows` order.

    ``valid (n, T)`` bool; windows of ``length`` steps start at ``0, stride, 2 stride, ...``
    while ``start + length <= T``, all windows of sequence 0 first. Returns ``(seq, start)``,
    each ``(W,)`` int, for the windows in which every step is valid.
    """
    v = np.asarray(valid.cpu() if isinstance(valid, Tensor) else valid, dtype=bool)
    if v.ndim != 2:
        raise ValueError(f"valid: expected shape (n, T), got {v.shape}")
    length = _check_int("length", length, 1)
    stride = _check_int("stride", stride, 1)
    n, T = v.shape
    if length > T:
        raise ValueError(f"length: must be <= T = {T}, got {length}")
    starts = np.arange(0, T - length + 1, stride)
    ok = np.stack([v[:, s:s + length].all(1) for s in starts], axis=1)   # (n, n_starts)
    seq, j = np.nonzero(ok)                                              # row-major: sequence 0 first
    return seq, starts[j]


def _check_reproduced(name: str, what: str, regenerated: np.ndarray, stored: Tensor) -> None:
    stored_np = stored.double().numpy()
    if regenerated.shape != stored_np.shape or not np.allclose(regenerated, stored_np, rtol=1e-5, atol=1e-5):
        raise RuntimeError(f"name: re-simulating {name!r} does not reproduce the stored {what}; "
                           "the generator and data/ disagree (python -m pgm_wm.datasets check)")


def _simulate(name: str, split: str, data: SequenceData) -> dict[str, Any]:
    """Re-simulate a split: full states per frame plus what the rollouts need (cached)."""
    key = (name, split)
    if key in _SIM_CACHE:
        return _SIM_CACHE[key]
    p = data.meta["generator"]["params"]
    seed = int(data.meta["split_info"]["seed"])
    n, T = data.obs.shape[:2]
    if name in ("memory_arm", "hysteresis_arm"):
        simulate = simulate_memory_arm if name == "memory_arm" else simulate_hysteresis_arm
        out = simulate(seed, n, T, p)
        _check_reproduced(name, "observations", out["obs"], data.obs)
        _check_reproduced(name, "actions", out["actions"], data.actions)
        keys = ("angle", "velocity", "pressure", "play", "creep") if name == "memory_arm" else \
            ("angle", "velocity", "pressure", "hysteresis")
        sim = {"kind": "valve", "state": {k: out[k] for k in keys}, "actions": out["actions"],
               "clean": out["angle"], "params": p}
    else:
        sched = _ARM_SCHEDULES[name](split, p)
        arm_p = {k: p[k] for k in ARM_PARAMS}
        out = simulate_two_link_arm(int(data.meta["split_info"]["sim_seed"]), sched["payload"], arm_p)
        d_obs = data.obs.shape[-1]
        _check_reproduced(name, "observations", out["obs"][..., :d_obs], data.obs)
        _check_reproduced(name, "payload", sched["payload"], data.hidden["payload"])
        train_payload = load(name, "train").hidden["payload"].double().numpy()
        nominal = float(data.meta.get("nominal_payload", train_payload.mean()))
        sim = {"kind": "arm", "state": out["state"], "ref": out["pd_target"], "noise": out["torque_noise"],
               "payload": sched["payload"], "nominal": nominal, "clean": out["state"][..., :d_obs],
               "params": arm_p, "d_obs": d_obs}
    _SIM_CACHE[key] = sim
    return sim


def _rollout(sim: dict[str, Any], name: str, seq: np.ndarray, t0: np.ndarray, horizon: int, params: str,
             replay_noise: bool) -> np.ndarray:
    """Noise-free observations at frames ``t0 + 1 .. t0 + horizon`` from the true state at ``t0``: ``(W, H, d)``."""
    steps = t0[:, None] + np.arange(horizon)[None, :]          # frames whose action is applied: (W, H)
    if sim["kind"] == "valve":
        state0 = {k: v[seq, t0] for k, v in sim["state"].items()}
        u = sim["actions"][seq[:, None], steps]
        rollout = rollout_memory_arm if name == "memory_arm" else rollout_hysteresis_arm
        rec, final = rollout(u, state0, sim["params"])
        return np.concatenate([rec["angle"][:, 1:], final["angle"][:, None]], axis=1)
    # two-link arm: record H + 1 frames (states at t0 .. t0 + H), keep t0 + 1 .. t0 + H
    frames = np.concatenate([steps, steps[:, -1:] + 1], axis=1)
    ref = sim["ref"][seq[:, None], frames]
    noise = sim["noise"][seq[:, None], frames] if replay_noise else np.zeros_like(ref)
    if params == "true":
        mp = sim["payload"][seq[:, None], frames]
    else:
        mp = np.full(frames.shape, sim["nominal"])
    state, _ = rollout_two_link_arm(sim["state"][seq, t0], ref, noise, mp, sim["params"])
    return state[:, 1:, :sim["d_obs"]]


def oracle_windows(name: str, split: str, context_len: int, horizon: int, stride: int, params: str = "true",
                   *, dtype: torch.dtype = torch.float32, replay_noise: bool = False) -> tuple[Tensor, Tensor]:
    r"""The physics oracle's open-loop predictions on the runner's evaluation windows (original units).

    Windows of ``context_len + horizon`` steps start every ``stride`` steps in each sequence
    of ``load(name, split)`` (all windows of sequence 0 first, as
    :func:`pgm_wm.evaluation.sliding_windows`), keeping those in which every step is valid
    (:func:`window_starts`). In each, the true simulator starts from the true full state at
    window step ``context_len - 1`` and applies the recorded actions open loop (see the
    module docstring); index ``k - 1`` is the :math:`k`-step-ahead prediction, as in
    Eq. (acrkn-multistep).

    Args:
        name: one of :data:`ORACLE_DATASETS`.
        split: a split of ``name`` (``SPLITS[name]``).
        context_len, horizon, stride: positive ints with ``context_len + horizon <= T``.
        params: ``"true"`` (each sequence's true payload schedule) or ``"nominal"`` (the
            documented nominal / training-mean payload; identical to ``"true"`` for
            ``memory_arm`` and ``hysteresis_arm``, which have no per-sequence parameter).
        dtype: floating dtype of the returned tensors (the simulation runs in float64).
        replay_noise: replay the generator's torque noise (PD-driven arms only; a check:
            ``mean`` then equals the noise-free simulated trajectory). Default ``False``.

    Returns:
        ``(mean, target)``, each ``(W, horizon, d_obs)``: the oracle's noise-free
        observations and the recorded observations at window steps
        ``context_len .. context_len + horizon - 1``.

    Raises:
        ValueError: unknown ``name``, ``split`` or ``params``, or a bad ``context_len``,
            ``horizon``, ``stride`` or ``dtype`` (the message starts with the argument's name).
        RuntimeError: the re-simulation does not reproduce the stored data.
    """
    if name not in ORACLE_DATASETS:
        raise ValueError(f"name: no physics oracle for {name!r}; valid names: {', '.join(ORACLE_DATASETS)}")
    if split not in SPLITS[name]:
        raise ValueError(f"split: {name!r} has no split {split!r}; valid splits: {', '.join(SPLITS[name])}")
    if params not in PARAMS_OPTIONS:
        raise ValueError(f"params: expected one of {', '.join(PARAMS_OPTIONS)}, got {params!r}")
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating torch dtype, got {dtype!r}")
    context_len = _check_int("context_len", context_len, 1)
    horizon = _check_int("horizon", horizon, 1)
    stride = _check_int("stride", stride, 1)
    data = load(name, split)
    n, T, d_obs = data.obs.shape
    if context_len + horizon > T:
        raise ValueError(f"horizon: context_len + horizon = {context_len + horizon} exceeds the "
                         f"sequence length T = {T}")
    seq, start = window_starts(data.valid, context_len + horizon, stride)
    if len(seq) == 0:
        empty = torch.zeros(0, horizon, d_obs, dtype=dtype)
        return empty, empty.clone()
    sim = _simulate(name, split, data)
    t0 = start + context_len - 1
    mean = _rollout(sim, name, seq, t0, horizon, params, replay_noise)
    steps = t0[:, None] + 1 + np.arange(horizon)[None, :]
    target = data.obs.double().numpy()[seq[:, None], steps]
    return torch.from_numpy(mean).to(dtype), torch.from_numpy(target).to(dtype)

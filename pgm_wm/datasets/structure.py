"""Structure diagnostics of the chapter-4/5/6 datasets with the structure (issue 12): each shows, with
a cheap, seeded estimator fitted on ``train`` and scored on ``valid``, that the phenomenon the
chapter's model targets is in the data at the horizons it is evaluated on.

- :func:`memory_checks` (``memory_arm``, ch. 4): runs with different pasts and the same future
  actions stay apart for seconds, and predictors of the angle 25 and 50 steps ahead gain from a
  1-s history over a 0.2-s one;
- :func:`hidden_payload_checks` (``hidden_payload_arm``, ch. 5): a physics oracle with the true
  payload beats one with the nominal payload, and a physics identifier cannot read the payload
  from the first steps of the target window but can from a context of previous steps;
- :func:`slow_payload_checks` (``slow_payload_arm``, ch. 6): the payload's autocorrelation at
  1/2/4/8 s, its predictability 8 s ahead given the pump actions, and what knowing it is worth
  to a physics oracle over the 8-s horizon.

``python -m pgm_wm.datasets report`` prints them (the numbers quoted in ``data/README.md``).
"""

from __future__ import annotations

import numpy as np

from .regression import ridge_rmse
from .loader import SequenceData, load
from .memory_arm import initial_state, memory_actions, rollout_memory_arm
from .two_link_arm import DEFAULT_PARAMS as ARM_PARAMS
from .two_link_arm import rollout_two_link_arm, simulate_two_link_arm

__all__ = ["random_feature_rmse", "memory_checks", "hidden_payload_checks", "slow_payload_checks"]


def random_feature_rmse(X: np.ndarray, Y: np.ndarray, X_test: np.ndarray, Y_test: np.ndarray,
                        n_features: int = 1500, lam: float = 1e-3, seed: int = 0) -> float:
    r"""Test RMSE of ridge regression on fixed random ReLU features (a seeded nonlinear regressor).

    Features of the standardised input ``z``: :math:`[\max(0, z W + b), z]` with
    :math:`W_{ij} \sim N(0, 1/p)`, :math:`b_j \sim U(-1, 1)`; then :func:`ridge_rmse`.
    """
    mu, sd = X.mean(0), X.std(0) + 1e-9
    rng = np.random.default_rng(seed)
    W = rng.standard_normal((X.shape[1], n_features)) / np.sqrt(X.shape[1])
    b = rng.uniform(-1.0, 1.0, n_features)

    def feats(A: np.ndarray) -> np.ndarray:
        Z = (A - mu) / sd
        return np.c_[np.maximum(Z @ W + b, 0.0), Z]

    return ridge_rmse(feats(X), Y, feats(X_test), Y_test, lam=lam)


def _history_pairs(data: SequenceData, frames: int, every: int, horizon: int, start: int = 100,
                   stride: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Features: angles and actions of the last ``frames`` frames (every ``every``-th), all actions
    up to ``t + horizon - 1``; target ``obs[t + horizon] - obs[t]``."""
    o = data.obs.double().numpy()
    a = data.actions.double().numpy()
    n = len(o)
    X, Y = [], []
    for t in range(start, o.shape[1] - horizon, stride):
        past = slice(t - frames + 1, t + 1)
        X.append(np.concatenate([o[:, past][:, ::-1][:, ::every].reshape(n, -1),
                                 a[:, past][:, ::-1][:, ::every].reshape(n, -1),
                                 a[:, t + 1:t + horizon].reshape(n, -1)], 1))
        Y.append(o[:, t + horizon] - o[:, t])
    return np.concatenate(X), np.concatenate(Y)


def memory_checks(train: SequenceData | None = None, valid: SequenceData | None = None,
                  horizons: tuple[int, ...] = (25, 50), seed: int = 0) -> dict[str, float]:
    """``memory_arm``: how long the past matters (rad).

    Keys: ``divergence_<s>s`` (mean absolute angle difference of 64 pairs of runs with
    different 3-s pasts and the same future actions, at 0, 0.5, 1 and 2 s);
    ``linear_h<h>_short`` / ``_long`` and ``rf_h<h>_short`` / ``_long`` (validation RMSE of
    ridge and random-feature ridge predictors of the angle ``h`` steps ahead from a 0.2-s
    history of angles and actions (10 frames) or a 1-s one (50 frames, every 5th), plus
    the actions up to ``t + h - 1``).
    """
    train = load("memory_arm", "train") if train is None else train
    valid = load("memory_arm", "valid") if valid is None else valid
    p = train.meta["generator"]["params"]
    rng = np.random.default_rng(seed)
    n, past, future = 64, 150, 101
    states = []
    for _ in range(2):
        _, final = rollout_memory_arm(memory_actions(rng, n, past, p), initial_state(n, p), p)
        states.append(final)
    u = memory_actions(rng, n, future, p)
    a, b = (rollout_memory_arm(u, s, p)[0]["angle"] for s in states)
    gap = np.abs(a - b).mean(axis=(0, 2))
    out = {f"divergence_{t * p['dt']:g}s": float(gap[t]) for t in (0, 25, 50, 100)}
    for h in horizons:
        for label, frames, every in (("short", 10, 1), ("long", 50, 5)):
            pairs = (_history_pairs(train, frames, every, h, stride=4)
                     + _history_pairs(valid, frames, every, h, stride=4))
            out[f"linear_h{h}_{label}"] = ridge_rmse(*pairs, lam=1e-4)
            out[f"rf_h{h}_{label}"] = random_feature_rmse(*pairs, n_features=1000)
    return out


def _arm_states(data: SequenceData) -> np.ndarray:
    """Noise-free states ``(n, T, 4)`` of a simulated arm split, re-simulated from its stored seed."""
    p = data.meta["generator"]["params"]
    payload = data.hidden["payload"].double().numpy()
    return simulate_two_link_arm(data.meta["split_info"]["sim_seed"], payload, {k: p[k] for k in ARM_PARAMS})["state"]


def hidden_payload_checks(valid: SequenceData | None = None, window: int = 25,
                          grid_step: float = 0.1) -> dict[str, float]:
    """``hidden_payload_arm``: the payload matters, and a short window does not reveal it.

    Keys: ``oracle_true`` / ``oracle_nominal`` / ``repeat_last`` (RMSE in rad of the angles
    over each ``window``-step window, predicted open loop from the true state at its start
    with the true PD targets and no noise, with the true payload or the nominal
    ``meta["nominal_payload"]``; or by repeating the first angle); ``identify_<part>_rmse``
    and ``_r2`` (a physics identifier: the payload on a grid that best predicts the next
    observed velocities from the observed states and PD targets, using the target window's
    first 5 or 12 transitions, or the previous 25 or 50 as context).
    """
    valid = load("hidden_payload_arm", "valid") if valid is None else valid
    p = valid.meta["generator"]["params"]
    state = _arm_states(valid)
    obs = valid.obs.double().numpy()
    ref = (valid.actions if valid.meta["action"] == "pd_target" else valid.hidden["pd_target"]).double().numpy()
    payload = valid.hidden["payload"][:, 0].double().numpy()
    n, T, _ = obs.shape
    starts = list(range(2 * window, T - window + 1, window))
    sq = {"oracle_true": [], "oracle_nominal": [], "repeat_last": []}
    zero = np.zeros((n, window, 2))
    for t0 in starts:
        truth = state[:, t0 + 1:t0 + window, :2]
        for key, mp in (("oracle_true", payload), ("oracle_nominal", np.full(n, valid.meta["nominal_payload"]))):
            x, _ = rollout_two_link_arm(state[:, t0], ref[:, t0:t0 + window], zero, np.repeat(mp[:, None], window, 1), p)
            sq[key].append((x[:, 1:, :2] - truth) ** 2)
        sq["repeat_last"].append((state[:, t0:t0 + 1, :2] - truth) ** 2)
    out = {key: float(np.sqrt(np.mean(val))) for key, val in sq.items()}
    grid = np.arange(0.0, 3.0 + 1e-9, grid_step)
    for part, (lo, hi) in {"target5": (0, 5), "target12": (0, 12), "context25": (-25, 0),
                           "context50": (-50, 0)}.items():
        errs = []
        for t0 in starts:
            ts = np.arange(t0 + lo, t0 + hi)
            s0 = obs[:, ts].reshape(-1, 4)
            r = np.repeat(ref[:, ts].reshape(-1, 1, 2), 2, axis=1)
            loss = []
            for mp in grid:
                x, _ = rollout_two_link_arm(s0, r, np.zeros_like(r), np.full((len(s0), 2), mp), p)
                loss.append(((x[:, 1, 2:] - obs[:, ts + 1].reshape(-1, 4)[:, 2:]) ** 2).sum(-1).reshape(n, -1).sum(1))
            errs.append(grid[np.argmin(np.stack(loss), 0)] - payload)
        mse = float(np.mean(np.square(errs)))
        out[f"identify_{part}_rmse"] = float(np.sqrt(mse))
        out[f"identify_{part}_r2"] = 1.0 - mse / float(payload.var())
    return out


def slow_payload_checks(train: SequenceData | None = None, valid: SequenceData | None = None,
                        horizon_s: float = 8.0) -> dict[str, float]:
    """``slow_payload_arm``: the slow factor stays predictable across the horizon, and it matters.

    Keys: ``autocorr_<s>s`` (correlation of the payload with itself ``s`` = 1, 2, 4, 8 s later,
    pooled over the training episodes); ``predict8s_r2_no_actions`` / ``_with_pump`` (R² on
    valid of ridge predictors of the payload 8 s ahead from its current value, without or
    with the sum of the pump commands in between, quadratic features); ``oracle8s_true`` /
    ``oracle8s_frozen`` / ``oracle8s_nominal`` (RMSE in rad of the angles over 8-s open-loop
    rollouts from the true state with the true PD targets and no noise, with the true payload
    schedule, the payload frozen at its value at the start, or the training-mean payload).
    """
    train = load("slow_payload_arm", "train") if train is None else train
    valid = load("slow_payload_arm", "valid") if valid is None else valid
    p = train.meta["generator"]["params"]
    dt = p["dt"]
    m = train.hidden["payload"].double().numpy()
    out = {}
    for s in (1, 2, 4, 8):
        lag = int(round(s / dt))
        out[f"autocorr_{s}s"] = float(np.corrcoef(m[:, :-lag].ravel(), m[:, lag:].ravel())[0, 1])
    L = int(round(horizon_s / dt))

    def pairs(data: SequenceData, with_pump: bool) -> tuple[np.ndarray, np.ndarray]:
        mp = data.hidden["payload"].double().numpy()
        pump = data.actions[..., 2].double().numpy()
        X, Y = [], []
        for t in range(0, mp.shape[1] - L, 10):
            f = [mp[:, t], mp[:, t] ** 2]
            if with_pump:
                u = pump[:, t:t + L].sum(1) * dt
                f += [u, u ** 2, u * mp[:, t]]
            X.append(np.stack(f, 1))
            Y.append(mp[:, t + L])
        return np.concatenate(X), np.concatenate(Y)[:, None]

    var = float(pairs(valid, False)[1].var())
    for label, with_pump in (("no_actions", False), ("with_pump", True)):
        rmse = ridge_rmse(*pairs(train, with_pump), *pairs(valid, with_pump), lam=1e-8)
        out[f"predict8s_r2_{label}"] = 1.0 - rmse ** 2 / var
    state = _arm_states(valid)
    ref = valid.actions[..., :2].double().numpy()
    mp = valid.hidden["payload"].double().numpy()
    nominal = float(m.mean())
    sq = {"oracle8s_true": [], "oracle8s_frozen": [], "oracle8s_nominal": []}
    n = len(state)
    zero = np.zeros((n, L, 2))
    for t0 in range(100, state.shape[1] - L, 300):
        truth = state[:, t0 + 1:t0 + L, :2]
        for key, sched in (("oracle8s_true", mp[:, t0:t0 + L]),
                           ("oracle8s_frozen", np.repeat(mp[:, t0:t0 + 1], L, 1)),
                           ("oracle8s_nominal", np.full((n, L), nominal))):
            x, _ = rollout_two_link_arm(state[:, t0], ref[:, t0:t0 + L], zero, sched, p)
            sq[key].append((x[:, 1:, :2] - truth) ** 2)
    out.update({key: float(np.sqrt(np.mean(val))) for key, val in sq.items()})
    return out


def report() -> None:
    """Print the three structure diagnostics (the numbers quoted in ``data/README.md``)."""
    for name, fn in (("memory_arm", memory_checks), ("hidden_payload_arm", hidden_payload_checks),
                     ("slow_payload_arm", slow_payload_checks)):
        print(f"{name}:")
        for key, val in fn().items():
            print(f"  {key:28s} {val:.4f}")

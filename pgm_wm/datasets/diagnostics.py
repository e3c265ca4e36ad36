"""Quick linear checks that the datasets show what their chapters need (``python -m pgm_wm.datasets report``).

- :func:`hysteresis_checks`: on ``hysteresis_arm``, ridge regressions of the
  future angle on a window of past angles and actions. If the angles were a
  Markov state (given the action), two past frames would predict the next one
  as well as ten; and if future actions did not matter, knowing them would not
  improve a 25-step (0.5 s) prediction.
- :func:`payload_probe`: on ``payload_arm``, a ridge probe that reads the
  payload from the average of quadratic features of a random *set* of ``k``
  transitions ``(o_t, a_t, o_{t+1} - o_t)`` of one sequence; its error shrinks
  as the set grows (the posterior-narrowing of chapter 2).

Linear probes are deliberately weak: they give lower bounds on how much the
history, the future actions or the context carry.
"""

from __future__ import annotations

import numpy as np

from .loader import SequenceData, load
from .regression import ridge_rmse

__all__ = ["ridge_rmse", "history_windows", "hysteresis_checks", "context_features", "payload_probe", "report"]


def history_windows(
    data: SequenceData, k: int, horizon: int, n_future: int,
    extra: tuple[str, ...] = (), start: int = 20, stride: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Regression pairs from every ``stride``-th time ``t``.

    Features: ``obs[t-k+1 .. t]``, ``actions[t-k+1 .. t+n_future]`` and
    ``hidden[key][t]`` for ``key`` in ``extra``; target ``obs[t+horizon] - obs[t]``.
    Returns ``X (N, p)``, ``Y (N, d_obs)``.
    """
    obs = data.obs.double().numpy()
    act = data.actions.double().numpy()
    n = obs.shape[0]
    X, Y = [], []
    for t in range(max(start, k - 1), obs.shape[1] - max(horizon, n_future + 1), stride):
        feats = [obs[:, t - k + 1:t + 1].reshape(n, -1), act[:, t - k + 1:t + 1 + n_future].reshape(n, -1)]
        feats += [data.hidden[key][:, t].double().numpy().reshape(n, -1) for key in extra]
        X.append(np.concatenate(feats, 1))
        Y.append(obs[:, t + horizon] - obs[:, t])
    return np.concatenate(X), np.concatenate(Y)


def hysteresis_checks(train: SequenceData | None = None, test: SequenceData | None = None) -> dict[str, float]:
    """Test RMSEs (rad) of ridge predictors on ``hysteresis_arm``.

    Keys: ``one_step_k2`` / ``one_step_k10`` (next angle from 2 / 10 past angles
    and actions), ``one_step_k2_true_state`` (2 frames plus the hidden velocity,
    pressure and hysteresis state), ``h25_without_future`` / ``h25_with_future``
    (angle 25 frames ahead from 10 past frames, without / with the 24 actions in between).
    """
    train = load("hysteresis_arm", "train") if train is None else train
    test = load("hysteresis_arm", "test") if test is None else test

    def rmse(k: int, horizon: int, n_future: int, extra: tuple[str, ...] = ()) -> float:
        return ridge_rmse(*history_windows(train, k, horizon, n_future, extra, stride=3),
                          *history_windows(test, k, horizon, n_future, extra, stride=3))

    return {
        "one_step_k2": rmse(2, 1, 0),
        "one_step_k10": rmse(10, 1, 0),
        "one_step_k2_true_state": rmse(2, 1, 0, ("velocity", "pressure", "hysteresis")),
        "h25_without_future": rmse(10, 25, 0),
        "h25_with_future": rmse(10, 25, 24),
    }


def context_features(data: SequenceData, k: int, rng: np.random.Generator) -> np.ndarray:
    """Set summary ``(n, p)``: mean over ``k`` random transitions of linear + quadratic features.

    Each transition ``(o_t, a_t, o_{t+1} - o_t)`` is standardised with the
    training statistics; the mean over the set is permutation invariant.
    """
    s = data.stats
    mu = np.r_[s["obs_mean"], s["act_mean"], s["diff_mean"]].astype(np.float64)
    sd = np.r_[s["obs_std"], s["act_std"], s["diff_std"]].astype(np.float64)
    o = data.obs.double().numpy()
    a = data.actions.double().numpy()
    n, T = o.shape[:2]
    idx = np.stack([rng.choice(T - 1, k, replace=False) for _ in range(n)])
    rows = np.arange(n)[:, None]
    x = (np.concatenate([o[rows, idx], a[rows, idx], o[rows, idx + 1] - o[rows, idx]], -1) - mu) / sd
    iu = np.triu_indices(x.shape[-1])
    quad = (x[..., :, None] * x[..., None, :])[..., iu[0], iu[1]]
    return np.concatenate([x, quad], -1).mean(1)


def payload_probe(sizes: tuple[int, ...] = (1, 3, 10, 50), action: str = "torque",
                  train: SequenceData | None = None, test: SequenceData | None = None,
                  repeats: int = 3) -> dict[int, float]:
    """Test RMSE (kg) of a ridge probe reading the payload from ``k`` transitions, per ``k``."""
    train = load("payload_arm", "train", action=action) if train is None else train
    test = load("payload_arm", "test", action=action) if test is None else test
    y = train.hidden["payload"][:, 0].double().numpy()
    y_test = test.hidden["payload"][:, 0].double().numpy()
    out = {}
    for k in sizes:
        rng = np.random.default_rng(k)
        X = np.concatenate([context_features(train, k, rng) for _ in range(repeats)])
        out[k] = ridge_rmse(X, np.tile(y, repeats), context_features(test, k, rng), y_test, lam=1e-3)
    return out


def report() -> None:
    """Print the checks above (used for the numbers in ``data/README.md``)."""
    h = hysteresis_checks()
    print("hysteresis_arm, ridge test RMSE (rad):")
    for key, val in h.items():
        print(f"  {key:24s} {val:.5f}")
    print(f"  history helps (k=2 / k=10):            {h['one_step_k2'] / h['one_step_k10']:.2f}x")
    print(f"  hidden state helps (k=2 / true state): {h['one_step_k2'] / h['one_step_k2_true_state']:.2f}x")
    print(f"  future actions help at 25 steps:       {h['h25_without_future'] / h['h25_with_future']:.2f}x")
    test_std = float(load("payload_arm", "test").hidden["payload"][:, 0].std())
    for action in ("torque", "pd_target"):
        probe = payload_probe(action=action)
        print(f"payload_arm ({action}), payload probe test RMSE (kg; std of test payloads {test_std:.3f}):")
        for k, val in probe.items():
            print(f"  {k:3d} transitions ({k * 0.02:.2f} s of data): {val:.3f}")

r"""Acting with a world model (Chapter 7): control as inference, sampling planners, closed loops.

Design note
-----------
Three layers, each usable on its own and each tested against an independent reference.

1. **Exact: LQR as inference** (float64, no sampling). A linear model
   :math:`x_{t+1} = Ax_t + Bu_t + c` with the quadratic cost Eq. (plan-cost) is solved by the
   backward Riccati recursion Eq. (plan-riccati). Read as messages, the cost-to-go
   :math:`V_t` defines :math:`\beta_t(x) \propto \exp(-\tfrac12 V_t(x))`, a Gaussian in
   information form (precision :math:`P_t`, information vector :math:`p_t`, Eq. plan-message);
   one backward step multiplies in the stage cost (a pseudo-observation of the reference with
   precision :math:`Q`) and eliminates the action by a Schur complement, which is the
   chapter-1 conditioning formula Eq. (gauss-condition) applied to precisions instead of
   covariances. Two readings are implemented with the package's own Kalman code:
   :func:`riccati_by_kalman` (Kalman's duality, Eq. plan-duality: the Riccati recursion *is*
   the covariance recursion of a Kalman filter with :math:`F = A^\top, H = B^\top`, run
   backwards in time) and :func:`lqr_by_smoothing` (control as inference, Eq. plan-cai: the
   optimal trajectory *is* the RTS-smoothed mean of a linear-Gaussian model in which the
   actions are the process noise and the reference is observed). :func:`arx_state_space`
   turns a fitted :class:`~pgm_wm.baselines.LinearARX` into the state-space form
   Eq. (plan-arx-state) so the same LQR plans through a learned linear model.
2. **Sampling planner** (torch, batched over candidates): :class:`SamplingPlanner` runs CEM
   (Eq. plan-cem) or MPPI (Eq. plan-mppi) over action sequences of length :math:`H`,
   scoring every candidate in one call of a *predictor*
   ``predict(obs_history, action_history, candidates) -> (mean, var)`` of the future
   observations with the cost Eq. (plan-expected-cost) (tracking + action + ``risk`` times the
   predicted variance). :func:`world_model_predictor` adapts any model with the package's
   world-model interface ``model(obs, actions, mask) -> (mean, var)`` through
   :func:`pgm_wm.evaluation.multistep_predict` (history observed, future masked), so a planner
   sees exactly the open-loop predictions the earlier chapters score.
3. **Closed loop against the true simulator**: :func:`closed_loop` plans, applies the first
   action to the *simulator*, observes and replans (Eq. plan-closed-loop); the model is never
   used to score the outcome. :class:`TwoLinkArmEnv` and :class:`MemoryArmEnv` wrap
   :func:`~pgm_wm.datasets.two_link_arm.rollout_two_link_arm` and
   :func:`~pgm_wm.datasets.memory_arm.rollout_memory_arm` without changing their numerics
   (stepping equals one rollout, tested); :func:`simulator_predictor` makes the true
   simulator a predictor (the upper reference row), :class:`ConstantPolicy` and
   :class:`RandomPolicy` the lower ones. Only a predictor marked ``needs_state`` (the
   simulator) ever receives the simulator's true state; model predictors see observations
   and actions only.

Multi-seed intervals of closed-loop results (success rates, costs, paired ratios) come from
:mod:`pgm_wm.experiments.stats` applied to ``(seeds, tasks)`` arrays of the per-run numbers
returned here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Mapping, Protocol, Sequence

import numpy as np
import torch
from torch import Tensor

from ._checks import as_tensor, check_finite, check_spd
from .beliefs import Gaussian
from .kalman import kalman_filter, kf_predict, kf_update, rts_smoother

__all__ = [
    # 1. LQR as inference
    "LQRSolution",
    "lqr_backward",
    "lqr_rollout",
    "lqr_cost",
    "lqr_infinite_horizon",
    "riccati_by_kalman",
    "lqr_by_smoothing",
    "DUALITY_MAP",
    # learned linear model
    "ARXStateSpace",
    "arx_state_space",
    "arx_lqr",
    "ARXLQRPolicy",
    # 2. sampling planner
    "Predictor",
    "QuadraticCost",
    "PlanResult",
    "SamplingPlanner",
    "world_model_predictor",
    "linear_predictor",
    "ensemble_predictor",
    # 3. closed loop
    "Env",
    "LinearEnv",
    "TwoLinkArmEnv",
    "MemoryArmEnv",
    "simulator_predictor",
    "ConstantPolicy",
    "RandomPolicy",
    "warm_up",
    "ClosedLoopResult",
    "closed_loop",
    "plan_prediction_errors",
    "command_statistics",
]


# =============================================================================================
# Input helpers
# =============================================================================================


def _as_float(name: str, x: object, dtype: torch.dtype | None = None) -> Tensor:
    """A finite float32/float64 tensor (:func:`pgm_wm._checks.as_tensor`); arrays, lists and numbers
    become float64, tensors keep their dtype unless ``dtype`` is given."""
    if not isinstance(x, Tensor):
        try:
            x = np.asarray(x, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{name}: cannot be converted to a float array ({err})") from err
    t = as_tensor(name, x, dtype)
    if t.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name}: dtype {t.dtype} is not supported; use float32 or float64")
    return check_finite(name, t)


def _shape(name: str, x: Tensor, shape: tuple[int, ...]) -> Tensor:
    if tuple(x.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(x.shape)}")
    return x


def _pos_int(name: str, x: object, low: int = 1) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or int(x) < low:
        raise ValueError(f"{name}: must be an int >= {low}, got {x!r}")
    return int(x)


def _per_step(name: str, x: object, steps: int, dim: int, dtype: torch.dtype) -> Tensor:
    """``(dim,)`` broadcast to ``(steps, dim)``, or exactly ``(steps, dim)``."""
    t = _as_float(name, x, dtype)
    if t.ndim == 1 and t.shape[0] == dim:
        return t.expand(steps, dim)
    return _shape(name, t, (steps, dim))


def _history(obs_history: object, action_history: object, do: int | None, da: int,
             dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``obs_history: (C, do)`` (C >= 1) and ``action_history: (C - 1, da)`` (may be empty), finite."""
    obs = _as_float("obs_history", obs_history, dtype)
    if obs.ndim != 2 or obs.shape[0] < 1 or (do is not None and obs.shape[1] != do):
        raise ValueError(f"obs_history: expected (C, {do or 'do'}) with C >= 1, got {tuple(obs.shape)}")
    act = _as_float("action_history", action_history, dtype)
    if act.numel() == 0:
        act = act.reshape(0, da)
    return obs, _shape("action_history", act, (obs.shape[0] - 1, da))


def _sym(m: Tensor) -> Tensor:
    return 0.5 * (m + m.transpose(-1, -2))


# =============================================================================================
# 1. LQR as inference
# =============================================================================================


@dataclass(frozen=True)
class LQRSolution:
    r"""The backward pass of Eq. (plan-riccati) over a horizon of :math:`N` steps.

    Attributes:
        K: ``(N, m, n)`` feedback gains and ``k: (N, m)`` feedforward terms of the optimal policy
            :math:`u_t = -K_t x_t + k_t` (Eq. plan-gain).
        P: ``(N + 1, n, n)``, ``p: (N + 1, n)``, ``s: (N + 1,)``: the optimal cost-to-go
            :math:`V_t(x) = x^\top P_t x - 2 p_t^\top x + s_t` (Eq. plan-value), i.e. the backward
            message :math:`\beta_t(x)\propto\exp(-\tfrac12 V_t(x))` with precision :math:`P_t` and
            information vector :math:`p_t` (Eq. plan-message).
        S: ``(N, m, m)``: :math:`S_t = R + B^\top P_{t+1} B`, the curvature of the cost in
            :math:`u_t` (the dual of the Kalman filter's innovation covariance).
    """

    K: Tensor
    k: Tensor
    P: Tensor
    p: Tensor
    s: Tensor
    S: Tensor

    @property
    def horizon(self) -> int:
        return self.K.shape[0]

    def value(self, x: Tensor, t: int = 0) -> Tensor:
        r""":math:`V_t(x) = x^\top P_t x - 2p_t^\top x + s_t` for ``x: (..., n)``."""
        P, p = self.P[t], self.p[t]
        return (x @ P * x).sum(-1) - 2.0 * (x * p).sum(-1) + self.s[t]

    def action(self, x: Tensor, t: int = 0) -> Tensor:
        r""":math:`u_t = -K_t x + k_t` for ``x: (..., n)`` -> ``(..., m)``."""
        return -(x @ self.K[t].transpose(-1, -2)) + self.k[t]


def _check_lqr_model(A: object, B: object, Q: object, R: object, Q_f: object | None,
                     c: object | None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    A = _as_float("A", A)
    dtype = A.dtype
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"A: expected a square matrix (n, n), got shape {tuple(A.shape)}")
    n = A.shape[0]
    B = _as_float("B", B, dtype)
    if B.ndim != 2 or B.shape[0] != n or B.shape[1] < 1:
        raise ValueError(f"B: expected shape ({n}, m) with m >= 1, got {tuple(B.shape)}")
    m = B.shape[1]
    Q = _shape("Q", _as_float("Q", Q, dtype), (n, n))
    check_spd("Q", Q, semidefinite=True)
    R = _shape("R", _as_float("R", R, dtype), (m, m))
    check_spd("R", R)
    Q_f = Q if Q_f is None else _shape("Q_f", _as_float("Q_f", Q_f, dtype), (n, n))
    check_spd("Q_f", Q_f, semidefinite=True)
    c = torch.zeros(n, dtype=dtype) if c is None else _shape("c", _as_float("c", c, dtype), (n,))
    return A, B, _sym(Q), _sym(R), _sym(Q_f), c


def _riccati_step(P: Tensor, p: Tensor, s: Tensor, A: Tensor, B: Tensor, Q: Tensor, R: Tensor,
                  c: Tensor, r: Tensor) -> tuple[Tensor, ...]:
    r"""One backward step of Eq. (plan-riccati) from :math:`(P_{t+1}, p_{t+1}, s_{t+1})`.

    With :math:`g = p_{t+1} - P_{t+1}c` and :math:`S = R + B^\top P_{t+1} B`:
    :math:`K = S^{-1}B^\top P_{t+1}A`, :math:`k = S^{-1}B^\top g`,
    :math:`P_t = Q + A^\top P_{t+1}A - K^\top S K`, :math:`p_t = Q r_t + (A - BK)^\top g`,
    :math:`s_t = r_t^\top Q r_t + s_{t+1} + c^\top P_{t+1}c - 2p_{t+1}^\top c - k^\top S k`.
    Returns ``(P_t, p_t, s_t, K, k, S)``.
    """
    g = p - P @ c
    PB = P @ B
    S = _sym(R + B.T @ PB)
    K = torch.linalg.solve(S, PB.T @ A)
    k = torch.linalg.solve(S, B.T @ g)
    P_new = _sym(Q + A.T @ P @ A - K.T @ S @ K)
    p_new = Q @ r + (A - B @ K).T @ g
    s_new = r @ Q @ r + s + c @ P @ c - 2.0 * (p @ c) - k @ S @ k
    return P_new, p_new, s_new, K, k, S


def lqr_backward(A: object, B: object, Q: object, R: object, horizon: int, Q_f: object | None = None,
                 c: object | None = None, ref: object | None = None) -> LQRSolution:
    r"""Finite-horizon LQR by the backward Riccati recursion, Eqs. (plan-cost)–(plan-riccati).

    Problem (Eq. plan-cost): dynamics :math:`x_{t+1} = Ax_t + Bu_t + c`, cost

    .. math:: J = \sum_{t=0}^{N-1}\big[(x_t - r_t)^\top Q (x_t - r_t) + u_t^\top R u_t\big]
              + (x_N - r_N)^\top Q_f (x_N - r_N).

    Bellman (Eq. plan-bellman): :math:`V_N(x) = (x - r_N)^\top Q_f(x - r_N)`,
    :math:`V_t(x) = \min_u\,[(x - r_t)^\top Q(x - r_t) + u^\top R u + V_{t+1}(Ax + Bu + c)]`.
    Every :math:`V_t` is quadratic, :math:`V_t(x) = x^\top P_t x - 2p_t^\top x + s_t`
    (Eq. plan-value), and the minimizer is affine, :math:`u_t = -K_t x + k_t` (Eq. plan-gain),
    with the recursion of :func:`_riccati_step` (Eq. plan-riccati):

    .. math:: S_t = R + B^\top P_{t+1}B,\quad K_t = S_t^{-1}B^\top P_{t+1}A,\quad
              P_t = Q + A^\top P_{t+1}A - A^\top P_{t+1}B\,S_t^{-1}B^\top P_{t+1}A .

    As messages (Eq. plan-message): :math:`\beta_t(x)\propto e^{-V_t(x)/2}` has precision
    :math:`P_t` and information vector :math:`p_t`. The step multiplies
    :math:`\beta_{t+1}(Ax + Bu + c)` by the action factor :math:`e^{-u^\top Ru/2}` (a joint
    Gaussian in :math:`(x, u)` with precision
    :math:`\left[\begin{smallmatrix}A^\top P A & A^\top P B\\ B^\top P A & R + B^\top P B\end{smallmatrix}\right]`),
    eliminates :math:`u` (maximizing or integrating give the same precision: the Schur
    complement, which is Eq. (gauss-condition) with precisions in place of covariances), and
    multiplies in the stage factor :math:`e^{-(x - r_t)^\top Q (x - r_t)/2}`, a
    pseudo-observation of :math:`r_t` with precision :math:`Q`.

    Args:
        A: ``(n, n)``; B: ``(n, m)``; Q: ``(n, n)`` positive semi-definite; R: ``(m, m)``
            positive definite; Q_f: ``(n, n)`` positive semi-definite (default ``Q``);
            c: ``(n,)`` constant drift (default 0); ref: ``(n,)`` or ``(N + 1, n)`` reference
            :math:`r_t` (default 0). Tensors keep their dtype (use float64); arrays become float64.
        horizon: :math:`N \ge 1`.

    Returns an :class:`LQRSolution`.
    """
    A, B, Q, R, Q_f, c = _check_lqr_model(A, B, Q, R, Q_f, c)
    N = _pos_int("horizon", horizon)
    n = A.shape[0]
    r = torch.zeros(N + 1, n, dtype=A.dtype) if ref is None else _per_step("ref", ref, N + 1, n, A.dtype)
    P, p = Q_f, Q_f @ r[N]
    s = r[N] @ Q_f @ r[N]
    Ps, ps, ss, Ks, ks, Ss = [P], [p], [s], [], [], []
    for t in range(N - 1, -1, -1):
        P, p, s, K, k, S = _riccati_step(P, p, s, A, B, Q, R, c, r[t])
        Ps.append(P), ps.append(p), ss.append(s), Ks.append(K), ks.append(k), Ss.append(S)
    rev = lambda xs: torch.stack(xs[::-1])  # noqa: E731 - built backwards, stored forwards
    return LQRSolution(rev(Ks), rev(ks), rev(Ps), rev(ps), rev(ss), rev(Ss))


def lqr_rollout(solution: LQRSolution, A: object, B: object, x0: object, c: object | None = None,
                action_low: object | None = None, action_high: object | None = None) -> tuple[Tensor, Tensor]:
    r"""Run the policy :math:`u_t = -K_t x_t + k_t` (Eq. plan-gain) through :math:`x_{t+1} = Ax_t + Bu_t + c`.

    Returns ``(x: (N + 1, n), u: (N, m))``. Optional bounds clip each action (then the result is
    the clipped LQR policy, not the constrained optimum).
    """
    if not isinstance(solution, LQRSolution):
        raise ValueError(f"solution: expected an LQRSolution, got {type(solution).__name__}")
    m, n = solution.K.shape[1:]
    dtype = solution.K.dtype
    A = _shape("A", _as_float("A", A, dtype), (n, n))
    B = _shape("B", _as_float("B", B, dtype), (n, m))
    x = _shape("x0", _as_float("x0", x0, dtype), (n,))
    c = torch.zeros(n, dtype=dtype) if c is None else _shape("c", _as_float("c", c, dtype), (n,))
    low, high = _check_bounds(action_low, action_high, m, dtype)
    xs, us = [x], []
    for t in range(solution.horizon):
        u = torch.minimum(torch.maximum(solution.action(x, t), low), high)
        x = A @ x + B @ u + c
        xs.append(x), us.append(u)
    return torch.stack(xs), torch.stack(us)


def lqr_cost(x: object, u: object, Q: object, R: object, Q_f: object | None = None,
             ref: object | None = None) -> Tensor:
    r"""The cost Eq. (plan-cost) of a trajectory ``x: (..., N + 1, n)``, ``u: (..., N, m)`` -> ``(...)``."""
    x = _as_float("x", x)
    dtype = x.dtype
    u = _as_float("u", u, dtype)
    if x.ndim < 2 or u.ndim < 2 or x.shape[-2] != u.shape[-2] + 1:
        raise ValueError(f"u: expected (..., N, m) with x (..., N + 1, n), got x {tuple(x.shape)}, "
                         f"u {tuple(u.shape)}")
    N, n, m = u.shape[-2], x.shape[-1], u.shape[-1]
    Q = _shape("Q", _as_float("Q", Q, dtype), (n, n))
    R = _shape("R", _as_float("R", R, dtype), (m, m))
    Q_f = Q if Q_f is None else _shape("Q_f", _as_float("Q_f", Q_f, dtype), (n, n))
    r = torch.zeros(N + 1, n, dtype=dtype) if ref is None else _per_step("ref", ref, N + 1, n, dtype)
    e = x - r
    stage = (e[..., :-1, :] @ Q * e[..., :-1, :]).sum((-1, -2)) + (u @ R * u).sum((-1, -2))
    return stage + (e[..., -1, :] @ Q_f * e[..., -1, :]).sum(-1)


def lqr_infinite_horizon(A: object, B: object, Q: object, R: object, tol: float = 1e-12,
                         max_iter: int = 100_000) -> tuple[Tensor, Tensor]:
    r"""Stationary LQR: iterate Eq. (plan-riccati) (no drift, no reference) to its fixed point.

    The limit :math:`P = Q + A^\top PA - A^\top PB(R + B^\top PB)^{-1}B^\top PA` is the
    discrete algebraic Riccati equation (Eq. plan-dare); returns ``(P, K)`` with
    :math:`K = (R + B^\top PB)^{-1}B^\top PA`. Stops when
    :math:`\|P_t - P_{t+1}\|_\infty \le \text{tol}\,(1 + \|P_t\|_\infty)`; raises
    ``ValueError`` naming ``A`` if it does not converge in ``max_iter`` steps (an
    unstabilizable pair).
    """
    A, B, Q, R, _, c = _check_lqr_model(A, B, Q, R, None, None)
    if not tol > 0:
        raise ValueError(f"tol: must be > 0, got {tol}")
    _pos_int("max_iter", max_iter)
    r = torch.zeros_like(c)
    P, p, s = Q, r, torch.zeros((), dtype=A.dtype)
    for _ in range(max_iter):
        P_new, _, _, K, _, _ = _riccati_step(P, p, s, A, B, Q, R, c, r)
        if not bool(torch.isfinite(P_new).all()):
            break
        if float((P_new - P).abs().max()) <= tol * (1.0 + float(P_new.abs().max())):
            return P_new, K
        P = P_new
    raise ValueError(f"A: the Riccati recursion diverged or did not converge in {max_iter} steps "
                     "(is (A, B) stabilizable?)")


#: Kalman's duality, term by term (Eq. plan-duality): LQR quantity -> Kalman-filter quantity.
DUALITY_MAP: dict[str, str] = {
    "time t = N, N-1, ..., 0 (backwards)": "filter step k = N - t = 0, 1, ..., N (forwards)",
    "A (dynamics)": "F = A^T (transition)",
    "B (input matrix)": "H = B^T (observation matrix)",
    "Q (state cost)": "Q = Q (process-noise covariance)",
    "R (action cost)": "R = R (observation-noise covariance)",
    "Q_f (terminal cost)": "Sigma_0 = Q_f (prior covariance of the first state)",
    "P_t (value matrix)": "Sigma^-_{N-t} (prior covariance)",
    "S_t = R + B^T P_{t+1} B (curvature in u)": "S = H Sigma^- H^T + R (innovation covariance)",
    "K_t = S_t^{-1} B^T P_{t+1} A (feedback gain)": "K_t = L^T A with L = Sigma^- H^T S^{-1} (Kalman gain)",
    "eliminate u_t (min over the action)": "update (condition on an observation)",
    "pull back through A, add the stage cost Q": "predict (propagate through F, add process noise)",
}


def riccati_by_kalman(A: object, B: object, Q: object, R: object, horizon: int,
                      Q_f: object | None = None) -> Tensor:
    r"""The LQR value matrices :math:`P_0..P_N` computed by a Kalman filter: Kalman's duality, Eq. (plan-duality).

    Run the covariance recursion of a Kalman filter with transition :math:`F = A^\top`,
    observation matrix :math:`H = B^\top`, process noise :math:`Q`, observation noise
    :math:`R` and prior covariance :math:`\Sigma^-_0 = Q_f` for :math:`N` steps, each an
    update (:func:`pgm_wm.kalman.kf_update`, Eq. kf-update) followed by a predict
    (:func:`pgm_wm.kalman.kf_predict`, Eq. kf-predict):

    .. math:: \Sigma^-_{k+1} = A^\top\big(\Sigma^-_k - \Sigma^-_k B(B^\top\Sigma^-_k B + R)^{-1}B^\top\Sigma^-_k\big)A + Q .

    This is Eq. (plan-riccati) with :math:`\Sigma^-_k = P_{N-k}`: the filter runs forwards in
    its own time while the LQR runs backwards (see :data:`DUALITY_MAP`). The covariances do not
    depend on the observed values, so the observations are zeros. Returns ``P: (N + 1, n, n)``
    ordered like :attr:`LQRSolution.P` (``P[t]`` = :math:`\Sigma^-_{N-t}`).
    """
    A, B, Q, R, Q_f, _ = _check_lqr_model(A, B, Q, R, Q_f, None)
    N = _pos_int("horizon", horizon)
    n, m = B.shape
    F, H = A.T.contiguous(), B.T.contiguous()
    y = torch.zeros(m, dtype=A.dtype)
    prior = Gaussian(torch.zeros(n, dtype=A.dtype), Q_f)
    covs = [prior.cov]
    for _ in range(N):
        post, _ = kf_update(prior, H, R, y)
        prior = kf_predict(post, F, Q)
        covs.append(prior.cov)
    return torch.stack(covs[::-1])


def lqr_by_smoothing(A: object, B: object, Q: object, R: object, x0: object, horizon: int,
                     c: object | None = None, ref: object | None = None,
                     init_var: float = 1e-10) -> tuple[Tensor, Tensor]:
    r"""Control as inference: the LQR trajectory as the RTS-smoothed mean of a linear-Gaussian model, Eq. (plan-cai).

    Write :math:`e^{-J/2}` (Eq. plan-cost with :math:`Q_f = Q`) as a probabilistic model: the
    actions are a priori :math:`u_t\sim\mathcal N(0, R^{-1})`, the dynamics are the
    deterministic :math:`x_{t+1} = Ax_t + Bu_t + c`, and the references are *observations*
    :math:`r_t = x_t + v_t`, :math:`v_t\sim\mathcal N(0, Q^{-1})`. The joint density is
    proportional to :math:`e^{-J/2}`, so the posterior mode (= mean, the posterior is Gaussian)
    of :math:`(x, u)` given all references is the LQR optimum. In state-space form with
    :math:`z_t = (x_t, u_t)`:

    .. math:: z_{t+1} = \begin{bmatrix}A & B\\ 0 & 0\end{bmatrix} z_t
              + \begin{bmatrix}c\\ 0\end{bmatrix} + w_t,\quad
              w_t\sim\mathcal N\Big(0, \begin{bmatrix}0 & 0\\ 0 & R^{-1}\end{bmatrix}\Big),\qquad
              r_t = [I\;\,0]\,z_t + v_t,

    filtered by :func:`pgm_wm.kalman.kalman_filter` and smoothed by
    :func:`pgm_wm.kalman.rts_smoother` (Eq. rts). Term by term: the filter's prior
    :math:`u_t\sim\mathcal N(0,R^{-1})` is the action cost, its observation noise
    :math:`Q^{-1}` the inverse tracking weight, the backward RTS pass the backward Riccati
    pass, and the smoothed mean the optimal trajectory.

    The known start :math:`x_0` is a prior with variance ``init_var`` (the filter needs a
    positive-definite prior covariance); the means differ from the exact LQR trajectory by
    :math:`O(\text{init\_var})` and by round-off of order machine epsilon / ``init_var``, so
    use float64 (the default for arrays). ``Q`` must be positive definite here.

    Returns ``(x: (N + 1, n), u: (N, m))``, comparable with :func:`lqr_rollout`.
    """
    A, B, Q, R, _, c = _check_lqr_model(A, B, Q, R, None, c)
    check_spd("Q", Q)
    N = _pos_int("horizon", horizon)
    if not init_var > 0:
        raise ValueError(f"init_var: must be > 0, got {init_var}")
    dtype = A.dtype
    n, m = B.shape
    x0 = _shape("x0", _as_float("x0", x0, dtype), (n,))
    r = torch.zeros(N + 1, n, dtype=dtype) if ref is None else _per_step("ref", ref, N + 1, n, dtype)
    d = n + m
    F = torch.zeros(d, d, dtype=dtype)
    F[:n, :n], F[:n, n:] = A, B
    W = torch.zeros(d, d, dtype=dtype)
    R_inv = _sym(torch.linalg.inv(R))
    W[n:, n:] = R_inv
    H = torch.cat([torch.eye(n, dtype=dtype), torch.zeros(n, m, dtype=dtype)], 1)
    obs_noise = _sym(torch.linalg.inv(Q))
    init_cov = torch.zeros(d, d, dtype=dtype)
    init_cov[:n, :n] = init_var * torch.eye(n, dtype=dtype)
    init_cov[n:, n:] = R_inv
    init = Gaussian(torch.cat([x0, torch.zeros(m, dtype=dtype)]), init_cov)
    drift_in = torch.cat([torch.eye(n, dtype=dtype), torch.zeros(m, n, dtype=dtype)], 0)
    mask = torch.ones(N + 1, dtype=torch.bool)
    mask[0] = False  # the cost of x_0 is a constant: nothing to observe there
    result = kalman_filter(r, init, F, H, W, obs_noise, mask, drift_in, c.expand(N + 1, n))
    smoothed = rts_smoother(result, F, W)
    return smoothed.mean[:, :n], smoothed.mean[:N, n:]


# ---------------------------------------------------------------------------------------------
# A learned linear model: the ARX baseline in state-space form
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ARXStateSpace:
    r"""A :class:`~pgm_wm.baselines.LinearARX` of order :math:`p` as :math:`s_{t+1} = A s_t + B a_t + c`, Eq. (plan-arx-state).

    State :math:`s_t = [o_t, o_{t-1}, \dots, o_{t-p+1}, a_{t-1}, \dots, a_{t-p+1}]` of size
    :math:`n = p\,d_o + (p-1)\,d_a`; the first :math:`d_o` entries are the observation
    (``obs_slice``). Attributes ``A: (n, n)``, ``B: (n, da)``, ``c: (n,)``, ``order``,
    ``obs_dim``, ``action_dim``.
    """

    A: Tensor
    B: Tensor
    c: Tensor
    order: int
    obs_dim: int
    action_dim: int

    @property
    def obs_slice(self) -> slice:
        return slice(0, self.obs_dim)

    def state(self, obs_history: object, action_history: object) -> Tensor:
        r"""The state :math:`s_t` at the last step of a history: ``obs_history: (C, do)`` with
        :math:`C \ge p`, ``action_history: (C - 1, da)`` (the actions between those
        observations; only the last :math:`p - 1` are used). Returns ``(n,)``."""
        dtype = self.A.dtype
        o = _as_float("obs_history", obs_history, dtype)
        if o.ndim != 2 or o.shape[1] != self.obs_dim or o.shape[0] < self.order:
            raise ValueError(f"obs_history: expected (C, {self.obs_dim}) with C >= order = {self.order}, "
                             f"got {tuple(o.shape)}")
        a = _shape("action_history", _as_float("action_history", action_history, dtype),
                   (o.shape[0] - 1, self.action_dim))
        p = self.order
        parts = [o[-1 - i] for i in range(p)] + [a[-i] for i in range(1, p)]
        return torch.cat(parts)


def arx_state_space(model: Any) -> ARXStateSpace:
    r"""Augmented state-space form of a fitted linear ARX model, Eq. (plan-arx-state).

    The ARX predicts :math:`\hat o_{t+1} = c + \sum_{i<p} A_i o_{t-i} + \sum_{i<p} B_i a_{t-i}`
    (:class:`~pgm_wm.baselines.LinearARX`, its ``weight`` acting on
    :math:`[o_t..o_{t-p+1}, a_t..a_{t-p+1}]`). Stacking the lags,

    .. math:: s_{t+1} = \underbrace{\begin{bmatrix} A_0\cdots A_{p-1} & B_1\cdots B_{p-1}\\
              \text{shift of } o & 0\\ 0 & \text{shift of } a\end{bmatrix}}_{A} s_t
              + \underbrace{\begin{bmatrix}B_0\\ 0\\ I\\ 0\end{bmatrix}}_{B} a_t
              + \begin{bmatrix}c\\ 0\end{bmatrix},

    where the identity block writes :math:`a_t` into the first action lag of :math:`s_{t+1}`.
    Float64 is used when the model is float32 (the LQR is an exact computation).
    """
    for attr in ("weight", "bias", "order", "obs_dim", "action_dim"):
        if not hasattr(model, attr):
            raise ValueError(f"model: expected a LinearARX-like model with .{attr}, got {type(model).__name__}")
    p, do, da = int(model.order), int(model.obs_dim), int(model.action_dim)
    if da < 1:
        raise ValueError("model: needs at least one action dimension to plan with")
    W = model.weight.detach().to(torch.float64)
    c0 = model.bias.detach().to(torch.float64)
    if tuple(W.shape) != (do, p * (do + da)):
        raise ValueError(f"model: weight has shape {tuple(W.shape)}, expected {(do, p * (do + da))}")
    n = p * do + (p - 1) * da
    A = torch.zeros(n, n, dtype=torch.float64)
    B = torch.zeros(n, da, dtype=torch.float64)
    c = torch.zeros(n, dtype=torch.float64)
    Wo, Wa = W[:, :p * do], W[:, p * do:]
    A[:do, :p * do] = Wo
    A[:do, p * do:] = Wa[:, da:]                  # B_1 .. B_{p-1} act on the stored action lags
    B[:do] = Wa[:, :da]                           # B_0 acts on the new action
    c[:do] = c0
    for i in range(1, p):                         # o_{t-i+1} moves to lag i
        A[i * do:(i + 1) * do, (i - 1) * do:i * do] = torch.eye(do, dtype=torch.float64)
    if p > 1:
        off = p * do
        B[off:off + da] = torch.eye(da, dtype=torch.float64)      # a_t -> first action lag
        for j in range(1, p - 1):                                 # a_{t-j} -> lag j + 1
            A[off + j * da:off + (j + 1) * da, off + (j - 1) * da:off + j * da] = torch.eye(da, dtype=torch.float64)
    return ARXStateSpace(A, B, c, p, do, da)


def _obs_cost_matrices(ss: ARXStateSpace, obs_weight: object, action_weight: object, target: object,
                       horizon: int) -> tuple[Tensor, Tensor, Tensor]:
    """``Q`` on the observation block of the augmented state, ``R``, and the reference ``(H + 1, n)``."""
    n, do, da = ss.A.shape[0], ss.obs_dim, ss.action_dim
    w = _weight_matrix("obs_weight", obs_weight, do)
    Q = torch.zeros(n, n, dtype=torch.float64)
    Q[:do, :do] = w
    R = _weight_matrix("action_weight", action_weight, da)
    r_obs = _per_step("target", target, horizon + 1, do, torch.float64)
    ref = torch.zeros(horizon + 1, n, dtype=torch.float64)
    ref[:, :do] = r_obs
    return Q, R, ref


def _weight_matrix(name: str, w: object, d: int) -> Tensor:
    """A weight given as ``(d,)`` (diagonal) or ``(d, d)`` -> ``(d, d)`` float64, PSD."""
    t = _as_float(name, w, torch.float64)
    if t.ndim == 1 and t.shape[0] == d:
        if bool((t < 0).any()):
            raise ValueError(f"{name}: weights must be >= 0")
        return torch.diag(t)
    _shape(name, t, (d, d))
    check_spd(name, t, semidefinite=True)
    return _sym(t)


def arx_lqr(model: Any, obs_history: object, action_history: object, target: object, obs_weight: object,
            action_weight: object, horizon: int) -> tuple[Tensor, LQRSolution]:
    r"""Plan through a fitted linear ARX model with the exact LQR (Eqs. plan-arx-state, plan-riccati).

    Cost: :math:`\sum_{k=1}^{H} (\hat o_k - r_k)^\top W (\hat o_k - r_k) + \sum_{k=0}^{H-1} a_k^\top R a_k`
    (the cost of :class:`QuadraticCost` with ``risk = 0``; the current observation's term is a
    constant), i.e. Eq. (plan-cost) on the augmented state with :math:`Q = Q_f =
    \mathrm{blockdiag}(W, 0)`. ``target``: ``(do,)`` or ``(H, do)`` (the targets of
    :math:`o_1..o_H`); weights ``(d,)`` (diagonal) or ``(d, d)``. ``R`` must be positive definite.
    Returns ``(actions: (H, da), solution)``: the optimal open-loop actions in the model from the
    current history and the full backward pass (gains on the augmented state).
    """
    ss = arx_state_space(model)
    H = _pos_int("horizon", horizon)
    tgt = _as_float("target", target, torch.float64)
    if tgt.ndim == 2:
        _shape("target", tgt, (H, ss.obs_dim))
        tgt = torch.cat([tgt[:1], tgt])  # r_0 is irrelevant (constant cost); keep the shape (H + 1, do)
    Q, R, ref = _obs_cost_matrices(ss, obs_weight, action_weight, tgt, H)
    sol = lqr_backward(ss.A, ss.B, Q, R, H, Q, ss.c, ref)
    x0 = ss.state(obs_history, action_history)
    _, u = lqr_rollout(sol, ss.A, ss.B, x0, ss.c)
    return u, sol


# =============================================================================================
# 2. Sampling planner through a model's predictive distribution
# =============================================================================================


class Predictor(Protocol):
    """``predict(obs_history (C, do), action_history (C - 1, da), candidates (N, H, da)) -> (mean, var)``,
    each ``(N, H, do)``: index ``k`` is the prediction of the observation after candidate action ``k``.
    A predictor with ``needs_state = True`` (the true simulator) is called with ``state=`` as well."""

    def __call__(self, obs_history: Tensor, action_history: Tensor, candidates: Tensor) -> tuple[Tensor, Tensor]: ...


@dataclass(frozen=True)
class QuadraticCost:
    r"""The planning cost of a batch of candidates, Eq. (plan-expected-cost):

    .. math:: J(a_{0:H-1}) = \sum_{k=1}^{H}\Big[(\mu_k - r_k)^\top W(\mu_k - r_k)
              + \lambda\,\operatorname{tr}(W\Sigma_k)\Big] + \sum_{k=0}^{H-1} a_k^\top R\, a_k,

    with :math:`(\mu_k, \Sigma_k)` the predicted mean and (diagonal) variance of the
    observation after :math:`k` actions, :math:`W = \mathrm{diag}(\text{obs\_weight})`,
    :math:`R = \mathrm{diag}(\text{action\_weight})` and :math:`\lambda` = ``risk``. Since
    :math:`\mathbb E[(o - r)^\top W (o - r)] = (\mu - r)^\top W(\mu - r) + \operatorname{tr}(W\Sigma)`,
    ``risk = 0`` scores the mean prediction (certainty equivalence), ``risk = 1`` the expected
    cost under the predictive distribution, and ``risk > 1`` is risk-averse (it penalizes
    predicted variance beyond its expected cost).

    ``obs_weight: (do,)`` and ``action_weight: (da,)`` non-negative; a zero weight leaves that
    dimension untracked (e.g. velocities).
    """

    obs_weight: Tensor
    action_weight: Tensor
    risk: float = 0.0

    def __post_init__(self) -> None:
        w = _as_float("obs_weight", self.obs_weight, torch.float64)
        a = _as_float("action_weight", self.action_weight, torch.float64)
        if w.ndim != 1 or bool((w < 0).any()) or not bool((w > 0).any()):
            raise ValueError(f"obs_weight: expected a (do,) vector of weights >= 0, not all 0, got {w.tolist()}")
        if a.ndim != 1 or bool((a < 0).any()):
            raise ValueError(f"action_weight: expected a (da,) vector of weights >= 0, got {a.tolist()}")
        if not (isinstance(self.risk, (int, float)) and math.isfinite(self.risk) and self.risk >= 0):
            raise ValueError(f"risk: must be a finite number >= 0, got {self.risk!r}")
        object.__setattr__(self, "obs_weight", w)
        object.__setattr__(self, "action_weight", a)

    @property
    def obs_dim(self) -> int:
        return self.obs_weight.shape[0]

    @property
    def action_dim(self) -> int:
        return self.action_weight.shape[0]

    def __call__(self, mean: Tensor, var: Tensor, actions: Tensor, target: Tensor) -> Tensor:
        """``mean, var: (N, H, do)``, ``actions: (N, H, da)``, ``target: (H, do)`` -> ``(N,)``."""
        w = self.obs_weight.to(mean.dtype)
        cost = ((mean - target) ** 2 * w).sum((-1, -2))
        if self.risk:
            cost = cost + self.risk * (var * w).sum((-1, -2))
        return cost + (actions ** 2 * self.action_weight.to(actions.dtype)).sum((-1, -2))


@dataclass(frozen=True)
class PlanResult:
    """One call of :meth:`SamplingPlanner.plan`.

    Attributes:
        actions: ``(H, da)`` the plan; ``cost``: its cost (Eq. plan-expected-cost).
        mean, var: ``(H, do)`` the predictor's prediction along the plan.
        mean_costs: ``(n_iters + 1,)`` the cost of the sampling distribution's mean at the start of
            every iteration and after the last one (the quantity CEM and MPPI decrease).
        best_costs: ``(n_iters + 1,)`` the lowest cost evaluated so far after each iteration
            (non-increasing) and of the returned plan at the end.
    """

    actions: Tensor
    cost: float
    mean: Tensor
    var: Tensor
    mean_costs: Tensor
    best_costs: Tensor


def _check_bounds(low: object | None, high: object | None, da: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``(da,)`` bounds; ``None`` means unbounded; NaN is an error, ``low <= high`` required."""
    def one(name: str, x: object | None, fill: float) -> Tensor:
        if x is None:
            return torch.full((da,), fill, dtype=dtype)
        t = torch.as_tensor(np.asarray(x, dtype=np.float64) if not isinstance(x, Tensor) else x).to(dtype)
        if t.ndim == 0:
            t = t.expand(da)
        if t.shape != (da,):
            raise ValueError(f"{name}: expected shape ({da},) or a scalar, got {tuple(t.shape)}")
        if bool(torch.isnan(t).any()):
            raise ValueError(f"{name}: contains NaN")
        return t.clone()
    lo, hi = one("action_low", low, -math.inf), one("action_high", high, math.inf)
    if bool((lo > hi).any()):
        raise ValueError(f"action_low: must be <= action_high, got {lo.tolist()} > {hi.tolist()}")
    return lo, hi


class SamplingPlanner:
    r"""Model-predictive control by sampling action sequences: CEM (Eq. plan-cem) or MPPI (Eq. plan-mppi).

    At each call of :meth:`plan` the planner keeps a Gaussian over action sequences
    :math:`a_{0:H-1}` with mean :math:`m` (warm-started with the previous plan shifted by one
    step, Eq. plan-warm-start) and standard deviation :math:`\sigma` (``init_std``). Each of
    ``n_iters`` iterations draws ``n_samples`` candidates :math:`a^{(j)} = \mathrm{clip}(m +
    \sigma\epsilon^{(j)})` into the box ``[action_low, action_high]``, scores them **and the
    current mean** in one batched call of ``predict`` and ``cost`` (Eq. plan-expected-cost), then

    * **CEM** (Eq. plan-cem): the :math:`E = \lceil\rho N\rceil` lowest-cost candidates (``elite_frac``
      :math:`\rho`) give :math:`m \leftarrow \alpha m + (1 - \alpha)\,\mathrm{mean}(\text{elites})`,
      :math:`\sigma \leftarrow \alpha\sigma + (1 - \alpha)\max(\mathrm{std}(\text{elites}), \sigma_\min)`
      (``momentum`` :math:`\alpha`, ``min_std`` :math:`\sigma_\min`);
    * **MPPI** (Eq. plan-mppi): :math:`m \leftarrow \alpha m + (1 - \alpha)\sum_j w_j a^{(j)}`,
      :math:`w_j \propto \exp(-(J_j - \min_i J_i)/\eta)` (``temperature`` :math:`\eta`, an absolute
      cost scale); with ``adapt_std`` (default) also
      :math:`\sigma \leftarrow \alpha\sigma + (1 - \alpha)\max\big((\textstyle\sum_j w_j (a^{(j)} - m)^2)^{1/2}, \sigma_\min\big)`
      (the weighted spread; measured on the double integrator of the tests it is needed to get
      within 1 % of the optimum in 20 iterations), with ``adapt_std=False`` the classic fixed
      :math:`\sigma`. ``momentum`` 0.5 avoided the early collapse of :math:`\sigma` seen with 0.

    The plan returned is the better of the final mean and the best candidate evaluated. All
    randomness comes from one ``torch.Generator`` seeded with ``seed`` (:meth:`reset` reseeds it).
    Calling the planner (``planner(obs_history, action_history, target, state)``) plans, stores
    the plan for the warm start and returns its first action: the policy interface of
    :func:`closed_loop`.
    """

    def __init__(self, predict: Callable[..., tuple[Tensor, Tensor]], cost: QuadraticCost, horizon: int,
                 action_low: object | None = None, action_high: object | None = None, *,
                 method: Literal["cem", "mppi"] = "cem", n_samples: int = 256, n_iters: int = 5,
                 elite_frac: float = 0.1, temperature: float = 1.0, init_std: object | None = None,
                 min_std: float = 1e-3, momentum: float = 0.0, adapt_std: bool = True,
                 init_mean: object | None = None,
                 seed: int = 0, dtype: torch.dtype = torch.float64) -> None:
        if not callable(predict):
            raise ValueError(f"predict: expected a callable, got {type(predict).__name__}")
        if not callable(cost):
            raise ValueError(f"cost: expected a callable cost, got {type(cost).__name__}")
        if method not in ("cem", "mppi"):
            raise ValueError(f"method: expected 'cem' or 'mppi', got {method!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype!r}")
        self.horizon = _pos_int("horizon", horizon)
        self.n_samples = _pos_int("n_samples", n_samples, 2)
        self.n_iters = _pos_int("n_iters", n_iters)
        if not (isinstance(elite_frac, (int, float)) and 0.0 < elite_frac <= 1.0):
            raise ValueError(f"elite_frac: must be in (0, 1], got {elite_frac!r}")
        if not (isinstance(temperature, (int, float)) and math.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature: must be a finite number > 0, got {temperature!r}")
        if not (isinstance(min_std, (int, float)) and min_std >= 0):
            raise ValueError(f"min_std: must be >= 0, got {min_std!r}")
        if not (isinstance(momentum, (int, float)) and 0.0 <= momentum < 1.0):
            raise ValueError(f"momentum: must be in [0, 1), got {momentum!r}")
        self.predict, self.cost, self.method, self.dtype = predict, cost, method, dtype
        da = getattr(cost, "action_dim", None)
        if da is None:
            if action_low is None:
                raise ValueError("action_low: give the bounds (or a QuadraticCost) so the action dimension is known")
            da = int(np.asarray(action_low).reshape(-1).shape[0])
        self.action_dim = int(da)
        self.low, self.high = _check_bounds(action_low, action_high, self.action_dim, dtype)
        bounded = torch.isfinite(self.low) & torch.isfinite(self.high)
        if init_std is None:
            std = torch.where(bounded, (self.high - self.low) / 4.0, torch.ones_like(self.low))
        else:
            std = _as_float("init_std", init_std, dtype)
            std = std.expand(self.action_dim).clone() if std.ndim == 0 else _shape("init_std", std, (self.action_dim,))
        if not bool((std > 0).all()):
            raise ValueError(f"init_std: must be > 0 in every dimension, got {std.tolist()}")
        self.init_std = std
        if init_mean is None:
            mean0 = torch.zeros(self.action_dim, dtype=dtype)
        else:
            mean0 = _shape("init_mean", _as_float("init_mean", init_mean, dtype), (self.action_dim,))
        self.init_mean = self._clip(mean0)
        self.n_elite = max(1, math.ceil(elite_frac * self.n_samples))
        if not isinstance(adapt_std, bool):
            raise ValueError(f"adapt_std: expected a bool, got {adapt_std!r}")
        self.elite_frac, self.temperature, self.min_std, self.momentum = elite_frac, temperature, min_std, momentum
        self.adapt_std = adapt_std
        self.seed = seed
        self.reset()

    # -- state ------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the warm start and reseed the generator."""
        self.generator = torch.Generator().manual_seed(int(self.seed))
        self._warm: Tensor | None = None
        self.last_plan: PlanResult | None = None

    def _clip(self, a: Tensor) -> Tensor:
        return torch.minimum(torch.maximum(a, self.low), self.high)

    # -- planning ---------------------------------------------------------------------------
    def _evaluate(self, obs: Tensor, act: Tensor, cand: Tensor, target: Tensor, state: Any
                  ) -> tuple[Tensor, Tensor, Tensor]:
        if getattr(self.predict, "needs_state", False):
            mean, var = self.predict(obs, act, cand, state=state)
        else:
            mean, var = self.predict(obs, act, cand)
        N, H = cand.shape[:2]
        for name, x in (("mean", mean), ("var", var)):
            if not isinstance(x, Tensor) or x.ndim != 3 or tuple(x.shape[:2]) != (N, H) \
                    or x.shape[2] != target.shape[-1]:
                raise ValueError(f"predict: returned {name} of shape "
                                 f"{tuple(getattr(x, 'shape', ()))}, expected ({N}, {H}, {target.shape[-1]})")
        mean, var = mean.to(self.dtype), var.to(self.dtype)
        if not bool(torch.isfinite(var).all()) or bool((var < 0).any()):
            raise ValueError("predict: returned negative or non-finite variances")
        cost = self.cost(mean, var, cand, target)
        cost = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, math.inf))  # a diverged prediction loses
        return cost, mean, var

    def _check_inputs(self, obs_history: object, action_history: object, target: object
                      ) -> tuple[Tensor, Tensor, Tensor]:
        obs, act = _history(obs_history, action_history, None, self.action_dim, self.dtype)
        return obs, act, _per_step("target", target, self.horizon, obs.shape[1], self.dtype)

    @torch.no_grad()
    def plan(self, obs_history: object, action_history: object, target: object, state: Any = None) -> PlanResult:
        """Optimize an action sequence from the current history (Eqs. plan-cem / plan-mppi).

        Args:
            obs_history: ``(C, do)`` observations so far (the last is the current one).
            action_history: ``(C - 1, da)`` the actions applied between them.
            target: ``(do,)`` or ``(H, do)``: the targets of the next ``H`` observations.
            state: the simulator's true state, passed only to a predictor with ``needs_state``.
        """
        obs, act, tgt = self._check_inputs(obs_history, action_history, target)
        H, da, N = self.horizon, self.action_dim, self.n_samples
        mean = self.init_mean.expand(H, da).clone() if self._warm is None else self._warm.clone()
        std = self.init_std.expand(H, da).clone()
        best_cost, best = math.inf, mean
        mean_costs, best_costs = [], []
        for _ in range(self.n_iters):
            eps = torch.randn(N, H, da, generator=self.generator, dtype=self.dtype)
            cand = self._clip(mean + std * eps)
            costs, _, _ = self._evaluate(obs, act, torch.cat([mean[None], cand]), tgt, state)
            mean_costs.append(float(costs[0]))
            j = int(torch.argmin(costs))
            if float(costs[j]) < best_cost:
                best_cost, best = float(costs[j]), (mean if j == 0 else cand[j - 1]).clone()
            best_costs.append(best_cost)
            c = costs[1:]
            if self.method == "cem":
                elite = cand[torch.topk(-c, self.n_elite).indices]
                new_mean = elite.mean(0)
                new_std = elite.std(0, unbiased=False).clamp_min(self.min_std) if self.n_elite > 1 \
                    else torch.full_like(std, self.min_std)
                mean = self.momentum * mean + (1.0 - self.momentum) * new_mean
                std = self.momentum * std + (1.0 - self.momentum) * new_std
            else:
                finite = torch.isfinite(c)
                if not bool(finite.any()):
                    continue
                logits = torch.where(finite, -(c - c[finite].min()) / self.temperature, torch.full_like(c, -math.inf))
                weights = torch.softmax(logits, 0)[:, None, None]
                new_mean = (weights * cand).sum(0)
                mean = self.momentum * mean + (1.0 - self.momentum) * new_mean
                if self.adapt_std:
                    new_std = (weights * (cand - new_mean) ** 2).sum(0).sqrt().clamp_min(self.min_std)
                    std = self.momentum * std + (1.0 - self.momentum) * new_std
        final_cost, final_mean, final_var = self._evaluate(obs, act, mean[None], tgt, state)
        mean_costs.append(float(final_cost[0]))
        if float(final_cost[0]) <= best_cost:
            plan, cost, pm, pv = mean, float(final_cost[0]), final_mean[0], final_var[0]
        else:
            c1, m1, v1 = self._evaluate(obs, act, best[None], tgt, state)
            plan, cost, pm, pv = best, float(c1[0]), m1[0], v1[0]
        best_costs.append(cost)
        result = PlanResult(plan, cost, pm, pv, torch.tensor(mean_costs, dtype=torch.float64),
                            torch.tensor(best_costs, dtype=torch.float64))
        self.last_plan = result
        return result

    def __call__(self, obs_history: object, action_history: object, target: object, state: Any = None) -> Tensor:
        """Plan, keep the plan shifted by one step as the next warm start (Eq. plan-warm-start:
        :math:`m_{0:H-2} \\leftarrow a_{1:H-1}`, :math:`m_{H-1} \\leftarrow a_{H-1}`), return the first action ``(da,)``."""
        result = self.plan(obs_history, action_history, target, state)
        self._warm = torch.cat([result.actions[1:], result.actions[-1:]])
        return result.actions[0]


def world_model_predictor(model: Callable[..., tuple[Tensor, Tensor]], stats: Mapping[str, object] | None = None,
                          context_len: int | None = None) -> Callable[..., tuple[Tensor, Tensor]]:
    r"""A :class:`Predictor` from a world model with the interface ``model(obs, actions, mask) -> (mean, var)``.

    For the history :math:`o_0..o_{C-1}`, :math:`a_0..a_{C-2}` and candidates
    :math:`a_{C-1}..a_{C+H-2}` it calls :func:`pgm_wm.evaluation.multistep_predict` on a batch
    of ``N`` sequences of length :math:`C + H`: the history observed, the future masked (the
    model never sees a future observation; the zeros there are placeholders), so output
    :math:`k` is the model's open-loop :math:`k`-step prediction of :math:`o_{C-1+k}`
    (Eq. acrkn-multistep). ``context_len`` keeps only the last that many observations of the
    history (default: all). ``stats`` (``obs_mean, obs_std, act_mean, act_std``, the training
    statistics of :class:`~pgm_wm.datasets.sequences.SequenceData`) normalizes the inputs and
    returns mean and variance in original units (``mean * std + mean_o``, ``var * std**2``).
    Runs without gradients, in the model's dtype; returns the planner's dtype.
    """
    from .evaluation import multistep_predict  # heavy import, only when a model is planned with

    if not callable(model):
        raise ValueError(f"model: expected a callable world model, got {type(model).__name__}")
    if context_len is not None:
        _pos_int("context_len", context_len)
    norm: dict[str, Tensor] = {}
    if stats is not None:
        for key in ("obs_mean", "obs_std", "act_mean", "act_std"):
            if key not in stats:
                raise ValueError(f"stats: missing {key!r}")
            norm[key] = _as_float(f"stats[{key!r}]", stats[key], torch.float64)
            if key.endswith("std") and not bool((norm[key] > 0).all()):
                raise ValueError(f"stats[{key!r}]: must be > 0")
    params = list(getattr(model, "parameters", lambda: [])()) + list(getattr(model, "buffers", lambda: [])())
    float_params = [t for t in params if torch.is_floating_point(t)]
    mdtype = float_params[0].dtype if float_params else torch.float32

    @torch.no_grad()
    def predict(obs_history: Tensor, action_history: Tensor, candidates: Tensor) -> tuple[Tensor, Tensor]:
        out_dtype = candidates.dtype
        obs, act, cand = obs_history.to(torch.float64), action_history.to(torch.float64), candidates.to(torch.float64)
        if context_len is not None and obs.shape[0] > context_len:
            obs, act = obs[-context_len:], act[obs_history.shape[0] - context_len:]
        if norm:
            if norm["obs_mean"].shape[0] != obs.shape[1] or norm["act_mean"].shape[0] != cand.shape[2]:
                raise ValueError("stats: dimensions do not match the observations / actions")
            obs = (obs - norm["obs_mean"]) / norm["obs_std"]
            act = (act - norm["act_mean"]) / norm["act_std"]
            cand = (cand - norm["act_mean"]) / norm["act_std"]
        N, H, _ = cand.shape
        C, do = obs.shape
        seq_obs = torch.zeros(N, C + H, do, dtype=torch.float64)
        seq_obs[:, :C] = obs
        seq_act = torch.zeros(N, C + H, cand.shape[2], dtype=torch.float64)
        seq_act[:, :C - 1] = act
        seq_act[:, C - 1:C - 1 + H] = cand            # the last action slot is never used
        mean, var = multistep_predict(model, seq_obs.to(mdtype), seq_act.to(mdtype), C, H)
        mean, var = mean.to(torch.float64), var.to(torch.float64)
        if norm:
            mean = mean * norm["obs_std"] + norm["obs_mean"]
            var = var * norm["obs_std"] ** 2
        return mean.to(out_dtype), var.to(out_dtype)

    return predict


def linear_predictor(A: object, B: object, c: object | None = None, process_var: object | None = None
                     ) -> Callable[..., tuple[Tensor, Tensor]]:
    r"""A :class:`Predictor` for a fully observed linear-Gaussian system :math:`o_{t+1} = Ao_t + Ba_t + c + w_t`.

    From the last observation it propagates the mean exactly and the covariance by
    Eq. (gauss-marginal), :math:`\Sigma_{k+1} = A\Sigma_k A^\top + \mathrm{diag}(\text{process\_var})`
    (:math:`\Sigma_0 = 0`), returning its diagonal. Batched over candidates; the analytic
    reference of the planner's tests and of the chapter's LQR section.
    """
    A = _as_float("A", A, torch.float64)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"A: expected a square matrix, got shape {tuple(A.shape)}")
    n = A.shape[0]
    B = _as_float("B", B, torch.float64)
    if B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"B: expected shape ({n}, m), got {tuple(B.shape)}")
    c = torch.zeros(n, dtype=torch.float64) if c is None else _shape("c", _as_float("c", c, torch.float64), (n,))
    w = torch.zeros(n, dtype=torch.float64) if process_var is None else \
        _shape("process_var", _as_float("process_var", process_var, torch.float64), (n,))
    if bool((w < 0).any()):
        raise ValueError("process_var: must be >= 0")

    def predict(obs_history: Tensor, action_history: Tensor, candidates: Tensor) -> tuple[Tensor, Tensor]:
        dtype = candidates.dtype
        x = obs_history[-1].to(torch.float64).expand(candidates.shape[0], n)
        u = candidates.to(torch.float64)
        cov = torch.zeros(n, n, dtype=torch.float64)
        means, variances = [], []
        for k in range(u.shape[1]):
            x = x @ A.T + u[:, k] @ B.T + c
            cov = A @ cov @ A.T + torch.diag(w)
            means.append(x)
            variances.append(torch.diagonal(cov).expand_as(x))
        return torch.stack(means, 1).to(dtype), torch.stack(variances, 1).to(dtype)

    return predict


def ensemble_predictor(predictors: Sequence[Callable[..., tuple[Tensor, Tensor]]]
                       ) -> Callable[..., tuple[Tensor, Tensor]]:
    r"""Several models as one :class:`Predictor`: the moments of their equal-weight mixture, Eq. (plan-ensemble),

    .. math:: \bar\mu = \frac1M\sum_{m=1}^M \mu_m, \qquad
              \bar\sigma^2 = \frac1M\sum_{m=1}^M \sigma_m^2 + \frac1M\sum_{m=1}^M (\mu_m - \bar\mu)^2,

    per candidate, step and dimension. The first term is the models' own predicted variance; the
    second is their disagreement, a variance that can grow where models trained from different seeds
    extrapolate differently: the epistemic part that Chapter 7, Section 7.5 found missing from a
    single model's variance (there, three seeds of one small ac-RKN disagreed less on a planner's
    commands than on training commands). Every predictor must return
    predictions of the same shape. The true simulator (``needs_state``) is not a model and is refused.
    """
    preds = list(predictors) if isinstance(predictors, (list, tuple)) else None
    if preds is None or len(preds) < 2:
        raise ValueError(f"predictors: expected a list or tuple of at least two predictors, got {predictors!r}")
    for i, p in enumerate(preds):
        if not callable(p):
            raise ValueError(f"predictors[{i}]: expected a callable predictor, got {type(p).__name__}")
        if getattr(p, "needs_state", False):
            raise ValueError(f"predictors[{i}]: needs the simulator's state; an ensemble mixes models only")

    def predict(obs_history: Tensor, action_history: Tensor, candidates: Tensor) -> tuple[Tensor, Tensor]:
        outs = [p(obs_history, action_history, candidates) for p in preds]
        shapes = {tuple(t.shape) for out in outs for t in out}
        if len(shapes) != 1:
            raise ValueError(f"predictors: their means and variances differ in shape: {sorted(shapes)}")
        means = torch.stack([m for m, _ in outs])
        mean = means.mean(0)
        return mean, torch.stack([v for _, v in outs]).mean(0) + (means - mean).square().mean(0)

    return predict


# =============================================================================================
# 3. Closed loop against the true simulator
# =============================================================================================


class Env(Protocol):
    """A step-able simulator: ``step(state, action) -> state``, ``observe(state) -> (do,)`` (noise-free),
    ``rollout(state, actions (N, H, da)) -> (N, H, do)`` (the observations after each action, from one
    state, batched over ``N`` action sequences), and ``obs_dim``, ``action_dim``."""

    obs_dim: int
    action_dim: int

    def step(self, state: Any, action: np.ndarray) -> Any: ...

    def observe(self, state: Any) -> np.ndarray: ...

    def rollout(self, state: Any, actions: np.ndarray) -> np.ndarray: ...


def _actions_array(actions: object, da: int, ndim: int) -> np.ndarray:
    a = np.asarray(actions.detach().cpu().numpy() if isinstance(actions, Tensor) else actions, dtype=np.float64)
    if a.ndim != ndim or a.shape[-1] != da:
        raise ValueError(f"actions: expected {ndim} dimensions ending in {da}, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError("actions: contains NaN or infinite values")
    return a


class LinearEnv:
    r"""A deterministic linear system :math:`x_{t+1} = Ax_t + Bu_t + c`, observed fully (:math:`o_t = x_t`)."""

    def __init__(self, A: object, B: object, c: object | None = None) -> None:
        A_, B_, _, _, _, c_ = _check_lqr_model(A, B, np.zeros((np.shape(A)[0],) * 2),
                                               np.eye(np.shape(B)[1]), None, c)
        self.A, self.B, self.c = A_.double().numpy(), B_.double().numpy(), c_.double().numpy()
        self.obs_dim, self.action_dim = self.A.shape[0], self.B.shape[1]

    def step(self, state: np.ndarray, action: object) -> np.ndarray:
        u = _actions_array(action, self.action_dim, 1)
        return self.A @ np.asarray(state, dtype=np.float64) + self.B @ u + self.c

    def observe(self, state: np.ndarray) -> np.ndarray:
        return np.asarray(state, dtype=np.float64).copy()

    def rollout(self, state: np.ndarray, actions: object) -> np.ndarray:
        u = _actions_array(actions, self.action_dim, 3)
        x = np.broadcast_to(np.asarray(state, dtype=np.float64), (u.shape[0], self.obs_dim))
        out = []
        for k in range(u.shape[1]):
            x = x @ self.A.T + u[:, k] @ self.B.T + self.c
            out.append(x)
        return np.stack(out, 1)


class TwoLinkArmEnv:
    r"""The payload arm of :mod:`pgm_wm.datasets.two_link_arm` as a step-able simulator (Eqs. arm-dynamics, arm-pd).

    ``state``: ``(4,)`` = :math:`(q_1, q_2, \dot q_1, \dot q_2)`; the observation is the state
    (noise-free; :func:`closed_loop` adds observation noise if asked). ``action``:

    * ``"pd_target"``: the PD targets :math:`r_t` (rad), the closed loop of Eq. (arm-pd) with
      gravity compensation, as in the datasets;
    * ``"torque"``: joint torques :math:`\tau_t` (N m) applied directly. This runs the same
      :func:`~pgm_wm.datasets.two_link_arm.rollout_two_link_arm` with
      :math:`K_p = K_d = 0`, no gravity compensation and the torque passed as its torque
      "noise" :math:`\xi_t`, so :math:`\tau_t = 0 + \xi_t` exactly.

    The torque noise of the datasets is off (a planner cannot know it). ``payload`` (kg) is
    constant; ``params`` override :data:`~pgm_wm.datasets.two_link_arm.DEFAULT_PARAMS`. Every
    call simulates one frame more than it returns (the rollout stores the state at the start of
    each frame), which leaves the numerics of the returned frames untouched: stepping
    :math:`T` times equals one rollout (tested).
    """

    obs_dim = 4
    action_dim = 2

    def __init__(self, payload: float = 0.0, params: dict | None = None,
                 action: Literal["pd_target", "torque"] = "pd_target") -> None:
        from .datasets.two_link_arm import DEFAULT_PARAMS

        if not (isinstance(payload, (int, float)) and math.isfinite(payload) and payload >= 0):
            raise ValueError(f"payload: must be a finite number >= 0 (kg), got {payload!r}")
        if action not in ("pd_target", "torque"):
            raise ValueError(f"action: expected 'pd_target' or 'torque', got {action!r}")
        if params is not None and not isinstance(params, dict):
            raise ValueError(f"params: expected a dict, got {type(params).__name__}")
        unknown = set(params or {}) - set(DEFAULT_PARAMS)
        if unknown:
            raise ValueError(f"params: unknown keys {sorted(unknown)}")
        self.payload, self.action = float(payload), action
        self.params = {**DEFAULT_PARAMS, **(params or {})}
        if action == "torque":
            self.params.update(Kp=[0.0, 0.0], Kd=[0.0, 0.0], gravity_compensation=0.0)
        self.dt = float(self.params["dt"])

    def _simulate(self, state0: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """``state0 (N, 4)``, ``actions (N, H, 2)`` -> states ``(N, H + 1, 4)`` after 0..H actions."""
        from .datasets.two_link_arm import rollout_two_link_arm

        N, H, _ = actions.shape
        frames = np.concatenate([actions, actions[:, -1:]], 1)     # one frame more: its start is the last state
        zeros = np.zeros_like(frames)
        ref, noise = (frames, zeros) if self.action == "pd_target" else (zeros, frames)
        payload = np.full((N, H + 1), self.payload)
        states, _ = rollout_two_link_arm(state0, ref, noise, payload, self.params)
        return states

    @staticmethod
    def _state(state: object) -> np.ndarray:
        s = np.asarray(state, dtype=np.float64)
        if s.shape != (4,) or not np.isfinite(s).all():
            raise ValueError(f"state: expected a finite (4,) array (q1, q2, qd1, qd2), got shape {s.shape}")
        return s

    def step(self, state: np.ndarray, action: object) -> np.ndarray:
        a = _actions_array(action, 2, 1)
        return self._simulate(self._state(state)[None], a[None, None])[0, 1]

    def observe(self, state: np.ndarray) -> np.ndarray:
        return self._state(state).copy()

    def rollout(self, state: np.ndarray, actions: object) -> np.ndarray:
        a = _actions_array(actions, 2, 3)
        s0 = np.repeat(self._state(state)[None], a.shape[0], 0)
        return self._simulate(s0, a)[:, 1:]


class MemoryArmEnv:
    r"""The long-memory hysteresis arm of :mod:`pgm_wm.datasets.memory_arm` as a step-able simulator.

    ``state``: the dict of :func:`~pgm_wm.datasets.memory_arm.initial_state` for one arm
    (``angle, velocity, pressure (1, 2)``, ``play (1, 2, n_play)``, ``creep (1, 2, 2)``); the
    observation is the joint angles ``(2,)`` (noise-free). ``action``: the valve commands in
    :math:`[-1, 1]` (``action_low`` / ``action_high``). Each step is one frame of
    :func:`~pgm_wm.datasets.memory_arm.rollout_memory_arm`, so stepping equals one rollout (tested).
    """

    obs_dim = 2
    action_dim = 2
    action_low = np.array([-1.0, -1.0])
    action_high = np.array([1.0, 1.0])

    def __init__(self, params: dict | None = None) -> None:
        from .datasets.memory_arm import DEFAULT_PARAMS

        if params is not None and not isinstance(params, dict):
            raise ValueError(f"params: expected a dict, got {type(params).__name__}")
        unknown = set(params or {}) - set(DEFAULT_PARAMS)
        if unknown:
            raise ValueError(f"params: unknown keys {sorted(unknown)}")
        self.params = {**DEFAULT_PARAMS, **(params or {})}
        self.dt = float(self.params["dt"])

    def initial_state(self) -> dict[str, np.ndarray]:
        """The all-zero state of one arm (:func:`~pgm_wm.datasets.memory_arm.initial_state`)."""
        from .datasets.memory_arm import initial_state

        return initial_state(1, self.params)

    @staticmethod
    def _state(state: object) -> dict[str, np.ndarray]:
        keys = ("angle", "velocity", "pressure", "play", "creep")
        if not isinstance(state, Mapping) or any(k not in state for k in keys):
            raise ValueError(f"state: expected a dict with keys {keys}")
        if any(np.asarray(state[k]).shape[0] != 1 for k in keys):
            raise ValueError("state: expected the state of one arm (leading size 1)")
        return {k: np.asarray(state[k], dtype=np.float64) for k in keys}

    def step(self, state: dict, action: object) -> dict[str, np.ndarray]:
        from .datasets.memory_arm import rollout_memory_arm

        a = _actions_array(action, 2, 1)
        _, final = rollout_memory_arm(a[None, None], self._state(state), self.params)
        return final

    def observe(self, state: dict) -> np.ndarray:
        return self._state(state)["angle"][0].copy()

    def rollout(self, state: dict, actions: object) -> np.ndarray:
        from .datasets.memory_arm import rollout_memory_arm

        a = _actions_array(actions, 2, 3)
        s = {k: np.repeat(v, a.shape[0], 0) for k, v in self._state(state).items()}
        rec, final = rollout_memory_arm(a, s, self.params)
        return np.concatenate([rec["angle"][:, 1:], final["angle"][:, None]], 1)


def simulator_predictor(env: Env) -> Callable[..., tuple[Tensor, Tensor]]:
    r"""The true simulator as a :class:`Predictor` (the upper reference row): from the simulator's
    *true* state it rolls every candidate out (``env.rollout``, batched) and returns the
    noise-free observations with zero variance. Marked ``needs_state``: the planner passes it the
    state that :func:`closed_loop` holds (no model predictor ever receives it)."""
    for attr in ("rollout", "obs_dim", "action_dim"):
        if not hasattr(env, attr):
            raise ValueError(f"env: expected a simulator with .{attr}, got {type(env).__name__}")

    def predict(obs_history: Tensor, action_history: Tensor, candidates: Tensor, *, state: Any = None
                ) -> tuple[Tensor, Tensor]:
        if state is None:
            raise ValueError("state: the simulator predictor needs the true simulator state")
        mean = torch.as_tensor(env.rollout(state, candidates), dtype=candidates.dtype)
        return mean, torch.zeros_like(mean)

    predict.needs_state = True  # type: ignore[attr-defined]
    return predict


class ConstantPolicy:
    """Lower reference: always the same action (e.g. zeros); the policy interface of :func:`closed_loop`."""

    def __init__(self, action: object) -> None:
        self.action = _as_float("action", action, torch.float64)
        if self.action.ndim != 1:
            raise ValueError(f"action: expected a (da,) vector, got shape {tuple(self.action.shape)}")

    def __call__(self, obs_history: Tensor, action_history: Tensor, target: Tensor, state: Any = None) -> Tensor:
        return self.action.clone()


class RandomPolicy:
    """Lower reference: actions uniform in ``[action_low, action_high]`` (finite), from a seeded generator."""

    def __init__(self, action_low: object, action_high: object, seed: int = 0) -> None:
        da = int(np.asarray(action_low).reshape(-1).shape[0])
        self.low, self.high = _check_bounds(action_low, action_high, da, torch.float64)
        if not bool(torch.isfinite(self.low).all() and torch.isfinite(self.high).all()):
            raise ValueError("action_low: random actions need finite bounds")
        self.generator = torch.Generator().manual_seed(int(seed))

    def __call__(self, obs_history: Tensor, action_history: Tensor, target: Tensor, state: Any = None) -> Tensor:
        u = torch.rand(self.low.shape, generator=self.generator, dtype=torch.float64)
        return self.low + (self.high - self.low) * u


class ARXLQRPolicy:
    r"""Receding-horizon LQR through a fitted linear ARX model (Eqs. plan-arx-state, plan-riccati):
    at every step :func:`arx_lqr` over ``horizon`` steps from the current history, first action
    applied (clipped to the bounds). The policy interface of :func:`closed_loop`."""

    def __init__(self, model: Any, obs_weight: object, action_weight: object, horizon: int,
                 action_low: object | None = None, action_high: object | None = None) -> None:
        self.space = arx_state_space(model)
        self.model, self.horizon = model, _pos_int("horizon", horizon)
        self.obs_weight, self.action_weight = obs_weight, action_weight
        self.low, self.high = _check_bounds(action_low, action_high, self.space.action_dim, torch.float64)
        self.last_plan: Tensor | None = None

    def __call__(self, obs_history: Tensor, action_history: Tensor, target: Tensor, state: Any = None) -> Tensor:
        u, _ = arx_lqr(self.model, obs_history, action_history, target, self.obs_weight, self.action_weight,
                       self.horizon)
        self.last_plan = u
        return torch.minimum(torch.maximum(u[0], self.low), self.high)


def warm_up(env: Env, state: Any, actions: object) -> tuple[Any, Tensor, Tensor]:
    """Apply ``actions: (C - 1, da)`` from ``state`` in the simulator to build the initial history of
    :func:`closed_loop`. Returns ``(state after them, obs_history (C, do), action_history (C - 1, da))``."""
    a = _actions_array(actions, env.action_dim, 2)
    obs = [env.observe(state)]
    for u in a:
        state = env.step(state, u)
        obs.append(env.observe(state))
    return state, torch.as_tensor(np.stack(obs)), torch.as_tensor(a)


@dataclass(frozen=True)
class ClosedLoopResult:
    r"""One closed-loop run (Eq. plan-closed-loop); all in original units, float64.

    Attributes:
        obs: ``(steps + 1, do)`` the observation before the first action and after each action.
        actions: ``(steps, da)``; targets: ``(steps, do)`` (``targets[t]`` is the target of ``obs[t + 1]``).
        step_cost: ``(steps,)`` :math:`\ell_t = (o_{t+1} - r_t)^\top W(o_{t+1} - r_t) + a_t^\top R a_t`
            in the **true** system; ``total_cost`` their sum.
        error: ``(steps,)`` the largest absolute tracking error over the tracked dimensions
            (``obs_weight > 0``) of ``obs[t + 1]``.
        success: True if ``error`` <= ``tol`` on each of the last ``success_steps`` steps.
        pred_mean, pred_var: ``(steps, H, do)`` the planner's predictions along its plan at each
            step (``None`` for policies that do not expose ``last_plan`` predictions).
        plan_actions: ``(steps, H, da)`` the plan chosen at each step, whose first action was sent
            (``None`` like ``pred_mean``); :func:`plan_prediction_errors` replays them.
        states: the simulator states after each action (``steps`` entries).
    """

    obs: Tensor
    actions: Tensor
    targets: Tensor
    step_cost: Tensor
    total_cost: float
    error: Tensor
    success: bool
    pred_mean: Tensor | None
    pred_var: Tensor | None
    plan_actions: Tensor | None
    states: list = field(repr=False)


def closed_loop(env: Env, policy: Callable[..., Tensor], state: Any, obs_history: object, action_history: object,
                targets: object, steps: int, cost: QuadraticCost, *, tol: float, success_steps: int = 1,
                obs_noise: object = 0.0, seed: int = 0) -> ClosedLoopResult:
    r"""Model-predictive control against the true simulator, Eq. (plan-closed-loop).

    For :math:`t = 0..T-1`: :math:`a_t = \pi(o_{\le t}, a_{<t}, r_{t:t+H-1})` (the policy, e.g. a
    :class:`SamplingPlanner`, replans from the whole history), :math:`s_{t+1} =
    \text{env.step}(s_t, a_t)`, :math:`o_{t+1} = \text{env.observe}(s_{t+1}) + \nu_t` with
    :math:`\nu_t\sim\mathcal N(0, \text{obs\_noise}^2)` (seeded ``numpy`` generator). The cost and
    the success are measured in the simulator, never in a model.

    Args:
        env: the simulator (:class:`Env`); state: its true state at the last history observation.
        policy: ``policy(obs_history (C, do), action_history (C - 1, da), target (H, do), state) -> (da,)``;
            the target window has length ``policy.horizon`` (1 if absent), padded with the last target.
            The state is passed to every policy; only the simulator predictor uses it.
        obs_history: ``(C, do)``, action_history: ``(C - 1, da)`` (see :func:`warm_up`).
        targets: ``(do,)`` or ``(steps, do)``, finite (untracked dimensions get weight 0 in ``cost``).
        steps: number of control steps :math:`T`.
        cost: the :class:`QuadraticCost` whose ``risk = 0`` part scores each step.
        tol, success_steps: success criterion (see :class:`ClosedLoopResult`).
        obs_noise: ``float`` or ``(do,)`` standard deviation of the observation noise (default 0).
    """
    steps = _pos_int("steps", steps)
    success_steps = _pos_int("success_steps", success_steps)
    if success_steps > steps:
        raise ValueError(f"success_steps: must be <= steps = {steps}, got {success_steps}")
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"tol: must be > 0, got {tol!r}")
    if not isinstance(cost, QuadraticCost):
        raise ValueError(f"cost: expected a QuadraticCost, got {type(cost).__name__}")
    if not callable(policy):
        raise ValueError(f"policy: expected a callable, got {type(policy).__name__}")
    do, da = env.obs_dim, env.action_dim
    if (cost.obs_dim, cost.action_dim) != (do, da):
        raise ValueError(f"cost: weights of size ({cost.obs_dim}, {cost.action_dim}) do not match the "
                         f"simulator's ({do}, {da})")
    obs, act = _history(obs_history, action_history, do, da, torch.float64)
    tg = _per_step("targets", targets, steps, do, torch.float64)
    noise = np.broadcast_to(np.asarray(obs_noise, dtype=np.float64), (do,))
    if not np.isfinite(noise).all() or (noise < 0).any():
        raise ValueError(f"obs_noise: must be finite and >= 0, got {obs_noise!r}")
    rng = np.random.default_rng(seed)
    H = int(getattr(policy, "horizon", 1))
    tracked = cost.obs_weight > 0
    obs_list, act_list = [obs[i] for i in range(obs.shape[0])], [act[i] for i in range(act.shape[0])]
    step_cost, errors, states, p_mean, p_var, p_act = [], [], [], [], [], []
    for t in range(steps):
        window = tg[torch.clamp(torch.arange(t, t + H), max=steps - 1)]
        a = policy(torch.stack(obs_list), torch.stack(act_list) if act_list else act[:0], window, state)
        a = _as_float("policy", torch.as_tensor(a), torch.float64).reshape(-1)
        if a.shape != (da,):
            raise ValueError(f"policy: returned an action of shape {tuple(a.shape)}, expected ({da},)")
        state = env.step(state, a.numpy())
        o = torch.as_tensor(env.observe(state) + noise * rng.standard_normal(do))
        plan = getattr(policy, "last_plan", None)
        if isinstance(plan, PlanResult):
            p_mean.append(plan.mean.to(torch.float64)), p_var.append(plan.var.to(torch.float64))
            p_act.append(plan.actions.to(torch.float64))
        step_cost.append(cost(o[None, None], torch.zeros(1, 1, do, dtype=torch.float64), a[None, None], tg[t][None])[0])
        errors.append((o - tg[t]).abs()[tracked].max())
        obs_list.append(o), act_list.append(a), states.append(state)
    err = torch.stack(errors)
    sc = torch.stack(step_cost)
    return ClosedLoopResult(
        obs=torch.stack(obs_list[obs.shape[0] - 1:]), actions=torch.stack(act_list[act.shape[0]:]), targets=tg.clone(),
        step_cost=sc, total_cost=float(sc.sum()), error=err, success=bool((err[-success_steps:] <= tol).all()),
        pred_mean=torch.stack(p_mean) if len(p_mean) == steps else None,
        pred_var=torch.stack(p_var) if len(p_var) == steps else None,
        plan_actions=torch.stack(p_act) if len(p_act) == steps else None, states=states)


def plan_prediction_errors(env: Env, run: ClosedLoopResult, state: Any) -> np.ndarray:
    r"""How wrong the planner's model was about the plans it chose: ``(steps, H, do)`` errors
    :math:`\hat o_{t+k\mid t} - o^{\text{sim}}_{t+k}` of the prediction ``run.pred_mean[t]`` along
    the plan ``run.plan_actions[t]``, against that plan replayed open loop in ``env`` from the true
    state in which it was made (``state`` for the first plan, ``run.states[t - 1]`` after that).
    A planner through the simulator itself scores zero (up to the observation noise of the run)."""
    if not isinstance(run, ClosedLoopResult):
        raise ValueError(f"run: expected a ClosedLoopResult, got {type(run).__name__}")
    if run.plan_actions is None or run.pred_mean is None:
        raise ValueError("run: its policy exposed no plans (run.plan_actions is None)")
    starts = [state, *run.states[:-1]]
    return np.stack([run.pred_mean[t].numpy() - env.rollout(starts[t], run.plan_actions[t][None].numpy())[0]
                     for t in range(len(starts))])


def command_statistics(actions: object, near: float = 0.9) -> tuple[float, float]:
    r"""Two numbers that say how a command sequence looks: the mean absolute change per step,
    :math:`\operatorname{mean}|a_t - a_{t-1}|`, and the share of entries with :math:`|a| >` ``near``
    (close to the bounds of a box [-1, 1]). ``actions``: ``(..., T, da)`` with ``T >= 2``."""
    a = _as_float("actions", actions, torch.float64)
    if a.ndim < 2 or a.shape[-2] < 2:
        raise ValueError(f"actions: expected (..., T, da) with T >= 2, got shape {tuple(a.shape)}")
    if not (isinstance(near, (int, float)) and near > 0):
        raise ValueError(f"near: must be > 0, got {near!r}")
    return float((a[..., 1:, :] - a[..., :-1, :]).abs().mean()), float((a.abs() > near).double().mean())

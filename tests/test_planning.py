"""Tests for pgm_wm.planning (Chapter 7), each against an independent reference:

* LQR: brute-force minimisation of the quadratic cost over the whole action sequence (the dense
  normal equations), scipy's discrete algebraic Riccati solver, random perturbations of the
  optimum, the package's Kalman filter run with the dual matrices (Kalman's duality), and the
  package's RTS smoother on the control-as-inference model;
* learned linear model: the ARX's own forward pass (state-space form) and the true LQR gains of
  the system the ARX was fitted on;
* sampling planner: the analytic LQR optimum, scipy's box-constrained optimum, a grid search
  for the risk-aware case, and properties (cost decrease in expectation, batching, warm start,
  seeding, input errors);
* simulators: stepping the wrappers equals one rollout of the dataset simulators; closed loop
  with the time-varying LQR policy equals the LQR rollout; physics-planner closed loops beat
  the lower references.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.optimize as sopt
import torch

from pgm_wm.baselines import LinearARX
from pgm_wm.datasets.memory_arm import DEFAULT_PARAMS as MEMORY_PARAMS
from pgm_wm.datasets.memory_arm import initial_state, rollout_memory_arm
from pgm_wm.datasets.two_link_arm import rollout_two_link_arm
from pgm_wm.planning import (
    ARXLQRPolicy,
    command_statistics,
    ensemble_predictor,
    plan_prediction_errors,
    ConstantPolicy,
    LinearEnv,
    MemoryArmEnv,
    QuadraticCost,
    RandomPolicy,
    SamplingPlanner,
    TwoLinkArmEnv,
    arx_lqr,
    arx_state_space,
    closed_loop,
    linear_predictor,
    lqr_backward,
    lqr_by_smoothing,
    lqr_cost,
    lqr_infinite_horizon,
    lqr_rollout,
    riccati_by_kalman,
    simulator_predictor,
    warm_up,
    world_model_predictor,
)

DT = torch.float64


# ---------------------------------------------------------------------------------------------
# Small problems
# ---------------------------------------------------------------------------------------------


def random_problem(seed: int, n: int = 3, m: int = 2, N: int = 6):
    """A random (not necessarily stable) linear system with drift, reference and costs."""
    rng = np.random.default_rng(seed)
    A = 0.9 * np.eye(n) + 0.4 * rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    L = rng.normal(size=(n, n))
    Q = L @ L.T / n + 0.1 * np.eye(n)
    Lr = rng.normal(size=(m, m))
    R = Lr @ Lr.T / m + 0.2 * np.eye(m)
    Q_f = 2.0 * Q + np.diag(rng.uniform(0, 1, n))
    c = 0.2 * rng.normal(size=n)
    ref = rng.normal(size=(N + 1, n))
    x0 = rng.normal(size=n)
    return A, B, Q, R, Q_f, c, ref, x0


def dense_cost_matrices(A, B, c, x0, N):
    """States as an affine function of the stacked actions: x = G u + d (``x: ((N+1) n,)``)."""
    n, m = B.shape
    G = np.zeros(((N + 1) * n, N * m))
    d = np.zeros((N + 1) * n)
    free = np.asarray(x0, dtype=float)
    for t in range(N + 1):
        d[t * n:(t + 1) * n] = free
        free = A @ free + c
        for s in range(t):
            G[t * n:(t + 1) * n, s * m:(s + 1) * m] = np.linalg.matrix_power(A, t - 1 - s) @ B
    return G, d


def brute_force_lqr(A, B, Q, R, Q_f, c, ref, x0, N):
    """Minimize Eq. (plan-cost) over all N m action entries at once (normal equations)."""
    n, m = B.shape
    G, d = dense_cost_matrices(A, B, c, x0, N)
    W = sla.block_diag(*([Q] * N + [Q_f]))
    Rb = np.kron(np.eye(N), R)
    r = np.broadcast_to(ref, (N + 1, n)).reshape(-1)
    u = np.linalg.solve(G.T @ W @ G + Rb, G.T @ W @ (r - d))
    x = (G @ u + d).reshape(N + 1, n)
    e = x.reshape(-1) - r
    return u.reshape(N, m), x, float(e @ W @ e + u @ Rb @ u)


# ---------------------------------------------------------------------------------------------
# 1. LQR as inference
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_lqr_equals_brute_force_minimisation(seed):
    A, B, Q, R, Q_f, c, ref, x0 = random_problem(seed)
    N = ref.shape[0] - 1
    sol = lqr_backward(A, B, Q, R, N, Q_f, c, ref)
    x, u = lqr_rollout(sol, A, B, x0, c)
    u_bf, x_bf, J_bf = brute_force_lqr(A, B, Q, R, Q_f, c, ref, x0, N)
    np.testing.assert_allclose(u.numpy(), u_bf, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(x.numpy(), x_bf, rtol=1e-9, atol=1e-9)
    J = float(lqr_cost(x, u, Q, R, Q_f, ref))
    assert J == pytest.approx(J_bf, rel=1e-10)
    # the value function at the start is the optimal cost (Eq. plan-value)
    assert float(sol.value(torch.as_tensor(x0), 0)) == pytest.approx(J_bf, rel=1e-10)


def test_lqr_cost_of_random_perturbations_is_higher():
    A, B, Q, R, Q_f, c, ref, x0 = random_problem(7)
    N = ref.shape[0] - 1
    sol = lqr_backward(A, B, Q, R, N, Q_f, c, ref)
    x, u = lqr_rollout(sol, A, B, x0, c)
    J = float(lqr_cost(x, u, Q, R, Q_f, ref))
    G, d = dense_cost_matrices(A, B, c, x0, N)
    g = torch.Generator().manual_seed(0)
    for scale in (1e-3, 1e-1, 1.0):
        du = scale * torch.randn(200, *u.shape, generator=g, dtype=DT)
        up = u + du
        xp = torch.as_tensor((G @ up.reshape(200, -1).numpy().T).T + d).reshape(200, N + 1, -1)
        Jp = lqr_cost(xp, up, Q, R, Q_f, ref)
        assert bool((Jp > J).all()), (scale, float((Jp - J).min()))


def test_infinite_horizon_equals_scipy_dare():
    for seed in range(3):
        A, B, Q, R, *_ = random_problem(seed, n=4, m=2)
        P_ref = sla.solve_discrete_are(A, B, Q, R)
        K_ref = np.linalg.solve(R + B.T @ P_ref @ B, B.T @ P_ref @ A)
        P, K = lqr_infinite_horizon(A, B, Q, R)
        np.testing.assert_allclose(P.numpy(), P_ref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(K.numpy(), K_ref, rtol=1e-8, atol=1e-10)
        # the finite-horizon recursion approaches the same fixed point from P_N = Q_f
        sol = lqr_backward(A, B, Q, R, 400)
        np.testing.assert_allclose(sol.P[0].numpy(), P_ref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(sol.K[0].numpy(), K_ref, rtol=1e-8, atol=1e-10)


def test_infinite_horizon_unstabilizable_raises():
    A = np.diag([1.5, 0.5])
    B = np.array([[0.0], [1.0]])  # the unstable mode is not reachable
    with pytest.raises(ValueError, match="^A:"):
        lqr_infinite_horizon(A, B, np.eye(2), np.eye(1), max_iter=2000)


@pytest.mark.parametrize("singular_q", [False, True])
def test_riccati_is_kalman_covariance_recursion_with_dual_matrices(singular_q):
    """Kalman's duality (Eq. plan-duality): the package's Kalman filter with F = A^T, H = B^T,
    process noise Q, observation noise R and prior covariance Q_f reproduces P_t backwards, and
    its gain L gives the LQR gain K_t = L^T A."""
    A, B, Q, R, Q_f, c, ref, _ = random_problem(3, n=4, m=2, N=9)
    if singular_q:
        Q = np.diag([1.0, 0.0, 0.5, 0.0])   # track only some coordinates
    N = ref.shape[0] - 1
    sol = lqr_backward(A, B, Q, R, N, Q_f, c, ref)  # P does not depend on c or ref
    P_kf = riccati_by_kalman(A, B, Q, R, N, Q_f)
    torch.testing.assert_close(P_kf, sol.P, rtol=1e-10, atol=1e-10)
    Bt = torch.as_tensor(B)
    for t in range(N):
        prior_cov = P_kf[t + 1]                                  # filter step N - t - 1
        S = Bt.T @ prior_cov @ Bt + torch.as_tensor(R)           # innovation covariance
        L = prior_cov @ Bt @ torch.linalg.inv(S)                 # Kalman gain
        torch.testing.assert_close(L.T @ torch.as_tensor(A), sol.K[t], rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(S, sol.S[t], rtol=1e-10, atol=1e-10)


def test_lqr_by_rts_smoothing_equals_lqr():
    """Control as inference (Eq. plan-cai): RTS-smoothed means of the model with actions as process
    noise and references as observations = the LQR trajectory (Q_f = Q)."""
    for seed in range(3):
        A, B, Q, R, _, c, ref, x0 = random_problem(seed, n=3, m=1, N=8)
        N = ref.shape[0] - 1
        sol = lqr_backward(A, B, Q, R, N, Q, c, ref)
        x, u = lqr_rollout(sol, A, B, x0, c)
        xs, us = lqr_by_smoothing(A, B, Q, R, x0, N, c, ref)
        scale = 1.0 + float(x.abs().max())
        assert float((xs - x).abs().max()) < 1e-7 * scale
        assert float((us - u).abs().max()) < 1e-7 * scale


def test_lqr_input_errors():
    A, B, Q, R, Q_f, c, ref, x0 = random_problem(0)
    with pytest.raises(ValueError, match="^A:"):
        lqr_backward(A[:, :2], B, Q, R, 3)
    with pytest.raises(ValueError, match="^B:"):
        lqr_backward(A, B[:2], Q, R, 3)
    with pytest.raises(ValueError, match="^R:"):
        lqr_backward(A, B, Q, -R, 3)
    with pytest.raises(ValueError, match="^Q:"):
        lqr_backward(A, B, -Q, R, 3)
    with pytest.raises(ValueError, match="^horizon:"):
        lqr_backward(A, B, Q, R, 0)
    with pytest.raises(ValueError, match="^ref:"):
        lqr_backward(A, B, Q, R, 3, ref=ref)          # ref has N + 1 = 7 rows, horizon 3 needs 4
    bad = B.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="^B:"):
        lqr_backward(A, bad, Q, R, 3)
    with pytest.raises(ValueError, match="^Q:"):
        lqr_by_smoothing(A, B, np.diag([1.0, 0.0, 1.0]), R, x0, 3)   # needs Q positive definite


# ---------------------------------------------------------------------------------------------
# Learned linear model (ARX)
# ---------------------------------------------------------------------------------------------


def random_arx(order: int, do: int = 2, da: int = 2, seed: int = 0) -> LinearARX:
    g = torch.Generator().manual_seed(seed)
    model = LinearARX(do, da, order).double()
    with torch.no_grad():
        model.weight.copy_(0.3 * torch.randn(do, order * (do + da), generator=g, dtype=DT))
        model.bias.copy_(torch.randn(do, generator=g, dtype=DT))
    return model


@pytest.mark.parametrize("order", [1, 2, 3])
def test_arx_state_space_reproduces_the_arx(order):
    model = random_arx(order)
    ss = arx_state_space(model)
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(1, 12, 2, generator=g, dtype=DT)
    act = torch.randn(1, 12, 2, generator=g, dtype=DT)
    pred, _ = model(obs, act)                 # pred[:, t] predicts obs[:, t + 1]
    for t in range(order - 1, 10):
        s = ss.state(obs[0, :t + 1], act[0, :t])
        nxt = ss.A @ s + ss.B @ act[0, t] + ss.c
        torch.testing.assert_close(nxt[:2], pred[0, t], rtol=1e-12, atol=1e-12)
        # the other blocks are the shifted lags, exactly
        s_next = ss.state(obs[0, :t + 2], act[0, :t + 1])
        assert torch.equal(nxt[2:], s_next[2:])


def linear_system_data(A, B, c, n_seq=16, T=120, noise=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    n, m = B.shape
    obs = np.zeros((n_seq, T, n))
    act = rng.normal(size=(n_seq, T, m))
    x = rng.normal(size=(n_seq, n))
    for t in range(T):
        obs[:, t] = x
        x = x @ A.T + act[:, t] @ B.T + c + noise * rng.normal(size=(n_seq, n))
    return torch.as_tensor(obs), torch.as_tensor(act)


A_LIN = np.array([[0.95, 0.1], [-0.2, 0.9]])
B_LIN = np.array([[0.0], [0.5]])
C_LIN = np.array([0.05, -0.02])


@pytest.mark.parametrize("order", [1, 2])
def test_fitted_arx_gives_the_true_lqr_gains(order):
    """An ARX fitted on data of a linear system plans like the true LQR. Order 1: the gains
    themselves agree. Order 2: the lags are (nearly) collinear with the current observation on
    the data, so the gains on the augmented state are not unique; the actions planned from real
    histories are what must agree."""
    obs, act = linear_system_data(A_LIN, B_LIN, C_LIN)
    model = LinearARX.fit(obs, act, order=order, ridge=1e-8)
    ss = arx_state_space(model)
    w, r, N = np.array([1.0, 0.3]), np.array([0.1]), 20
    if order == 1:
        true = lqr_backward(A_LIN, B_LIN, np.diag(w), np.diag(r), N)
        fitted = lqr_backward(ss.A, ss.B, np.diag(w), np.diag(r), N)
        assert float((fitted.K - true.K).abs().max()) < 1e-2 * float(true.K.abs().max())
    target = np.array([0.5, -0.3])
    sol = lqr_backward(A_LIN, B_LIN, np.diag(w), np.diag(r), N, None, C_LIN, target)
    for seq, t in ((0, 10), (3, 50), (7, 90)):
        hist_obs, hist_act = obs[seq, t - order + 1:t + 1], act[seq, t - order + 1:t]
        u_arx, _ = arx_lqr(model, hist_obs, hist_act, target, w, r, N)
        _, u_true = lqr_rollout(sol, A_LIN, B_LIN, hist_obs[-1], C_LIN)
        assert float((u_arx - u_true).abs().max()) < 2e-2 * float(u_true.abs().max())


# ---------------------------------------------------------------------------------------------
# 2. Sampling planner
# ---------------------------------------------------------------------------------------------

DTI = 0.1
A_DI = np.array([[1.0, DTI], [0.0, 1.0]])           # double integrator
B_DI = np.array([[0.5 * DTI ** 2], [DTI]])
W_DI, R_DI, H_DI = np.array([1.0, 0.1]), np.array([0.05]), 15
TARGET_DI, X0_DI = np.array([1.0, 0.0]), np.array([0.0, 0.0])
CEM = dict(method="cem", n_samples=512, n_iters=10, elite_frac=0.1)
MPPI = dict(method="mppi", n_samples=1024, n_iters=20, temperature=1.0, momentum=0.5)


def di_problem():
    cost = QuadraticCost(torch.as_tensor(W_DI), torch.as_tensor(R_DI))
    pred = linear_predictor(A_DI, B_DI)
    obs, act = torch.as_tensor(X0_DI)[None], torch.zeros(0, 1, dtype=DT)
    return cost, pred, obs, act


def plan_cost(cost, pred, obs, act, actions):
    mean, var = pred(obs, act, actions[None])
    return float(cost(mean, var, actions[None], torch.as_tensor(TARGET_DI).expand(H_DI, 2))[0])


@pytest.mark.parametrize("kind", ["cem", "mppi"])
def test_planner_reaches_the_lqr_optimum(kind):
    """Unbounded (wide bounds) double integrator, quadratic cost: the LQR open-loop optimum is the
    analytic reference. Tolerances: cost within 1 % of the optimum; first action within 5 % (CEM)
    / 15 % (MPPI); measured over 20 seeds: worst 0.04 % / 0.34 % in cost, 2.3 % / 7.8 % in a_0."""
    cost, pred, obs, act = di_problem()
    sol = lqr_backward(A_DI, B_DI, np.diag(W_DI), np.diag(R_DI), H_DI, None, None, TARGET_DI)
    _, u_opt = lqr_rollout(sol, A_DI, B_DI, X0_DI)
    J_opt = plan_cost(cost, pred, obs, act, u_opt)
    # the planner's cost and the LQR cost differ by the constant x_0 term only
    assert J_opt == pytest.approx(float(sol.value(torch.as_tensor(X0_DI))) - float(
        (torch.as_tensor(X0_DI - TARGET_DI) ** 2 * torch.as_tensor(W_DI)).sum()), rel=1e-10)
    cfg, a0_tol = (CEM, 0.05) if kind == "cem" else (MPPI, 0.15)
    for seed in range(3):
        planner = SamplingPlanner(pred, cost, H_DI, -20.0, 20.0, init_std=5.0, seed=seed, **cfg)
        res = planner.plan(obs, act, TARGET_DI)
        assert res.cost == pytest.approx(plan_cost(cost, pred, obs, act, res.actions), rel=1e-12)
        assert res.cost <= 1.01 * J_opt
        assert abs(float(res.actions[0, 0] / u_opt[0, 0]) - 1.0) < a0_tol


def test_cem_reaches_the_box_constrained_optimum():
    """Active bounds: the reference is scipy's L-BFGS-B on the exact quadratic cost."""
    cost, pred, obs, act = di_problem()
    low, high = -2.0, 2.0
    G, d = dense_cost_matrices(A_DI, B_DI, np.zeros(2), X0_DI, H_DI)
    W = np.kron(np.eye(H_DI + 1), np.diag(W_DI))
    W[:2, :2] = 0.0                                  # the planner does not score x_0
    r = np.tile(TARGET_DI, H_DI + 1)
    Rb = np.kron(np.eye(H_DI), np.diag(R_DI))

    def f(u):
        e = G @ u + d - r
        return e @ W @ e + u @ Rb @ u, 2 * G.T @ W @ e + 2 * Rb @ u

    ref = sopt.minimize(f, np.zeros(H_DI), jac=True, method="L-BFGS-B", bounds=[(low, high)] * H_DI,
                        options=dict(ftol=1e-15, gtol=1e-12))
    assert ref.success and (np.isclose(ref.x, high)).any()       # a bound is active
    planner = SamplingPlanner(pred, cost, H_DI, low, high, seed=0, **CEM)
    res = planner.plan(obs, act, TARGET_DI)
    assert bool((res.actions >= low).all() and (res.actions <= high).all())
    assert res.cost == pytest.approx(f(res.actions[:, 0].numpy())[0], rel=1e-10)
    assert res.cost <= 1.01 * ref.fun
    assert abs(float(res.actions[0, 0]) - ref.x[0]) < 0.05


@pytest.mark.parametrize("kind", ["cem", "mppi"])
def test_cost_decreases_in_expectation(kind):
    """Averaged over 20 seeds, the cost of the sampling distribution's mean falls at every
    iteration on the convex problem; the best cost seen never increases in any run."""
    cost, pred, obs, act = di_problem()
    cfg = dict(CEM) if kind == "cem" else dict(MPPI, n_iters=10)
    runs = []
    for seed in range(20):
        planner = SamplingPlanner(pred, cost, H_DI, -20.0, 20.0, init_std=5.0, seed=100 + seed, **cfg)
        res = planner.plan(obs, act, TARGET_DI)
        assert bool((torch.diff(res.best_costs) <= 0).all())
        runs.append(res.mean_costs)
    avg = torch.stack(runs).mean(0)
    assert bool((torch.diff(avg) < 0).all()), avg
    assert float(avg[-1]) < 0.5 * float(avg[0])


def risky_predictor(obs_history, action_history, candidates):
    """One step, do = 1: a = +1 reaches the target in the mean but is poorly known (variance 1),
    a = -1 misses by 0.3 but is well known (variance 0.01)."""
    a = candidates[..., :1]
    return 0.15 * (1.0 - a), 0.01 + 0.99 * ((a + 1.0) / 2.0) ** 4


@pytest.mark.parametrize("kind", ["cem", "mppi"])
def test_risk_term_changes_the_choice(kind):
    grid = torch.linspace(-1, 1, 20001, dtype=DT)[:, None, None]
    chosen = {}
    for risk in (0.0, 1.0):
        cost = QuadraticCost(torch.ones(1, dtype=DT), torch.zeros(1, dtype=DT), risk=risk)
        m, v = risky_predictor(None, None, grid)
        a_grid = float(grid[torch.argmin(cost(m, v, grid, torch.zeros(1, 1, dtype=DT))), 0, 0])
        cfg = CEM if kind == "cem" else dict(MPPI, temperature=1e-3)
        planner = SamplingPlanner(risky_predictor, cost, 1, -1.0, 1.0, seed=0, **cfg)
        res = planner.plan(torch.zeros(1, 1, dtype=DT), torch.zeros(0, 1, dtype=DT), torch.zeros(1))
        assert abs(float(res.actions[0, 0]) - a_grid) < 0.02, (risk, a_grid, res.actions)
        chosen[risk] = (a_grid, float(res.var.sum()))
    assert chosen[0.0][0] > 0.99 and chosen[1.0][0] < 0.0      # the choice flips ...
    assert chosen[1.0][1] < 0.1 * chosen[0.0][1]                # ... to the well-known action


def test_planner_is_batched_seeded_and_warm_started():
    cost, pred, obs, act = di_problem()
    calls = []

    def counting(o, a, cand):
        calls.append(cand.shape[0])
        return pred(o, a, cand)

    planner = SamplingPlanner(counting, cost, H_DI, -20.0, 20.0, seed=3, **dict(CEM, n_iters=4))
    first = planner(obs, act, TARGET_DI)
    # one call per iteration with every candidate and the mean, then the final mean (and the best)
    assert calls[:4] == [513] * 4 and set(calls[4:]) == {1} and len(calls) <= 6
    res1 = planner.last_plan
    assert torch.equal(first, res1.actions[0])
    # warm start: the next plan starts from the previous plan shifted by one step
    shifted = torch.cat([res1.actions[1:], res1.actions[-1:]])
    res2 = planner.plan(obs, act, TARGET_DI)
    assert res2.mean_costs[0] == pytest.approx(plan_cost(cost, pred, obs, act, shifted), rel=1e-12)
    # the same seed gives the same plan after reset; another seed another plan
    planner.reset()
    again = planner.plan(obs, act, TARGET_DI)
    assert torch.equal(again.actions, res1.actions)
    other = SamplingPlanner(pred, cost, H_DI, -20.0, 20.0, seed=4, **dict(CEM, n_iters=4)).plan(obs, act, TARGET_DI)
    assert not torch.equal(other.actions, res1.actions)


@pytest.mark.parametrize("kwargs, arg", [
    (dict(horizon=0), "horizon"),
    (dict(horizon=-2), "horizon"),
    (dict(temperature=0.0), "temperature"),
    (dict(temperature=-1.0), "temperature"),
    (dict(elite_frac=0.0), "elite_frac"),
    (dict(elite_frac=1.5), "elite_frac"),
    (dict(action_low=1.0, action_high=-1.0), "action_low"),
    (dict(action_low=[0.0, 1.0]), "action_low"),
    (dict(action_high=float("nan")), "action_high"),
    (dict(method="random"), "method"),
    (dict(n_samples=1), "n_samples"),
    (dict(n_iters=0), "n_iters"),
    (dict(init_std=0.0), "init_std"),
    (dict(momentum=1.0), "momentum"),
    (dict(predict=3), "predict"),
])
def test_planner_constructor_errors(kwargs, arg):
    cost, pred, _, _ = di_problem()
    args = dict(predict=pred, cost=cost, horizon=H_DI, action_low=-1.0, action_high=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"^{arg}:"):
        SamplingPlanner(**args)


def test_planner_input_errors():
    cost, pred, obs, act = di_problem()
    planner = SamplingPlanner(pred, cost, H_DI, -1.0, 1.0, n_samples=8, n_iters=1)
    with pytest.raises(ValueError, match="^target:"):
        planner.plan(obs, act, [float("nan"), 0.0])
    with pytest.raises(ValueError, match="^target:"):
        planner.plan(obs, act, torch.zeros(H_DI + 1, 2, dtype=DT))
    with pytest.raises(ValueError, match="^obs_history:"):
        planner.plan(torch.zeros(2, dtype=DT), act, TARGET_DI)
    with pytest.raises(ValueError, match="^action_history:"):
        planner.plan(obs, torch.zeros(1, 1, dtype=DT), TARGET_DI)
    bad = SamplingPlanner(lambda o, a, c: (torch.zeros(c.shape[0], 2, 2), torch.zeros(c.shape[0], 2, 2)),
                          cost, H_DI, -1.0, 1.0, n_samples=8, n_iters=1)
    with pytest.raises(ValueError, match="^predict:"):
        bad.plan(obs, act, TARGET_DI)
    neg = SamplingPlanner(lambda o, a, c: (torch.zeros(c.shape[0], H_DI, 2), -torch.ones(c.shape[0], H_DI, 2)),
                          cost, H_DI, -1.0, 1.0, n_samples=8, n_iters=1)
    with pytest.raises(ValueError, match="^predict:"):
        neg.plan(obs, act, TARGET_DI)
    for w, arg in ((torch.tensor([-1.0, 1.0]), "obs_weight"), (torch.zeros(2), "obs_weight")):
        with pytest.raises(ValueError, match=f"^{arg}:"):
            QuadraticCost(w, torch.ones(1))
    with pytest.raises(ValueError, match="^action_weight:"):
        QuadraticCost(torch.ones(2), torch.tensor([-0.1]))
    with pytest.raises(ValueError, match="^risk:"):
        QuadraticCost(torch.ones(2), torch.ones(1), risk=-1.0)


# ---------------------------------------------------------------------------------------------
# The world-model adapter
# ---------------------------------------------------------------------------------------------


def arx_state_space_rollout(model, obs_hist, act_hist, cand):
    """Open-loop predictions through Eq. (plan-arx-state), the independent path."""
    ss = arx_state_space(model)
    out = []
    for seq in cand:
        s = ss.state(obs_hist, act_hist)
        preds = []
        for a in seq:
            s = ss.A @ s + ss.B @ a + ss.c
            preds.append(s[:ss.obs_dim])
        out.append(torch.stack(preds))
    return torch.stack(out)


@pytest.mark.parametrize("order", [1, 3])
def test_world_model_predictor_matches_the_state_space_rollout(order):
    model = random_arx(order, seed=2)
    g = torch.Generator().manual_seed(5)
    obs_hist = torch.randn(6, 2, generator=g, dtype=DT)
    act_hist = torch.randn(5, 2, generator=g, dtype=DT)
    cand = torch.randn(7, 4, 2, generator=g, dtype=DT)
    predict = world_model_predictor(model)
    mean, var = predict(obs_hist, act_hist, cand)
    torch.testing.assert_close(mean, arx_state_space_rollout(model, obs_hist, act_hist, cand), rtol=1e-12, atol=1e-12)
    assert var.shape == mean.shape
    # a context of the last `order` observations is all an ARX needs
    short, _ = world_model_predictor(model, context_len=order + 1)(obs_hist, act_hist, cand)
    torch.testing.assert_close(short, mean, rtol=1e-12, atol=1e-12)


def test_world_model_predictor_normalisation_round_trip():
    """A linear ARX fitted on normalised data and wrapped with the statistics predicts what an ARX
    fitted on the raw data predicts (least squares is affine-equivariant; the bias is unpenalised)."""
    obs, act = linear_system_data(A_LIN, B_LIN, C_LIN, noise=0.05)
    obs = obs * torch.tensor([3.0, 0.2], dtype=DT) + torch.tensor([1.0, -2.0], dtype=DT)
    act = act * 4.0 + 0.5
    stats = dict(obs_mean=obs.mean((0, 1)), obs_std=obs.std((0, 1)), act_mean=act.mean((0, 1)),
                 act_std=act.std((0, 1)))
    raw = LinearARX.fit(obs, act, order=2, ridge=0.0)
    normed = LinearARX.fit((obs - stats["obs_mean"]) / stats["obs_std"],
                           (act - stats["act_mean"]) / stats["act_std"], order=2, ridge=0.0)
    cand = 4.0 * torch.randn(5, 6, 1, generator=torch.Generator().manual_seed(0), dtype=DT) + 0.5
    m_raw, v_raw = world_model_predictor(raw)(obs[0, :5], act[0, :4], cand)
    m_n, v_n = world_model_predictor(normed, stats)(obs[0, :5], act[0, :4], cand)
    torch.testing.assert_close(m_n, m_raw, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(v_n, v_raw, rtol=1e-9, atol=1e-9)


def test_world_model_predictor_with_an_acrkn_is_batch_consistent():
    from _helpers import linear_acrkn

    model = linear_acrkn(3, 2, seed=0)
    g = torch.Generator().manual_seed(0)
    obs_hist, act_hist = torch.randn(5, 3, generator=g, dtype=DT), torch.randn(4, 2, generator=g, dtype=DT)
    cand = torch.randn(6, 4, 2, generator=g, dtype=DT)
    predict = world_model_predictor(model)
    mean, var = predict(obs_hist, act_hist, cand)
    assert bool((var > 0).all())
    for j in (0, 5):
        m1, v1 = predict(obs_hist, act_hist, cand[j:j + 1])
        torch.testing.assert_close(m1[0], mean[j], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(v1[0], var[j], rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# 3. Simulators and the closed loop
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("payload", [0.0, 1.3])
def test_two_link_arm_env_steps_equal_one_rollout(payload):
    rng = np.random.default_rng(0)
    T = 25
    refs = rng.uniform(-0.6, 0.6, size=(T + 1, 2))
    state0 = np.array([0.1, -0.2, 0.3, 0.0])
    env = TwoLinkArmEnv(payload=payload)
    ref_states, ref_torques = rollout_two_link_arm(state0[None], refs[None], np.zeros((1, T + 1, 2)),
                                                   np.full((1, T + 1), payload))
    s, stepped = state0, [state0]
    for t in range(T):
        s = env.step(s, refs[t])
        stepped.append(s)
    np.testing.assert_array_equal(np.stack(stepped), ref_states[0])
    # torque mode: applying the PD loop's torques directly reproduces the PD trajectory
    env_tau = TwoLinkArmEnv(payload=payload, action="torque")
    s, stepped = state0, [state0]
    for t in range(T):
        s = env_tau.step(s, ref_torques[0, t])
        stepped.append(s)
    np.testing.assert_allclose(np.stack(stepped), ref_states[0], rtol=1e-12, atol=1e-12)
    # the batched rollout equals stepping each sequence
    acts = rng.uniform(-0.6, 0.6, size=(3, 6, 2))
    batch = env.rollout(state0, acts)
    for j in range(3):
        s = state0
        for k in range(6):
            s = env.step(s, acts[j, k])
            np.testing.assert_allclose(batch[j, k], s, rtol=1e-13, atol=1e-13)


def test_memory_arm_env_steps_equal_one_rollout():
    rng = np.random.default_rng(1)
    T = 40
    u = np.clip(rng.normal(0, 0.6, size=(T, 2)), -1, 1)
    env = MemoryArmEnv()
    rec, final = rollout_memory_arm(u[None], initial_state(1, MEMORY_PARAMS))
    s, angles = env.initial_state(), []
    for t in range(T):
        angles.append(env.observe(s))
        s = env.step(s, u[t])
    np.testing.assert_array_equal(np.stack(angles), rec["angle"][0])
    for key in final:
        np.testing.assert_array_equal(s[key], final[key])
    acts = np.clip(rng.normal(0, 0.6, size=(3, 5, 2)), -1, 1)
    batch = env.rollout(s, acts)
    for j in range(3):
        sj = s
        for k in range(5):
            sj = env.step(sj, acts[j, k])
            np.testing.assert_allclose(batch[j, k], env.observe(sj), rtol=1e-13, atol=1e-13)


class TimeVaryingLQR:
    """The finite-horizon LQR feedback u_t = -K_t x_t + k_t, with t read from the history length."""

    def __init__(self, sol, start):
        self.sol, self.start = sol, start

    def __call__(self, obs_history, action_history, target, state=None):
        t = obs_history.shape[0] - self.start
        return self.sol.action(obs_history[-1], t)


def test_closed_loop_with_lqr_feedback_equals_the_lqr_rollout():
    A, B, Q, R, _, c, ref, x0 = random_problem(2, n=3, m=2, N=10)
    N = ref.shape[0] - 1
    w = np.array([1.0, 0.5, 2.0])
    target = ref[3]
    sol = lqr_backward(A, B, np.diag(w), R, N, None, c, target)
    x, u = lqr_rollout(sol, A, B, x0, c)
    env = LinearEnv(A, B, c)
    cost = QuadraticCost(torch.as_tensor(w), torch.as_tensor(np.diag(R).copy()))
    R_diag = np.diag(np.diag(R))                   # the closed loop scores a diagonal action cost
    res = closed_loop(env, TimeVaryingLQR(sol, 1), x0, torch.as_tensor(x0)[None], torch.zeros(0, 2, dtype=DT),
                      target, N, cost, tol=1e-6)
    torch.testing.assert_close(res.obs, x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.actions, u, rtol=1e-12, atol=1e-12)
    J = float(lqr_cost(x, u, np.diag(w), R_diag, None, target)) - float(((x0 - target) ** 2 * w).sum())
    assert res.total_cost == pytest.approx(J, rel=1e-12)


def test_arx_lqr_policy_closed_loop_matches_the_true_lqr():
    obs, act = linear_system_data(A_LIN, B_LIN, C_LIN)
    model = LinearARX.fit(obs, act, order=2, ridge=1e-8)
    w, r, H = np.array([1.0, 0.3]), np.array([0.1]), 20
    target = np.array([0.5, -0.3])
    env = LinearEnv(A_LIN, B_LIN, C_LIN)
    cost = QuadraticCost(torch.as_tensor(w), torch.as_tensor(r))
    x0 = np.array([-0.4, 0.2])
    state, oh, ah = warm_up(env, x0, np.zeros((1, 1)))
    res = closed_loop(env, ARXLQRPolicy(model, w, r, H), state, oh, ah, target, 30, cost, tol=0.05,
                      success_steps=5)

    class TrueLQR:  # receding-horizon LQR with the true matrices
        def __call__(self, o, a, tg, state=None):
            sol = lqr_backward(A_LIN, B_LIN, np.diag(w), np.diag(r), H, None, C_LIN, target)
            return sol.action(o[-1], 0)

    ref = closed_loop(env, TrueLQR(), state, oh, ah, target, 30, cost, tol=0.05, success_steps=5)
    assert res.total_cost == pytest.approx(ref.total_cost, rel=1e-2)
    zero = closed_loop(env, ConstantPolicy([0.0]), state, oh, ah, target, 30, cost, tol=0.05)
    assert res.total_cost < zero.total_cost


def test_physics_planner_closed_loop_beats_the_lower_references():
    """Two-link arm with a 1 kg payload, PD-target actions: the true simulator as the model (upper
    reference) reaches the target angles; zero and random actions do not."""
    env = TwoLinkArmEnv(payload=1.0)
    target = np.array([0.4, -0.5, 0.0, 0.0])
    cost = QuadraticCost(torch.tensor([1.0, 1.0, 0.0, 0.0]), torch.tensor([1e-3, 1e-3]))
    state, oh, ah = warm_up(env, np.zeros(4), np.zeros((2, 2)))
    planner = SamplingPlanner(simulator_predictor(env), cost, 8, -1.5, 1.5, n_samples=48, n_iters=3,
                              init_std=0.5, seed=0)
    kw = dict(tol=0.03, success_steps=5)
    res = closed_loop(env, planner, state, oh, ah, target, 30, cost, **kw)
    zero = closed_loop(env, ConstantPolicy([0.0, 0.0]), state, oh, ah, target, 30, cost, **kw)
    rand = closed_loop(env, RandomPolicy([-1.5, -1.5], [1.5, 1.5], seed=0), state, oh, ah, target, 30, cost, **kw)
    assert res.success and not zero.success and not rand.success
    assert res.total_cost < 0.5 * min(zero.total_cost, rand.total_cost)
    assert res.pred_mean is not None and res.pred_mean.shape == (30, 8, 4)
    # the upper reference's predictions are exact: its first predicted step is what happened
    torch.testing.assert_close(res.pred_mean[:, 0], res.obs[1:], rtol=1e-10, atol=1e-10)


def test_physics_planner_on_the_memory_arm():
    env = MemoryArmEnv()
    target = np.array([0.15, -0.1])
    cost = QuadraticCost(torch.ones(2, dtype=DT), torch.full((2,), 1e-4, dtype=DT))
    state, oh, ah = warm_up(env, env.initial_state(), np.zeros((3, 2)))
    planner = SamplingPlanner(simulator_predictor(env), cost, 10, env.action_low, env.action_high,
                              n_samples=48, n_iters=3, seed=0)
    res = closed_loop(env, planner, state, oh, ah, target, 40, cost, tol=0.02, success_steps=5)
    zero = closed_loop(env, ConstantPolicy([0.0, 0.0]), state, oh, ah, target, 40, cost, tol=0.02, success_steps=5)
    assert res.success and not zero.success
    assert res.total_cost < 0.5 * zero.total_cost
    # the plans are kept, their first actions are the ones sent, and the simulator is exact about them
    assert res.plan_actions.shape == (40, 10, 2) and zero.plan_actions is None
    torch.testing.assert_close(res.plan_actions[:, 0], res.actions, rtol=0, atol=0)
    assert np.abs(plan_prediction_errors(env, res, state)).max() < 1e-10


def test_plan_prediction_errors_of_a_wrong_linear_model_by_hand():
    """A planner through a model with the wrong input matrix: the errors along its plans equal the
    difference of the two linear recursions, written out here with numpy."""
    env = LinearEnv(A_DI, B_DI)
    B_wrong = 0.6 * np.asarray(B_DI)
    cost = QuadraticCost(torch.as_tensor(W_DI), torch.as_tensor(R_DI))
    planner = SamplingPlanner(linear_predictor(A_DI, B_wrong), cost, 4, -3.0, 3.0, n_samples=16, n_iters=2, seed=0)
    res = closed_loop(env, planner, X0_DI, torch.as_tensor(X0_DI)[None], torch.zeros(0, 1, dtype=DT),
                      TARGET_DI, 6, cost, tol=1.0)
    err = plan_prediction_errors(env, res, X0_DI)
    assert err.shape == (6, 4, 2)
    x_true = [np.asarray(X0_DI, dtype=float)] + [np.asarray(x, dtype=float) for x in res.states[:-1]]
    for t in range(6):
        u = res.plan_actions[t].numpy()
        xm = xs = x_true[t]
        for k in range(4):
            xm, xs = np.asarray(A_DI) @ xm + B_wrong @ u[k], np.asarray(A_DI) @ xs + np.asarray(B_DI) @ u[k]
            np.testing.assert_allclose(err[t, k], xm - xs, rtol=1e-9, atol=1e-12)
    assert np.abs(err).max() > 1e-3                    # the wrong model is wrong
    zero = closed_loop(env, ConstantPolicy([0.0]), X0_DI, torch.as_tensor(X0_DI)[None], torch.zeros(0, 1, dtype=DT),
                       TARGET_DI, 3, cost, tol=1.0)
    with pytest.raises(ValueError, match="^run:"):
        plan_prediction_errors(env, zero, X0_DI)


def test_ensemble_predictor_is_the_mixture_of_two_linear_models():
    """Two linear-Gaussian models with different input matrices and process noises: the ensemble's
    mean and variance are the moments of their equal-weight mixture, computed here with numpy from
    the mixture's definition E[o^2] - E[o]^2; an ensemble of one model with itself is that model."""
    A = np.array([[0.9, 0.1], [0.0, 0.8]])
    B1, B2 = np.array([[0.5], [1.0]]), np.array([[0.2], [1.5]])
    w1, w2 = np.array([1e-2, 2e-2]), np.array([3e-2, 1e-3])
    p1, p2 = linear_predictor(A, B1, process_var=w1), linear_predictor(A, B2, process_var=w2)
    gen = torch.Generator().manual_seed(0)
    obs, act = torch.randn(3, 2, generator=gen, dtype=DT), torch.randn(2, 1, generator=gen, dtype=DT)
    cand = torch.randn(5, 4, 1, generator=gen, dtype=DT)
    mean, var = ensemble_predictor([p1, p2])(obs, act, cand)
    (m1, v1), (m2, v2) = (tuple(t.numpy() for t in p(obs, act, cand)) for p in (p1, p2))
    second_moment = 0.5 * ((v1 + m1 ** 2) + (v2 + m2 ** 2))
    np.testing.assert_allclose(mean.numpy(), 0.5 * (m1 + m2), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(var.numpy(), second_moment - (0.5 * (m1 + m2)) ** 2, rtol=1e-9, atol=1e-14)
    assert (var.numpy() >= 0.5 * (v1 + v2)).all()        # disagreement only adds variance
    same_mean, same_var = ensemble_predictor((p1, p1))(obs, act, cand)
    torch.testing.assert_close(same_mean, torch.as_tensor(m1), rtol=0, atol=0)
    torch.testing.assert_close(same_var, torch.as_tensor(v1), rtol=0, atol=0)
    # inside the planner, an ensemble of one model with itself plans exactly like the model
    cost = QuadraticCost(torch.ones(2, dtype=DT), torch.full((1,), 0.1, dtype=DT), risk=1.0)
    plans = [SamplingPlanner(p, cost, 4, -2.0, 2.0, n_samples=16, n_iters=2, seed=3).plan(obs, act, torch.zeros(4, 2, dtype=DT))
             for p in (p1, ensemble_predictor([p1, p1]))]
    torch.testing.assert_close(plans[0].actions, plans[1].actions, rtol=0, atol=0)


def test_ensemble_predictor_input_errors():
    p = linear_predictor(A_DI, B_DI)
    for bad in ([p], [], p, "p"):
        with pytest.raises(ValueError, match="^predictors:"):
            ensemble_predictor(bad)
    with pytest.raises(ValueError, match=r"^predictors\[1\]:"):
        ensemble_predictor([p, 3])
    with pytest.raises(ValueError, match=r"^predictors\[0\]:"):
        ensemble_predictor([simulator_predictor(LinearEnv(A_DI, B_DI)), p])
    wide = linear_predictor(np.eye(3), np.ones((3, 1)))
    obs = torch.zeros(2, 2, dtype=DT)
    with pytest.raises(ValueError, match="^predictors:"):
        ensemble_predictor([p, lambda o, a, c: wide(torch.zeros(2, 3, dtype=DT), a, c)])(obs, obs[:1, :1], torch.zeros(4, 3, 1, dtype=DT))


def test_command_statistics_against_numpy():
    a = np.random.default_rng(0).uniform(-1, 1, size=(3, 20, 2))
    change, near = command_statistics(a)
    assert change == pytest.approx(np.abs(np.diff(a, axis=1)).mean(), rel=1e-12)
    assert near == pytest.approx((np.abs(a) > 0.9).mean(), rel=1e-12)
    assert command_statistics(a[0], near=0.5)[1] == pytest.approx((np.abs(a[0]) > 0.5).mean())
    with pytest.raises(ValueError, match="^actions:"):
        command_statistics(a[:, :1])
    with pytest.raises(ValueError, match="^actions:"):
        command_statistics(np.full((4, 2), np.nan))
    with pytest.raises(ValueError, match="^near:"):
        command_statistics(a, near=0.0)


def test_model_predictors_never_receive_the_true_state():
    env = LinearEnv(A_DI, B_DI)
    cost = QuadraticCost(torch.as_tensor(W_DI), torch.as_tensor(R_DI))
    pred = linear_predictor(A_DI, B_DI)

    def strict(o, a, cand):          # no `state` parameter: passing one would raise TypeError
        return pred(o, a, cand)

    planner = SamplingPlanner(strict, cost, 5, -3.0, 3.0, n_samples=16, n_iters=2)
    res = closed_loop(env, planner, X0_DI, torch.as_tensor(X0_DI)[None], torch.zeros(0, 1, dtype=DT),
                      TARGET_DI, 3, cost, tol=1.0, obs_noise=0.01, seed=1)
    assert res.obs.shape == (4, 2)
    with pytest.raises(ValueError, match="^state:"):
        simulator_predictor(env)(res.obs, res.actions[:-1], torch.zeros(2, 3, 1, dtype=DT))


def test_closed_loop_input_errors():
    env = LinearEnv(A_DI, B_DI)
    cost = QuadraticCost(torch.as_tensor(W_DI), torch.as_tensor(R_DI))
    pol = ConstantPolicy([0.0])
    oh, ah = torch.as_tensor(X0_DI)[None], torch.zeros(0, 1, dtype=DT)
    args = (env, pol, X0_DI, oh, ah, TARGET_DI, 5, cost)
    for kwargs, arg in ((dict(tol=0.0), "tol"), (dict(tol=0.1, success_steps=6), "success_steps"),
                        (dict(tol=0.1, obs_noise=-1.0), "obs_noise")):
        with pytest.raises(ValueError, match=f"^{arg}:"):
            closed_loop(*args, **kwargs)
    with pytest.raises(ValueError, match="^steps:"):
        closed_loop(env, pol, X0_DI, oh, ah, TARGET_DI, 0, cost, tol=0.1)
    with pytest.raises(ValueError, match="^targets:"):
        closed_loop(env, pol, X0_DI, oh, ah, [math.nan, 0.0], 5, cost, tol=0.1)
    with pytest.raises(ValueError, match="^cost:"):
        closed_loop(env, pol, X0_DI, oh, ah, TARGET_DI, 5, QuadraticCost(torch.ones(3), torch.ones(1)), tol=0.1)
    with pytest.raises(ValueError, match="^action_history:"):
        closed_loop(env, pol, X0_DI, oh, torch.zeros(1, 1, dtype=DT), TARGET_DI, 5, cost, tol=0.1)
    with pytest.raises(ValueError, match="^policy:"):
        closed_loop(env, ConstantPolicy([0.0, 1.0]), X0_DI, oh, ah, TARGET_DI, 5, cost, tol=0.1)
    with pytest.raises(ValueError, match="^payload:"):
        TwoLinkArmEnv(payload=-1.0)
    with pytest.raises(ValueError, match="^action:"):
        TwoLinkArmEnv(action="velocity")
    with pytest.raises(ValueError, match="^state:"):
        TwoLinkArmEnv().step(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="^actions:"):
        MemoryArmEnv().step(MemoryArmEnv().initial_state(), np.array([np.nan, 0.0]))


def test_adapter_and_arx_input_errors():
    model = random_arx(2)
    with pytest.raises(ValueError, match="^model:"):
        world_model_predictor(3)
    with pytest.raises(ValueError, match="^context_len:"):
        world_model_predictor(model, context_len=0)
    with pytest.raises(ValueError, match="^stats:"):
        world_model_predictor(model, dict(obs_mean=torch.zeros(2), obs_std=torch.ones(2)))
    with pytest.raises(ValueError, match=r"^stats\['obs_std'\]:"):
        world_model_predictor(model, dict(obs_mean=torch.zeros(2), obs_std=torch.zeros(2),
                                          act_mean=torch.zeros(2), act_std=torch.ones(2)))
    with pytest.raises(ValueError, match="^model:"):
        arx_state_space(torch.nn.Linear(2, 2))
    ss = arx_state_space(model)
    with pytest.raises(ValueError, match="^obs_history:"):
        ss.state(torch.zeros(1, 2, dtype=DT), torch.zeros(0, 2, dtype=DT))     # order 2 needs 2 steps
    with pytest.raises(ValueError, match="^action_history:"):
        ss.state(torch.zeros(3, 2, dtype=DT), torch.zeros(3, 2, dtype=DT))
    with pytest.raises(ValueError, match="^obs_weight:"):
        arx_lqr(model, torch.zeros(2, 2, dtype=DT), torch.zeros(1, 2, dtype=DT), torch.zeros(2),
                [-1.0, 1.0], [1.0, 1.0], 5)
    with pytest.raises(ValueError, match="^target:"):
        arx_lqr(model, torch.zeros(2, 2, dtype=DT), torch.zeros(1, 2, dtype=DT), torch.zeros(4, 2),
                [1.0, 1.0], [1.0, 1.0], 5)


def test_float32_model_and_planner():
    """A float32 world model is fed in its dtype and its predictions come back in the planner's
    dtype, equal to the float64 model's to float32 precision; a float32 planner plans with it."""
    model64 = random_arx(2, seed=4)
    model32 = random_arx(2, seed=4).float()
    g = torch.Generator().manual_seed(2)
    obs_hist, act_hist = torch.randn(4, 2, generator=g, dtype=DT), torch.randn(3, 2, generator=g, dtype=DT)
    cand = torch.randn(5, 3, 2, generator=g, dtype=DT)
    m64, _ = world_model_predictor(model64)(obs_hist, act_hist, cand)
    m32, _ = world_model_predictor(model32)(obs_hist, act_hist, cand)
    assert m32.dtype == DT
    torch.testing.assert_close(m32, m64, rtol=1e-5, atol=1e-5)
    cost = QuadraticCost(torch.ones(2), torch.full((2,), 0.1))
    planner = SamplingPlanner(world_model_predictor(model32), cost, 3, -1.0, 1.0, n_samples=32, n_iters=2,
                              dtype=torch.float32)
    res = planner.plan(obs_hist, act_hist, torch.zeros(2))
    assert res.actions.dtype == torch.float32 and res.mean.dtype == torch.float32
    assert res.cost <= float(res.mean_costs[0])

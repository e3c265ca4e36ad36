r"""Chapter 7's closed-loop study: planning through learned world models on the memory arm.

``python -m pgm_wm.experiments ch7 --seeds 5 --budget 240 --jobs 2`` writes
``results/ch7_memory_arm.json``. The design (Chapter 7, Section 7.4):

* **Models** of Chapter 4's study, trained exactly as there (:func:`~pgm_wm.experiments.runner.train_model`
  with :func:`~pgm_wm.experiments.chapters.ch4_experiment`'s protocol and the same CPU budget per
  model and seed): the ac-RKN (difference readout) and the GRU; plus the linear ARX model fitted in
  closed form on the training split in radians, its order chosen among 1, 2 and 5 on validation
  (:func:`fit_arx`).
* **Tasks**: ``n_tasks`` target angle pairs drawn once (``task_seed``) uniformly inside the 10–90 %
  quantiles of the training split's angles per joint (:func:`planning_tasks`): targets the arm
  visits in the data, none of them a training sequence. Every policy and seed plans the same tasks.
* **Closed loop** (:func:`pgm_wm.planning.closed_loop`, Eq. plan-closed-loop): from rest, after a
  history of ``context`` steps with zero commands (the warm-up of Chapter 4's protocol), ``steps``
  control steps; at each step the policy plans ``horizon`` steps ahead, its first command goes to
  the simulator. Cost and success are measured in the simulator only.
* **Policies** (rows): CEM through the simulator from its true state (upper reference), LQR through
  the ARX model (exact, clipped), CEM through the ARX model, CEM through the ac-RKN, CEM through the
  GRU, zero commands and uniform random commands (lower references). Every CEM row uses the same
  settings (``n_samples``, ``n_iters``, ``elite_frac``) and, per seed and task, the same sampler
  seed.

The file stores, per policy, ``(seeds, tasks)`` arrays of the true total cost, success (0/1),
final tracking error (mean over the last 10 steps), the mean absolute command change per step and
the share of commands beyond 0.9 in magnitude (with the training split's values in
``data_commands``), for the CEM rows the RMSE of the model's predictions along the plans it chose
(every plan replayed in the simulator from the state where it was made; ``(seeds, tasks, H)``),
the wall time per seed, and, per trained model and seed, the training
record of Chapter 4's runner (steps, CPU seconds, best validation RMSE, the stopping rule's
verdict). :func:`planning_table` and :func:`planning_ratios` compute the chapter's tables from it
with the intervals of :mod:`pgm_wm.experiments.stats` (tasks as windows, paired over tasks).

A second study, ``python -m pgm_wm.experiments ch7_payload --seeds 5 --budget 240 --jobs 2``
(:func:`run_payload_study`, ``results/ch7_payload_arm.json``, Chapter 7, Section 7.6), plans on the
vertical payload arm with payloads the models never trained on: the HiP-RSSM of Chapter 5, whose task
is inferred from the previous window of interaction, against the task-blind Chapter 4 ac-RKN and the
simulator with the true and with the nominal payload. Its files have the same layout (plus
``payloads`` and ``regimes``; its on-plan RMSE is over the two joint angles), so the same tables read
them.

A third, ``python -m pgm_wm.experiments ch7_risk --seeds 5 --budget 240 --jobs 2``
(:func:`run_risk_study`, ``results/ch7_risk.json``, Chapter 7, Section 7.5), asks whether
penalising predicted variance (the risk term of Eq. plan-expected-cost) avoids a failure: the
targets of the memory-arm study with a stop :attr:`RiskProtocol.stop_margin` past each target,
touching it a failure (:func:`stop_overshoot`); planners through the ac-RKN and through the
ac-RKN + GRU ensemble (Eq. plan-ensemble), each without and with a risk weight chosen per seed on
separate validation targets; with the 2σ coverage of each model's predictions along the plans it chose.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from .results import provenance, write_json
from .stats import Interval, mean_interval, paired_mean_ratio

__all__ = ["PlanningProtocol", "PLANNING_MODELS", "POLICIES", "fit_arx", "planning_tasks", "run_planning_study",
           "PayloadProtocol", "PAYLOAD_MODELS", "PAYLOAD_POLICIES", "PAYLOAD_REGIMES", "payload_arm_params",
           "payload_tasks", "PayloadTaskRuns", "payload_closed_loops", "run_payload_study", "RiskProtocol",
           "RISK_POLICIES", "stop_overshoot", "run_risk_study", "check_planning_study", "load_planning_study",
           "planning_table", "planning_ratios"]

PLANNING_MODELS = ("ac-RKN (difference readout)", "GRU")
"""The trained models of Chapter 4's study that the study plans through."""

POLICIES = ("CEM + true simulator", "LQR through the ARX model", "CEM through the ARX model",
            "CEM through the ac-RKN", "CEM through the GRU", "zero commands", "random commands")
"""The rows of the study, in table order (upper reference first, lower references last)."""


def _check_protocol(protocol: Any, counts: Sequence[str]) -> None:
    """The checks every study protocol shares: ``counts`` positive ints, ``success_steps <= steps``,
    ``tol`` and the cost weights positive and finite, ``elite_frac`` in (0, 1]."""
    for name in counts:
        v = getattr(protocol, name)
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name}: must be a positive int, got {v!r}")
    if protocol.success_steps > protocol.steps:
        raise ValueError(f"success_steps: must be <= steps = {protocol.steps}, got {protocol.success_steps}")
    for name in ("tol", "obs_weight", "action_weight"):
        v = getattr(protocol, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: must be a positive finite number, got {v!r}")
    if not 0.0 < protocol.elite_frac <= 1.0:
        raise ValueError(f"elite_frac: must be in (0, 1], got {protocol.elite_frac!r}")


@dataclass(frozen=True)
class PlanningProtocol:
    """Settings of the closed-loop study (the same for every policy).

    ``context``: rest steps before the first command (the models' warm-up); ``horizon``: the
    planning horizon :math:`H`; ``steps``: control steps :math:`T`; a task succeeds when the largest
    joint error is at most ``tol`` (rad) on each of the last ``success_steps`` steps; the cost
    weights are ``obs_weight`` :math:`\\cdot I` and ``action_weight`` :math:`\\cdot I`; CEM draws
    ``n_samples`` candidates for ``n_iters`` iterations with ``elite_frac``; ``model_context``:
    the most recent observations a learned model sees."""

    context: int = 50
    horizon: int = 10
    steps: int = 50
    tol: float = 0.02
    success_steps: int = 5
    n_tasks: int = 16
    task_seed: int = 7
    obs_weight: float = 1.0
    action_weight: float = 1e-2
    n_samples: int = 64
    n_iters: int = 3
    elite_frac: float = 0.1
    model_context: int = 50

    def __post_init__(self) -> None:
        _check_protocol(self, ("context", "horizon", "steps", "success_steps", "n_tasks", "n_samples", "n_iters",
                               "model_context"))


def fit_arx(train: Any, valid: Any, orders: Sequence[int] = (1, 2, 5), horizon: int = 50) -> nn.Module:
    """The linear ARX model in original units (radians, valve commands), fitted in closed form on
    ``train`` (:class:`~pgm_wm.datasets.sequences.SequenceData`), its order chosen among ``orders``
    by the mean open-loop RMSE over ``1..horizon`` steps on ``valid`` (windows of ``horizon``
    steps after a 50-step context, stride 50), as in Chapter 4."""
    from ..baselines import LinearARX
    from ..evaluation import evaluate_open_loop

    obs_tr, act_tr = train.obs.double(), train.actions.double()
    obs_va, act_va = valid.obs.double(), valid.actions.double()
    fits = {p: LinearARX.fit(obs_tr, act_tr, order=p) for p in orders}
    score = {p: float(evaluate_open_loop(m, obs_va, act_va, 50, horizon, stride=50).rmse.mean())
             for p, m in fits.items()}
    return fits[min(score, key=score.get)]


def planning_tasks(train: Any, n_tasks: int, seed: int) -> np.ndarray:
    """``(n_tasks, do)`` targets drawn uniformly inside the 10–90 % quantiles of the training
    split's observations per dimension (seeded)."""
    obs = train.obs.double().reshape(-1, train.obs.shape[-1]).numpy()
    lo, hi = np.quantile(obs, [0.1, 0.9], axis=0)
    return np.random.default_rng(seed).uniform(lo, hi, size=(n_tasks, obs.shape[1]))


def _experiment(which: str) -> Any:
    """The chapter experiment whose models a study plans through: Chapter 4's on the memory arm
    (``"ch4"``) or Chapter 5's on the vertical payload arm (``"ch5_payload"``)."""
    from .chapters import ch4_experiment, ch5_experiment

    return ch4_experiment("memory_arm") if which == "ch4" else ch5_experiment("payload_arm")


def _train_one(task: tuple[str, str, int, float, int | None]
               ) -> tuple[str, int, dict[str, torch.Tensor], dict[str, Any]]:
    from .runner import train_model

    torch.set_num_threads(1)
    which, name, seed, budget_s, max_steps = task
    model, info = train_model(_experiment(which), name, seed, budget_s, max_steps=max_steps)
    return name, seed, {k: v.detach().clone() for k, v in model.state_dict().items()}, info


def _train_models(which: str, names: Sequence[str], seeds: list[int], budget_s: float, max_steps: int | None,
                  jobs: int) -> tuple[dict[int, dict[str, dict[str, torch.Tensor]]], dict[str, list[dict[str, Any]]]]:
    """Train every model of ``names`` for every seed (``jobs`` processes); returns the parameters
    per seed and model and the training records per model (in seed order)."""
    trained = _pool_map(_train_one, [(which, n, s, float(budget_s), max_steps) for s in seeds for n in names], jobs)
    states: dict[int, dict[str, dict[str, torch.Tensor]]] = {s: {} for s in seeds}
    training: dict[str, list[dict[str, Any]]] = {n: [None] * len(seeds) for n in names}  # type: ignore[list-item]
    for name, seed, state, info in trained:
        states[seed][name] = state
        training[name][seeds.index(seed)] = info
    return states, training


def _load_models(exp: Any, splits: Any, states: Mapping[str, Mapping[str, torch.Tensor]], seed: int
                 ) -> dict[str, nn.Module]:
    from ..training import set_seed

    models = {}
    for name, state in states.items():
        set_seed(seed)
        m = exp.models[name].build(splits)
        m.load_state_dict(state)
        models[name] = m.eval()
    return models


def _empty_record(policies: Sequence[str]) -> dict[str, Any]:
    return {name: {"cost": [], "success": [], "final_error": [], "command_change": [], "near_bounds": [],
                   "onplan_rmse": [], "wall_s": 0.0} for name in policies}


def _record_run(entry: dict[str, Any], env: Any, run: Any, state0: Any, wall_s: float,
                dims: Sequence[int] | None = None) -> None:
    """Append one closed-loop run's scores to a policy's record: true cost, success, final error
    (mean over the last 10 steps), command statistics and, for planners, the RMSE of the model's
    predictions along the plans it chose (every plan replayed in the simulator from the true
    state where it was made) over the observation dimensions ``dims`` (default: all)."""
    from ..planning import command_statistics, plan_prediction_errors

    entry["wall_s"] += wall_s
    entry["cost"].append(run.total_cost)
    entry["success"].append(float(run.success))
    entry["final_error"].append(float(run.error[-10:].mean()))
    change, near = command_statistics(run.actions)
    entry["command_change"].append(change)
    entry["near_bounds"].append(near)
    if run.plan_actions is not None:
        err = plan_prediction_errors(env, run, state0)
        if dims is not None:
            err = err[..., list(dims)]
        entry["onplan_rmse"].append(np.sqrt((err ** 2).mean(axis=(0, 2))).tolist())


def _memory_arm_start(p: PlanningProtocol) -> tuple[Any, Any, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The memory arm's simulator, its state, observation and command histories after ``p.context``
    rest steps with zero commands (where every closed loop starts), and the cost weights ``W``, ``R``."""
    from ..planning import MemoryArmEnv, warm_up

    env = MemoryArmEnv()
    state0, oh0, ah0 = warm_up(env, env.initial_state(), np.zeros((p.context - 1, env.action_dim)))
    W = torch.full((env.obs_dim,), p.obs_weight, dtype=torch.float64)
    R = torch.full((env.action_dim,), p.action_weight, dtype=torch.float64)
    return env, state0, oh0, ah0, W, R


def _seed_setup(task: tuple[int, dict[str, dict[str, torch.Tensor]], dict[str, Any]], protocol_cls: type,
                which: str = "ch4") -> tuple[int, Any, dict[str, Any], Any, dict[str, nn.Module]]:
    """Unpack one worker task ``(seed, model states, config)`` of a study on experiment ``which``
    (one thread): ``(seed, protocol, config, splits, the seed's trained models)``."""
    torch.set_num_threads(1)
    seed, states, cfg = task
    exp = _experiment(which)
    splits = exp.load()
    return seed, protocol_cls(**cfg["protocol"]), cfg, splits, _load_models(exp, splits, states, seed)


def _plan_seed(task: tuple[int, dict[str, dict[str, torch.Tensor]], dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    from ..planning import (ARXLQRPolicy, ConstantPolicy, QuadraticCost, RandomPolicy, SamplingPlanner, closed_loop,
                            command_statistics, simulator_predictor, world_model_predictor)

    seed, p, cfg, splits, models = _seed_setup(task, PlanningProtocol)
    env, state0, oh0, ah0, W, R = _memory_arm_start(p)
    arx = fit_arx(splits.train, splits.valid)
    cost = QuadraticCost(W, R)
    stats = splits.train.stats
    predictors = {"CEM + true simulator": simulator_predictor(env),
                  "CEM through the ARX model": world_model_predictor(arx, context_len=arx.order + 1),
                  "CEM through the ac-RKN": world_model_predictor(models[PLANNING_MODELS[0]], stats,
                                                                  context_len=p.model_context),
                  "CEM through the GRU": world_model_predictor(models[PLANNING_MODELS[1]], stats,
                                                               context_len=p.model_context)}
    tasks = np.asarray(cfg["tasks"], dtype=np.float64)
    out: dict[str, Any] = _empty_record(POLICIES)
    # the commands of the training split, for comparison with the planners' commands
    a_tr = splits.train.actions.double()
    out["_data_commands"] = dict(zip(("command_change", "near_bounds"), command_statistics(a_tr)))
    for i, target in enumerate(tasks):
        sampler_seed = 1000 * seed + i

        def cem(predict: Any) -> SamplingPlanner:
            return SamplingPlanner(predict, cost, p.horizon, env.action_low, env.action_high, method="cem",
                                   n_samples=p.n_samples, n_iters=p.n_iters, elite_frac=p.elite_frac,
                                   seed=sampler_seed)

        policies = {**{n: cem(pr) for n, pr in predictors.items()},
                    "LQR through the ARX model": ARXLQRPolicy(arx, W, R, p.horizon, env.action_low, env.action_high),
                    "zero commands": ConstantPolicy(np.zeros(env.action_dim)),
                    "random commands": RandomPolicy(env.action_low, env.action_high, seed=sampler_seed)}
        for name in POLICIES:
            policy = policies[name]
            t0 = time.perf_counter()
            run = closed_loop(env, policy, state0, oh0, ah0, target, p.steps, cost, tol=p.tol,
                              success_steps=p.success_steps)
            _record_run(out[name], env, run, state0, time.perf_counter() - t0)
    out["_arx_order"] = arx.order
    return seed, out


def _pool_map(fn: Any, tasks: list, jobs: int) -> list:
    if jobs <= 1 or len(tasks) <= 1:
        return [fn(t) for t in tasks]
    with mp.get_context("spawn").Pool(min(jobs, len(tasks))) as pool:
        return pool.map(fn, tasks, chunksize=1)


def _check_run_args(seeds: Sequence[int], budget_s: float) -> list[int]:
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"seeds: need distinct non-negative seeds, got {seeds}")
    if not (isinstance(budget_s, (int, float)) and math.isfinite(budget_s) and budget_s > 0):
        raise ValueError(f"budget_s: must be a positive finite number of CPU seconds, got {budget_s!r}")
    return seeds


def run_planning_study(seeds: Sequence[int], budget_s: float, out_path: str | None = None, *,
                       protocol: PlanningProtocol | None = None, jobs: int = 1,
                       max_steps: int | None = None) -> dict[str, Any]:
    """Train the :data:`PLANNING_MODELS` for every seed (``budget_s`` CPU seconds each, Chapter 4's
    protocol), then run every policy of :data:`POLICIES` on every task in closed loop; write the
    results to ``out_path`` (if given) and return them. ``jobs`` processes, one thread each."""
    from .chapters import ch4_experiment

    p = protocol or PlanningProtocol()
    seeds = _check_run_args(seeds, budget_s)
    wall0 = time.perf_counter()
    splits = ch4_experiment("memory_arm").load()
    tasks = planning_tasks(splits.train, p.n_tasks, p.task_seed)
    states, training = _train_models("ch4", PLANNING_MODELS, seeds, budget_s, max_steps, jobs)
    cfg = {"protocol": asdict(p), "tasks": tasks.tolist()}
    planned = dict(_pool_map(_plan_seed, [(s, states[s], cfg) for s in seeds], jobs))
    keys = ("cost", "success", "final_error", "command_change", "near_bounds", "onplan_rmse", "wall_s")
    policies = {name: {key: [planned[s][name][key] for s in seeds] for key in keys} for name in POLICIES}
    res = {"experiment": "ch7_memory_arm",
           "description": "Chapter 7, closed-loop planning through learned world models on memory_arm",
           "provenance": provenance(budget_cpu_s=float(budget_s), seeds=seeds, jobs=jobs, max_steps=max_steps,
                                    wall_s=round(time.perf_counter() - wall0, 1)),
           "protocol": asdict(p), "tasks": tasks.tolist(), "units": "rad",
           "arx_order": planned[seeds[0]]["_arx_order"], "data_commands": planned[seeds[0]]["_data_commands"], "models": list(PLANNING_MODELS),
           "training": training, "policies": policies}
    check_planning_study(res, min_seeds=1)
    if out_path is not None:
        write_json(out_path, res)
    return res


# =============================================================================================
# The payload study (Section 7.6): planning with an inferred task
# =============================================================================================

PAYLOAD_MODELS = ("HiP-RSSM (linear task term)", "ac-RKN (Chapter 4)")
"""The trained models of Chapter 5's experiment, on the vertical payload arm, that the payload study plans through."""

PAYLOAD_POLICIES = ("CEM + true-payload simulator", "CEM + nominal-payload simulator", "CEM through the HiP-RSSM",
                    "CEM through the ac-RKN", "PD to the target")
"""The rows of the payload study, in table order: the simulator with the true payload (upper reference),
the same simulator with the nominal payload (what knowing the payload is worth to exact physics),
the two learned models, and the arm's own PD controller sent the target (lower reference)."""

PAYLOAD_REGIMES = {"training range": None, "gap, 0.5-0.75 kg": (0.5, 0.75), "heavier, 2.0-2.5 kg": (2.0, 2.5)}
"""Where the study's payloads are drawn (kg): the union of the training ranges
(:func:`pgm_wm.datasets.payload_arm.sample_train_payloads`), the gap left out of training and the
heavier range of the dataset's ``interp`` and ``extrap`` splits."""


@dataclass(frozen=True)
class PayloadProtocol:
    """Settings of the payload study (the same for every policy).

    Every task is a payload and a target angle pair. ``warm_up`` steps of the datasets' own random
    PD waypoints (:func:`pgm_wm.datasets.two_link_arm.pd_targets`, seeded per task) from rest move
    the arm with the unseen payload before the first planned command: the interaction from which
    the HiP-RSSM infers its task. Then ``steps`` control steps with a planning horizon
    ``horizon`` (one window of Chapter 5 minus its observed prefix, so that a model's input is
    exactly two of its windows); a task succeeds when both joint errors are at most ``tol`` (rad) on
    each of the last ``success_steps`` steps. Cost weights: ``obs_weight`` on the two angles (0 on
    the velocities), ``action_weight`` on the PD targets. ``n_per_regime`` tasks per entry of
    :data:`PAYLOAD_REGIMES`; CEM settings as in :class:`PlanningProtocol`; ``model_context``: the
    most recent observations a learned model sees (Chapter 5's context length)."""

    warm_up: int = 50
    horizon: int = 13
    steps: int = 50
    tol: float = 0.03
    success_steps: int = 5
    n_per_regime: int = 6
    task_seed: int = 11
    obs_weight: float = 1.0
    action_weight: float = 1e-4
    n_samples: int = 64
    n_iters: int = 3
    elite_frac: float = 0.1
    model_context: int = 37

    def __post_init__(self) -> None:
        _check_protocol(self, ("warm_up", "horizon", "steps", "success_steps", "n_per_regime", "n_samples",
                               "n_iters", "model_context"))
        if self.warm_up < self.model_context:
            raise ValueError(f"warm_up: must be >= model_context = {self.model_context}, got {self.warm_up}")


def payload_arm_params() -> dict:
    """The vertical payload arm's simulator parameters (:data:`pgm_wm.datasets.payload_arm.DEFAULT_PARAMS`)
    as :class:`pgm_wm.planning.TwoLinkArmEnv` takes them (without the schedule's own keys)."""
    from ..datasets.payload_arm import DEFAULT_PARAMS
    from ..datasets.two_link_arm import DEFAULT_PARAMS as ARM

    return {k: v for k, v in DEFAULT_PARAMS.items() if k in ARM}


def payload_tasks(train: Any, n_per_regime: int, seed: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The payload study's tasks: ``(targets (n, 4), payloads (n,), regimes)``, ``n_per_regime``
    per entry of :data:`PAYLOAD_REGIMES` (seeded). Target angles are uniform inside the 10–90 %
    quantiles of the training split's angles, target velocities 0 (weight 0 in the cost)."""
    from ..datasets.payload_arm import sample_train_payloads

    if not isinstance(n_per_regime, int) or isinstance(n_per_regime, bool) or n_per_regime < 1:
        raise ValueError(f"n_per_regime: must be a positive int, got {n_per_regime!r}")
    rng = np.random.default_rng(seed)
    obs = train.obs.double().reshape(-1, train.obs.shape[-1]).numpy()
    lo, hi = np.quantile(obs[:, :2], [0.1, 0.9], axis=0)
    payloads, regimes = [], []
    for regime, rng_kg in PAYLOAD_REGIMES.items():
        draw = sample_train_payloads(rng, n_per_regime) if rng_kg is None else rng.uniform(*rng_kg, n_per_regime)
        payloads.extend(draw.tolist())
        regimes.extend([regime] * n_per_regime)
    n = len(payloads)
    targets = np.zeros((n, obs.shape[1]))
    targets[:, :2] = rng.uniform(lo, hi, size=(n, 2))
    return targets, np.asarray(payloads), regimes


@dataclass
class PayloadTaskRuns:
    """The closed loops of one task of the payload study: its simulator ``env`` (true payload), the
    state ``state0`` after the warm-up (where planning starts) and, per policy, the run and its wall time."""

    env: Any
    state0: Any
    runs: dict[str, Any]
    wall_s: dict[str, float]


def payload_closed_loops(protocol: PayloadProtocol, targets: Any, payloads: Sequence[float], nominal_payload: float,
                         seed: int, learned: Mapping[str, Any] | None = None,
                         rows: Sequence[str] = PAYLOAD_POLICIES) -> list[PayloadTaskRuns]:
    """Run the payload study's policies ``rows`` (names of :data:`PAYLOAD_POLICIES`) on every task
    (``targets (n, 4)``, ``payloads (n,)`` in kg) for one ``seed``: per task the warm-up of
    :class:`PayloadProtocol` in :class:`pgm_wm.planning.TwoLinkArmEnv` with the task's payload, then
    :func:`pgm_wm.planning.closed_loop` for each row, every CEM row with the same sampler seed.
    ``learned`` maps the learned rows (``"CEM through the HiP-RSSM"``, ``"CEM through the ac-RKN"``)
    to their predictors; the simulator rows and the PD controller need nothing."""
    from ..datasets.two_link_arm import pd_targets
    from ..planning import (ConstantPolicy, QuadraticCost, SamplingPlanner, TwoLinkArmEnv, closed_loop,
                            simulator_predictor, warm_up)

    p = protocol
    learned = dict(learned or {})
    unknown = [r for r in rows if r not in PAYLOAD_POLICIES]
    if unknown:
        raise ValueError(f"rows: unknown policies {unknown}; known: {list(PAYLOAD_POLICIES)}")
    missing = [r for r in rows if r.startswith("CEM through") and r not in learned]
    if missing:
        raise ValueError(f"learned: no predictor for {missing}")
    targets = np.asarray(targets, dtype=np.float64)
    if targets.ndim != 2 or targets.shape[1] != 4 or len(targets) != len(payloads):
        raise ValueError(f"targets: expected shape (len(payloads), 4), got {targets.shape}")
    params = payload_arm_params()
    W = torch.tensor([p.obs_weight, p.obs_weight, 0.0, 0.0], dtype=torch.float64)
    cost = QuadraticCost(W, torch.full((2,), p.action_weight, dtype=torch.float64))
    low, high = np.asarray(params["target_low"], float), np.asarray(params["target_high"], float)
    nominal = TwoLinkArmEnv(float(nominal_payload), params)
    out = []
    for i, (target, payload) in enumerate(zip(targets, payloads)):
        env = TwoLinkArmEnv(float(payload), params)
        commands = pd_targets(np.random.default_rng(p.task_seed * 1000 + i), 1, p.warm_up - 1, params)[0]
        state0, oh0, ah0 = warm_up(env, np.zeros(4), commands)     # the same interaction for every policy and seed

        def cem(predict: Any) -> SamplingPlanner:
            return SamplingPlanner(predict, cost, p.horizon, low, high, method="cem", n_samples=p.n_samples,
                                   n_iters=p.n_iters, elite_frac=p.elite_frac, seed=1000 * seed + i)

        make = {"CEM + true-payload simulator": lambda: cem(simulator_predictor(env)),
                "CEM + nominal-payload simulator": lambda: cem(simulator_predictor(nominal)),
                "PD to the target": lambda: ConstantPolicy(target[:2]),
                **{n: (lambda pr=pr: cem(pr)) for n, pr in learned.items()}}
        task = PayloadTaskRuns(env, state0, {}, {})
        for name in rows:
            t0 = time.perf_counter()
            task.runs[name] = closed_loop(env, make[name](), state0, oh0, ah0, target, p.steps, cost, tol=p.tol,
                                          success_steps=p.success_steps)
            task.wall_s[name] = time.perf_counter() - t0
        out.append(task)
    return out


def _plan_payload_seed(task: tuple[int, dict[str, dict[str, torch.Tensor]], dict[str, Any]]
                       ) -> tuple[int, dict[str, Any]]:
    from ..planning import command_statistics, world_model_predictor

    seed, p, cfg, splits, models = _seed_setup(task, PayloadProtocol, "ch5_payload")
    stats = splits.train.stats
    learned = {"CEM through the HiP-RSSM": world_model_predictor(models[PAYLOAD_MODELS[0]], stats,
                                                                 context_len=p.model_context),
               "CEM through the ac-RKN": world_model_predictor(models[PAYLOAD_MODELS[1]], stats,
                                                               context_len=p.model_context)}
    out: dict[str, Any] = _empty_record(PAYLOAD_POLICIES)
    out["_data_commands"] = dict(zip(("command_change", "near_bounds"),
                                     command_statistics(splits.train.actions.double())))
    for t in payload_closed_loops(p, cfg["tasks"], cfg["payloads"], cfg["nominal_payload"], seed, learned):
        for name in PAYLOAD_POLICIES:
            _record_run(out[name], t.env, t.runs[name], t.state0, t.wall_s[name], dims=(0, 1))   # the angles
    return seed, out


def run_payload_study(seeds: Sequence[int], budget_s: float, out_path: str | None = None, *,
                      protocol: PayloadProtocol | None = None, jobs: int = 1,
                      max_steps: int | None = None) -> dict[str, Any]:
    """Train the :data:`PAYLOAD_MODELS` of Chapter 5's experiment on ``payload_arm`` for every seed
    (``budget_s`` CPU seconds each, :func:`~pgm_wm.experiments.chapters.ch5_experiment`'s protocol),
    then run every policy of :data:`PAYLOAD_POLICIES` on every task of :func:`payload_tasks` in
    closed loop on :class:`pgm_wm.planning.TwoLinkArmEnv` with the task's payload; write the
    results to ``out_path`` (if given) and return them. The nominal payload is the training split's
    mean. ``jobs`` processes, one thread each."""
    p = protocol or PayloadProtocol()
    seeds = _check_run_args(seeds, budget_s)
    wall0 = time.perf_counter()
    splits = _experiment("ch5_payload").load()
    targets, payloads, regimes = payload_tasks(splits.train, p.n_per_regime, p.task_seed)
    nominal = float(splits.train.hidden["payload"].double().mean())
    states, training = _train_models("ch5_payload", PAYLOAD_MODELS, seeds, budget_s, max_steps, jobs)
    cfg = {"protocol": asdict(p), "tasks": targets.tolist(), "payloads": payloads.tolist(), "nominal_payload": nominal}
    planned = dict(_pool_map(_plan_payload_seed, [(s, states[s], cfg) for s in seeds], jobs))
    keys = ("cost", "success", "final_error", "command_change", "near_bounds", "onplan_rmse", "wall_s")
    policies = {name: {key: [planned[s][name][key] for s in seeds] for key in keys} for name in PAYLOAD_POLICIES}
    res = {"experiment": "ch7_payload_arm",
           "description": "Chapter 7, closed-loop planning with an inferred task on payload_arm (unseen payloads)",
           "provenance": provenance(budget_cpu_s=float(budget_s), seeds=seeds, jobs=jobs, max_steps=max_steps,
                                    wall_s=round(time.perf_counter() - wall0, 1)),
           "protocol": asdict(p), "tasks": targets.tolist(), "payloads": payloads.tolist(), "regimes": regimes,
           "nominal_payload": nominal, "units": "rad",
           "data_commands": planned[seeds[0]]["_data_commands"], "models": list(PAYLOAD_MODELS),
           "training": training, "policies": policies}
    check_planning_study(res, min_seeds=1)
    if out_path is not None:
        write_json(out_path, res)
    return res


# =============================================================================================
# The risk study (Section 7.5): does penalising predicted variance avoid a failure?
# =============================================================================================

ENSEMBLE = "ac-RKN + GRU ensemble"
"""The two trained models of :data:`PLANNING_MODELS` as one predictor, the moments of their mixture
(:func:`pgm_wm.planning.ensemble_predictor`, Eq. plan-ensemble): members that differ in architecture,
not only in seed."""

RISK_POLICIES = ("CEM + true simulator", "CEM through the ac-RKN", "CEM through the ac-RKN, risk-averse",
                 f"CEM through the {ENSEMBLE}", f"CEM through the {ENSEMBLE}, risk-averse", "zero commands")
"""The rows of the risk study, in table order: the simulator (upper reference), each learned predictor
without the risk term (:math:`\\lambda = 0`) and with the :math:`\\lambda` chosen on the validation
targets, and zero commands (lower reference; it never moves, so it never touches a stop)."""


@dataclass(frozen=True)
class RiskProtocol(PlanningProtocol):
    """Settings of the risk study: those of :class:`PlanningProtocol` (the memory-arm study's tasks,
    closed loop and CEM) plus a **stop** ``stop_margin`` (rad) past each target, on each joint, on the
    far side seen from the rest posture where every run starts; a run that passes a stop at any step
    *fails* (:func:`stop_overshoot`). The planners do not know the stops; their cost is unchanged.
    The risk weight :math:`\\lambda` of Eq. (plan-expected-cost) is chosen per seed and predictor
    among ``risks`` on ``n_valid_tasks`` validation targets (:func:`~pgm_wm.experiments.planning_study.planning_tasks`
    with ``valid_task_seed``): fewest failures, then lowest mean cost. The test targets are never used
    for the choice."""

    stop_margin: float = 0.1
    risks: tuple[float, ...] = (0.0, 10.0, 100.0, 1000.0)
    n_valid_tasks: int = 6
    valid_task_seed: int = 11

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_protocol(self, ("n_valid_tasks",))
        if not (isinstance(self.stop_margin, (int, float)) and math.isfinite(self.stop_margin) and self.stop_margin > 0):
            raise ValueError(f"stop_margin: must be a positive finite number, got {self.stop_margin!r}")
        risks = tuple(self.risks) if isinstance(self.risks, (list, tuple)) else ()
        if (not risks or any(not isinstance(r, (int, float)) or not math.isfinite(r) or r < 0 for r in risks)
                or len(set(risks)) != len(risks)):
            raise ValueError(f"risks: must be distinct finite numbers >= 0, got {self.risks!r}")
        object.__setattr__(self, "risks", tuple(float(r) for r in risks))


def stop_overshoot(obs: Any, start: Any, target: Any) -> float:
    r"""How far a run went past its target: :math:`\max_{t,j} d_j\,(o_{t,j} - r_j)` with
    :math:`d_j = \operatorname{sign}(r_j - s_j)` the direction of travel of joint :math:`j` from the
    start posture :math:`s` (rad; negative if the run never reached a target). A run fails when this
    exceeds :attr:`RiskProtocol.stop_margin`. ``obs: (T, do)``, ``start, target: (do,)``."""
    o = np.asarray(obs, dtype=np.float64)
    s, r = np.asarray(start, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if o.ndim != 2 or s.shape != (o.shape[1],) or r.shape != s.shape:
        raise ValueError(f"obs: expected (T, do) with start and target (do,), got {o.shape}, {s.shape}, {r.shape}")
    if not (np.isfinite(o).all() and np.isfinite(s).all() and np.isfinite(r).all()):
        raise ValueError("obs: obs, start and target must be finite")
    return float((np.sign(r - s) * (o - r)).max())


def _plan_risk_seed(task: tuple[int, dict[str, dict[str, torch.Tensor]], dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    from ..planning import (ConstantPolicy, QuadraticCost, SamplingPlanner, closed_loop, ensemble_predictor,
                            plan_prediction_errors, simulator_predictor, world_model_predictor)

    seed, p, cfg, splits, models = _seed_setup(task, RiskProtocol)
    env, state0, oh0, ah0, W, R = _memory_arm_start(p)
    score = QuadraticCost(W, R)
    stats = splits.train.stats
    single = {n: world_model_predictor(models[n], stats, context_len=p.model_context) for n in PLANNING_MODELS}
    learned = {"CEM through the ac-RKN": single[PLANNING_MODELS[0]],
               f"CEM through the {ENSEMBLE}": ensemble_predictor(list(single.values()))}

    def run(predict: Any, risk: float, target: np.ndarray, i: int) -> Any:
        policy = (ConstantPolicy(np.zeros(env.action_dim)) if predict is None else
                  SamplingPlanner(predict, QuadraticCost(W, R, risk=risk), p.horizon, env.action_low, env.action_high,
                                  method="cem", n_samples=p.n_samples, n_iters=p.n_iters, elite_frac=p.elite_frac,
                                  seed=1000 * seed + i))
        return closed_loop(env, policy, state0, oh0, ah0, target, p.steps, score, tol=p.tol, success_steps=p.success_steps)

    def overshoot(r: Any, target: np.ndarray) -> float:
        return stop_overshoot(r.obs[1:], oh0[-1], target)

    # the risk weight of each learned predictor, chosen on the validation targets: fewest failures, then cost
    valid: dict[str, dict[str, dict[str, list[float]]]] = {}
    chosen: dict[str, float] = {}
    for name, predict in learned.items():
        valid[name] = {}
        for risk in p.risks:
            runs = [(run(predict, risk, tg, 100 + i), tg) for i, tg in enumerate(np.asarray(cfg["valid_tasks"]))]
            valid[name][f"{risk:g}"] = {"failure": [float(overshoot(r, tg) > p.stop_margin) for r, tg in runs],
                                        "cost": [r.total_cost for r, _ in runs]}
        chosen[name] = min(p.risks, key=lambda lam: (sum(valid[name][f"{lam:g}"]["failure"]),
                                                     float(np.mean(valid[name][f"{lam:g}"]["cost"]))))
    rows = {"CEM + true simulator": (simulator_predictor(env), 0.0), "zero commands": (None, 0.0),
            **{n: (pr, 0.0) for n, pr in learned.items()},
            **{f"{n}, risk-averse": (pr, chosen[n]) for n, pr in learned.items()}}
    out: dict[str, Any] = _empty_record(RISK_POLICIES)
    for name in RISK_POLICIES:
        out[name].update(overshoot=[], failure=[], onplan_coverage=[], onplan_sd=[])
    for i, target in enumerate(np.asarray(cfg["tasks"])):
        for name in RISK_POLICIES:
            predict, risk = rows[name]
            t0 = time.perf_counter()
            r = run(predict, risk, target, i)
            entry = out[name]
            _record_run(entry, env, r, state0, time.perf_counter() - t0)
            entry["overshoot"].append(overshoot(r, target))
            entry["failure"].append(float(entry["overshoot"][-1] > p.stop_margin))
            if r.plan_actions is not None and name != "CEM + true simulator":
                err, var = plan_prediction_errors(env, r, state0), r.pred_var.numpy()
                entry["onplan_coverage"].append((np.abs(err) <= 2.0 * np.sqrt(var)).mean(axis=(0, 2)).tolist())
                entry["onplan_sd"].append(np.sqrt(var.mean(axis=(0, 2))).tolist())
    out["_validation"] = valid
    out["_chosen"] = chosen
    return seed, out


def run_risk_study(seeds: Sequence[int], budget_s: float, out_path: str | None = None, *,
                   protocol: RiskProtocol | None = None, jobs: int = 1, max_steps: int | None = None) -> dict[str, Any]:
    """Train the :data:`PLANNING_MODELS` for every seed exactly as :func:`run_planning_study` does,
    choose each learned predictor's risk weight on the validation targets (:class:`RiskProtocol`),
    then run every policy of :data:`RISK_POLICIES` on the test targets (those of the memory-arm study)
    with their stops; write the results to ``out_path`` (if given) and return them. Per policy the
    file holds the arrays of :func:`run_planning_study` plus ``overshoot`` and ``failure``
    ``(seeds, tasks)``, and for the learned rows ``onplan_coverage`` and ``onplan_sd``
    ``(seeds, tasks, H)`` (2σ coverage and predicted σ along the chosen plans); per learned predictor
    the validation scores of every risk weight and the weight chosen, per seed."""
    p = protocol or RiskProtocol()
    seeds = _check_run_args(seeds, budget_s)
    wall0 = time.perf_counter()
    splits = _experiment("ch4").load()
    tasks = planning_tasks(splits.train, p.n_tasks, p.task_seed)
    valid_tasks = planning_tasks(splits.train, p.n_valid_tasks, p.valid_task_seed)
    states, training = _train_models("ch4", PLANNING_MODELS, seeds, budget_s, max_steps, jobs)
    cfg = {"protocol": asdict(p), "tasks": tasks.tolist(), "valid_tasks": valid_tasks.tolist()}
    planned = dict(_pool_map(_plan_risk_seed, [(s, states[s], cfg) for s in seeds], jobs))
    keys = ("cost", "success", "final_error", "command_change", "near_bounds", "onplan_rmse", "wall_s",
            "overshoot", "failure", "onplan_coverage", "onplan_sd")
    policies = {name: {key: [planned[s][name][key] for s in seeds] for key in keys} for name in RISK_POLICIES}
    learned = list(planned[seeds[0]]["_chosen"])
    res = {"experiment": "ch7_risk",
           "description": "Chapter 7, risk-averse planning through learned world models on memory_arm, with stops",
           "provenance": provenance(budget_cpu_s=float(budget_s), seeds=seeds, jobs=jobs, max_steps=max_steps,
                                    wall_s=round(time.perf_counter() - wall0, 1)),
           "protocol": asdict(p), "tasks": tasks.tolist(), "valid_tasks": valid_tasks.tolist(), "units": "rad",
           "models": list(PLANNING_MODELS), "training": training, "policies": policies,
           "risk_chosen": {n: [planned[s]["_chosen"][n] for s in seeds] for n in learned},
           "validation": {n: [planned[s]["_validation"][n] for s in seeds] for n in learned}}
    check_planning_study(res, min_seeds=1)
    if out_path is not None:
        write_json(out_path, res)
    return res


def _policies(results: Mapping[str, Any]) -> tuple[str, ...]:
    """The rows of a study in table order: :data:`POLICIES` for the memory-arm study,
    :data:`PAYLOAD_POLICIES` for the payload study, :data:`RISK_POLICIES` for the risk study (its
    ``experiment`` key says which)."""
    return {"ch7_payload_arm": PAYLOAD_POLICIES, "ch7_risk": RISK_POLICIES}.get(results.get("experiment"), POLICIES)


def check_planning_study(results: Mapping[str, Any], min_seeds: int = 5) -> None:
    """Raise ``ValueError`` unless ``results`` is a complete closed-loop study: at least
    ``min_seeds`` seeds, the package provenance, every policy of :data:`POLICIES` with finite
    ``(seeds, tasks)`` costs, 0/1 successes and errors, and for every trained model and seed its
    training record (steps, curve, the stopping rule's verdict)."""
    for key in ("provenance", "protocol", "tasks", "training", "policies"):
        if key not in results:
            raise ValueError(f"results: missing key {key!r}")
    prov = results["provenance"]
    seeds = prov.get("seeds", [])
    if len(seeds) < min_seeds:
        raise ValueError(f"results: {len(seeds)} seeds, need at least {min_seeds}")
    if not prov.get("package_hash") or not prov.get("code_hashes"):
        raise ValueError("results: no package_hash / code_hashes in the provenance")
    shape = (len(seeds), len(results["tasks"]))
    for name in _policies(results):
        entry = results["policies"].get(name)
        if entry is None:
            raise ValueError(f"results: no policy {name!r}")
        for key in ("cost", "success", "final_error"):
            v = np.asarray(entry[key], dtype=np.float64)
            if v.shape != shape or not np.isfinite(v).all() or (v < 0).any():
                raise ValueError(f"results: policy {name!r}, {key!r} is not a finite non-negative {shape} array")
        if not np.isin(np.asarray(entry["success"]), (0.0, 1.0)).all():
            raise ValueError(f"results: policy {name!r}, 'success' is not 0/1")
    for name in results.get("models", PLANNING_MODELS):
        runs = results["training"].get(name, [])
        if len(runs) != len(seeds) or any(r is None or not {"steps", "curve", "converged", "best_valid"} <= set(r)
                                          for r in runs):
            raise ValueError(f"results: model {name!r} lacks a training record per seed")


def load_planning_study(path: str | os.PathLike) -> dict[str, Any]:
    """Read a closed-loop study written by :func:`run_planning_study` and check it
    (:func:`check_planning_study`, any number of seeds)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"path: no results file at {p}; run `python -m pgm_wm.experiments ch7` to make it")
    res = json.loads(p.read_text())
    check_planning_study(res, min_seeds=1)
    return res


def training_summary(results: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Per trained model of a planning study: optimizer steps over seeds (``"steps"``, e.g.
    ``"6812–7540"``), the median best validation RMSE (``"valid"``), how many seeds met the
    stopping rule (``"converged"``) and of how many (``"seeds"``)."""
    return {n: {"steps": f"{min(r['steps'] for r in runs)}–{max(r['steps'] for r in runs)}",
                "valid": float(np.median([r["best_valid"] for r in runs])),
                "converged": sum(bool(r["converged"]) for r in runs), "seeds": len(runs)}
            for n, runs in results["training"].items()}


def study_header(results: Mapping[str, Any], training_caption: str) -> str:
    """Markdown for the head of a planning study's section: how the file was produced (command,
    date, commit, machine, seeds, targets, training budget, run time), the package note if the
    package's code changed since (:func:`pgm_wm.experiments.results.package_note`), and the
    table of :func:`training_summary` under the bold ``training_caption``."""
    from ..plotting import markdown_table
    from .results import package_note

    prov = results["provenance"]
    noun = "tasks (target and payload)" if "payloads" in results else "targets"
    targets = f"{len(results['tasks'])} {noun}" + (
        f" and {len(results['valid_tasks'])} validation targets" if "valid_tasks" in results else "")
    text = (f"Produced by `{prov['command'].split(' --out')[0]}` (written to this file) on {prov['date']} at commit {prov['commit'][:10]}, "
            f"{prov['machine']['cpu_count']} CPUs, torch {prov['machine']['torch']}; seeds {prov['seeds']}, {targets}, "
            f"{prov['budget_cpu_s']:g} CPU s of training per model and seed; the whole run took "
            f"{prov['wall_s'] / 60:.0f} min.")
    note = package_note(results)
    if note:
        text += f"\n\n**Note:** {note}"
    rows = [[n, t["steps"], t["valid"], f"{t['converged']}/{t['seeds']}"] for n, t in training_summary(results).items()]
    return text + f"\n\n**{training_caption}**\n\n" + markdown_table(
        rows, ["model", "optimizer steps", "best validation RMSE (median)", "met the stopping rule"], floatfmt=".3g")


def planning_table(results: Mapping[str, Any], n_boot: int = 2000) -> dict[str, dict[str, Interval]]:
    """Per policy: mean true cost, success rate and mean final tracking error (rad), each with the
    two-level (seeds × tasks) bootstrap interval of :func:`~pgm_wm.experiments.stats.mean_interval`."""
    out = {}
    for name in _policies(results):
        e = results["policies"][name]
        out[name] = {key: mean_interval(np.asarray(e[key], dtype=np.float64), n_boot=n_boot)
                     for key in ("cost", "success", "final_error")}
    return out


def planning_ratios(results: Mapping[str, Any], policy: str, rivals: Sequence[str],
                    n_boot: int = 2000) -> dict[str, Interval]:
    """Mean cost of ``policy`` over the mean cost of each rival, paired over tasks
    (:func:`~pgm_wm.experiments.stats.paired_mean_ratio`); below 1: ``policy`` is cheaper."""
    pol = results["policies"]
    for name in (policy, *rivals):
        if name not in pol:
            raise ValueError(f"policy: unknown policy {name!r}; known: {', '.join(pol)}")
    a = np.asarray(pol[policy]["cost"], dtype=np.float64)
    return {r: paired_mean_ratio(a, np.asarray(pol[r]["cost"], dtype=np.float64), n_boot=n_boot) for r in rivals}

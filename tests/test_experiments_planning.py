"""Chapter 7's closed-loop study (pgm_wm.experiments.planning_study): a small end-to-end run, its
checks, its tables and its command line."""
from __future__ import annotations

import numpy as np
import pytest

from pgm_wm.experiments.planning_study import (PLANNING_MODELS, POLICIES, PlanningProtocol, check_planning_study,
                                               planning_ratios, planning_table, planning_tasks, run_planning_study)


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("ch7") / "ch7.json"
    protocol = PlanningProtocol(n_tasks=2, steps=8, success_steps=2, n_samples=16, n_iters=2, model_context=20)
    res = run_planning_study([0, 1], budget_s=30.0, out_path=str(out), protocol=protocol, jobs=1, max_steps=3)
    return res, out


def test_small_study_has_every_policy_seed_and_task(small_study):
    from pgm_wm.experiments.planning_study import load_planning_study

    res, out = small_study
    assert load_planning_study(out)["policies"].keys() == set(POLICIES)
    with pytest.raises(ValueError, match="^path"):
        load_planning_study(out.with_name("nothing.json"))
    check_planning_study(res, min_seeds=2)
    for name in POLICIES:
        e = res["policies"][name]
        assert np.asarray(e["cost"]).shape == (2, 2) and len(e["wall_s"]) == 2
        planned = name.startswith("CEM")
        assert np.asarray(e["onplan_rmse"]).shape == ((2, 2, 10) if planned else (2, 0))
    for name in PLANNING_MODELS:
        assert [r["steps"] for r in res["training"][name]] == [3, 3]


def test_small_study_properties(small_study):
    res, _ = small_study
    pol = {n: np.asarray(e["cost"]) for n, e in res["policies"].items()}
    # deterministic policies give the same run for every seed; the simulator predicts its own plans exactly
    for name in ("LQR through the ARX model", "zero commands"):
        np.testing.assert_array_equal(pol[name][0], pol[name][1])
    assert np.abs(res["policies"]["CEM + true simulator"]["onplan_rmse"]).max() < 1e-9
    # planning through the true simulator beats doing nothing on every task
    assert (pol["CEM + true simulator"] < pol["zero commands"]).all()
    # zero commands: no change, never near the bounds
    assert np.asarray(res["policies"]["zero commands"]["command_change"]).max() == 0.0
    assert not np.asarray(res["policies"]["zero commands"]["success"]).any()


def test_tables_are_computed_from_the_arrays(small_study):
    res, _ = small_study
    table = planning_table(res, n_boot=100)
    for name in POLICIES:
        assert table[name]["cost"].point == pytest.approx(np.mean(res["policies"][name]["cost"]))
        assert table[name]["success"].point == pytest.approx(np.mean(res["policies"][name]["success"]))
    ratios = planning_ratios(res, "CEM through the ac-RKN", ["zero commands"], n_boot=100)
    expected = np.mean(res["policies"]["CEM through the ac-RKN"]["cost"]) / np.mean(res["policies"]["zero commands"]["cost"])
    assert ratios["zero commands"].point == pytest.approx(expected)
    with pytest.raises(ValueError, match="^policy"):
        planning_ratios(res, "CEM through a crystal ball", ["zero commands"])


def test_study_header_says_how_the_file_was_made_and_summarises_training(small_study, monkeypatch):
    from pgm_wm.experiments import planning_study
    from pgm_wm.experiments.planning_study import study_header, training_summary

    res, _ = small_study
    summary = training_summary(res)
    assert list(summary) == list(PLANNING_MODELS)
    for name, t in summary.items():
        runs = res["training"][name]
        assert t == {"steps": "3–3", "valid": pytest.approx(float(np.median([r["best_valid"] for r in runs]))),
                     "converged": sum(bool(r["converged"]) for r in runs), "seeds": 2}
    text = study_header(res, "Training caption.")
    assert "--out" not in text and f"`{res['provenance']['command'].split(' --out')[0]}`" in text
    assert "seeds [0, 1], 2 targets," in text and "**Training caption.**" in text
    assert "**Note:**" not in text                          # made by this package's code
    assert all(f"| {name} | 3–3 |" in text for name in PLANNING_MODELS)
    monkeypatch.setattr("pgm_wm.experiments.results.package_note", lambda r: "made by other code")
    assert "**Note:** made by other code" in planning_study.study_header(res, "T.")


def test_check_planning_study_rejects_incomplete_files(small_study):
    res, _ = small_study
    with pytest.raises(ValueError, match="seeds"):
        check_planning_study(res, min_seeds=5)
    missing = {**res, "policies": {k: v for k, v in res["policies"].items() if k != "zero commands"}}
    with pytest.raises(ValueError, match="zero commands"):
        check_planning_study(missing, min_seeds=2)
    bad = {**res, "policies": {**res["policies"], "zero commands": {**res["policies"]["zero commands"],
                                                                    "cost": [[1.0, float("nan")], [1.0, 1.0]]}}}
    with pytest.raises(ValueError, match="finite"):
        check_planning_study(bad, min_seeds=2)
    untrained = {**res, "training": {PLANNING_MODELS[0]: res["training"][PLANNING_MODELS[0]]}}
    with pytest.raises(ValueError, match="GRU"):
        check_planning_study(untrained, min_seeds=2)


def test_tasks_lie_inside_the_training_range_and_are_seeded():
    from pgm_wm.datasets import load

    train = load("memory_arm", "train")
    t = planning_tasks(train, 200, seed=3)
    obs = train.obs.double().reshape(-1, 2).numpy()
    lo, hi = np.quantile(obs, [0.1, 0.9], axis=0)
    assert t.shape == (200, 2) and (t >= lo).all() and (t <= hi).all()
    np.testing.assert_array_equal(t, planning_tasks(train, 200, seed=3))
    assert not np.array_equal(t, planning_tasks(train, 200, seed=4))


@pytest.mark.parametrize("bad", [dict(horizon=0), dict(success_steps=60), dict(tol=-1.0), dict(elite_frac=0.0),
                                 dict(n_tasks=1.5)])
def test_protocol_rejects_bad_settings(bad):
    with pytest.raises(ValueError, match=f"^{next(iter(bad))}"):
        PlanningProtocol(**bad)


def test_run_rejects_bad_seeds_and_budget():
    with pytest.raises(ValueError, match="^seeds"):
        run_planning_study([0, 0], 10.0)
    with pytest.raises(ValueError, match="^budget_s"):
        run_planning_study([0], 0.0)


@pytest.mark.parametrize("study, runner, bad_args", [
    ("ch7", "run_planning_study", (["--jobs", "999"], ["--seeds", "0"], ["--seed-start", "-1"],
                                   ["--out", "results/ch4_memory_arm.json"])),
    ("ch7_payload", "run_payload_study", (["--jobs", "999"], ["--tasks", "0"],
                                          ["--out", "results/ch4_memory_arm.json"])),
    ("ch7_risk", "run_risk_study", (["--jobs", "999"], ["--tasks", "0"], ["--steps", "0"],
                                    ["--out", "results/ch4_memory_arm.json"]))])
def test_cli_checks_arguments_before_training(tmp_path, monkeypatch, study, runner, bad_args):
    from pgm_wm.experiments import __main__ as cli
    from pgm_wm.experiments import planning_study

    def no_run(*a, **k):
        raise AssertionError("the study ran")

    monkeypatch.setattr(planning_study, runner, no_run)
    for args in bad_args:
        argv = [study, *args]
        with pytest.raises(SystemExit):
            cli.main(argv + ([] if "--out" in argv else ["--out", str(tmp_path / "x.json")]))


# --- the payload study (Section 7.6) -------------------------------------------------------------


@pytest.fixture(scope="module")
def small_payload_study():
    from pgm_wm.experiments.planning_study import PayloadProtocol, run_payload_study

    protocol = PayloadProtocol(n_per_regime=1, steps=6, success_steps=2, n_samples=16, n_iters=2)
    return run_payload_study([0, 1], budget_s=30.0, protocol=protocol, jobs=1, max_steps=3)


def test_small_payload_study_has_every_policy_seed_and_task(small_payload_study):
    from pgm_wm.experiments.planning_study import PAYLOAD_MODELS, PAYLOAD_POLICIES, PAYLOAD_REGIMES

    res = small_payload_study
    check_planning_study(res, min_seeds=2)
    assert list(res["policies"]) == list(PAYLOAD_POLICIES)
    assert res["regimes"] == list(PAYLOAD_REGIMES)
    for name in PAYLOAD_POLICIES:
        e = res["policies"][name]
        assert np.asarray(e["cost"]).shape == (2, 3)
        assert np.asarray(e["onplan_rmse"]).shape == ((2, 3, 13) if name.startswith("CEM") else (2, 0))
    for name in PAYLOAD_MODELS:
        assert [r["steps"] for r in res["training"][name]] == [3, 3]
    # the table reads the payload study's own rows
    assert list(planning_table(res, n_boot=50)) == list(PAYLOAD_POLICIES)
    missing = {**res, "policies": {k: v for k, v in res["policies"].items() if k != "PD to the target"}}
    with pytest.raises(ValueError, match="PD to the target"):
        check_planning_study(missing, min_seeds=2)


def test_small_payload_study_properties(small_payload_study):
    res = small_payload_study
    pol = res["policies"]
    # the PD controller is deterministic: the same run for every seed
    np.testing.assert_array_equal(pol["PD to the target"]["cost"][0], pol["PD to the target"]["cost"][1])
    # the true-payload simulator predicts its own plans exactly; the nominal one does not when the
    # payload differs from the nominal (the heavier regime: more than 1 kg away)
    assert np.abs(pol["CEM + true-payload simulator"]["onplan_rmse"]).max() < 1e-9
    heavy = res["regimes"].index("heavier, 2.0-2.5 kg")
    assert abs(res["payloads"][heavy] - res["nominal_payload"]) > 1.0
    onplan = np.asarray(pol["CEM + nominal-payload simulator"]["onplan_rmse"])
    assert onplan[:, heavy].min() > 1e-4
    # scored on the angles only (rad): one step of 0.02 s moves them by far less than 0.05 rad
    assert onplan[..., 0].max() < 0.05


def test_payload_tasks_are_in_their_regimes_and_seeded():
    from pgm_wm.datasets import load
    from pgm_wm.datasets.payload_arm import TRAIN_PAYLOAD_RANGES
    from pgm_wm.experiments.planning_study import PAYLOAD_REGIMES, payload_tasks

    train = load("payload_arm", "train")
    targets, payloads, regimes = payload_tasks(train, 50, seed=3)
    assert targets.shape == (150, 4) and payloads.shape == (150,) and len(regimes) == 150
    assert (targets[:, 2:] == 0).all()
    lo, hi = np.quantile(train.obs.double().reshape(-1, 4).numpy()[:, :2], [0.1, 0.9], axis=0)
    assert (targets[:, :2] >= lo).all() and (targets[:, :2] <= hi).all()
    for regime, rng_kg in PAYLOAD_REGIMES.items():
        p = payloads[[r == regime for r in regimes]]
        assert len(p) == 50
        ranges = TRAIN_PAYLOAD_RANGES if rng_kg is None else [rng_kg]
        assert all(any(a <= x <= b for a, b in ranges) for x in p)
    again = payload_tasks(train, 50, seed=3)
    np.testing.assert_array_equal(targets, again[0])
    np.testing.assert_array_equal(payloads, again[1])
    assert not np.array_equal(payloads, payload_tasks(train, 50, seed=4)[1])
    with pytest.raises(ValueError, match="^n_per_regime"):
        payload_tasks(train, 0, seed=3)


@pytest.mark.parametrize("bad", [dict(horizon=0), dict(warm_up=10), dict(tol=0.0), dict(elite_frac=1.5),
                                 dict(n_per_regime=2.0)])
def test_payload_protocol_rejects_bad_settings(bad):
    from pgm_wm.experiments.planning_study import PayloadProtocol

    with pytest.raises(ValueError, match=f"^{next(iter(bad))}"):
        PayloadProtocol(**bad)



def test_payload_closed_loops_nominal_equals_true_at_the_nominal_payload():
    from pgm_wm.experiments.planning_study import PayloadProtocol, payload_closed_loops

    p = PayloadProtocol(steps=4, success_steps=2, n_samples=16, n_iters=2)
    targets = np.array([[0.2, -0.3, 0.0, 0.0], [-0.1, 0.4, 0.0, 0.0]])
    rows = ("CEM + true-payload simulator", "CEM + nominal-payload simulator", "PD to the target")
    same, other = (payload_closed_loops(p, targets, [1.0, 2.2], nominal, seed=0, rows=rows) for nominal in (1.0, 0.5))
    # task 0 has the nominal payload 1.0: the two simulator planners are the same planner
    a, b = same[0].runs[rows[0]], same[0].runs[rows[1]]
    np.testing.assert_array_equal(a.actions.numpy(), b.actions.numpy())
    assert a.total_cost == b.total_cost
    # with a wrong nominal payload the plans differ; the true-payload row does not depend on it
    assert not np.array_equal(other[0].runs[rows[1]].actions.numpy(), a.actions.numpy())
    np.testing.assert_array_equal(other[1].runs[rows[0]].actions.numpy(), same[1].runs[rows[0]].actions.numpy())
    # the PD controller holds its command at the target
    np.testing.assert_allclose(same[1].runs[rows[2]].actions.numpy(), np.tile(targets[1, :2], (4, 1)))
    with pytest.raises(ValueError, match="^rows"):
        payload_closed_loops(p, targets, [1.0, 2.2], 1.0, 0, rows=("CEM through a crystal ball",))
    with pytest.raises(ValueError, match="^learned"):
        payload_closed_loops(p, targets, [1.0, 2.2], 1.0, 0, rows=("CEM through the HiP-RSSM",))
    with pytest.raises(ValueError, match="^targets"):
        payload_closed_loops(p, targets[:, :2], [1.0, 2.2], 1.0, 0, rows=rows)


def test_payload_arm_sags_with_the_payload_under_its_pd_controller():
    """The phenomenon the payload study needs: on the vertical arm the PD controller compensates the
    gravity of the arm without payload, so commanding the target leaves a steady error that grows
    with the payload (about K_p^-1 times its gravity torque); without payload there is none."""
    from pgm_wm.experiments.planning_study import payload_arm_params
    from pgm_wm.planning import TwoLinkArmEnv

    target = np.array([0.3, -0.4])
    sag = {}
    for payload in (0.0, 1.0, 2.25):
        env = TwoLinkArmEnv(payload, payload_arm_params())
        q = env.rollout(np.zeros(4), np.tile(target, (1, 150, 1)))[0, -1]     # 3 s holding the command
        sag[payload] = np.abs(q[:2] - target).max()
    assert sag[0.0] < 1e-3
    assert 0.05 < sag[1.0] < sag[2.25]
    assert sag[2.25] > 0.2


# --- the risk study (Section 7.5) ----------------------------------------------------------------


def test_stop_overshoot_measures_the_distance_past_the_target_in_the_direction_of_travel():
    from pgm_wm.experiments.planning_study import stop_overshoot

    start, target = np.array([0.0, 0.0]), np.array([0.5, -0.3])
    # joint 0 moves up and passes its target by 0.04; joint 1 moves down and passes it by 0.07
    obs = np.array([[0.1, -0.1], [0.54, -0.37], [0.5, -0.31]])
    assert stop_overshoot(obs, start, target) == pytest.approx(0.07)
    # a run that stops short of both targets has a negative overshoot (the smaller shortfall)
    assert stop_overshoot(obs[:1], start, target) == pytest.approx(-0.2)
    # moving in the opposite direction is not an overshoot
    assert stop_overshoot(np.array([[-0.9, 0.8]]), start, target) < 0
    with pytest.raises(ValueError, match="^obs"):
        stop_overshoot(obs, start, target[:1])
    with pytest.raises(ValueError, match="^obs"):
        stop_overshoot(obs * np.nan, start, target)


@pytest.mark.parametrize("bad", [dict(stop_margin=0.0), dict(risks=()), dict(risks=(0.0, -1.0)), dict(risks=(1.0, 1.0)),
                                 dict(n_valid_tasks=0), dict(horizon=0)])
def test_risk_protocol_rejects_bad_settings(bad):
    from pgm_wm.experiments.planning_study import RiskProtocol

    with pytest.raises(ValueError, match=f"^{next(iter(bad))}"):
        RiskProtocol(**bad)


@pytest.fixture(scope="module")
def small_risk_study():
    from pgm_wm.experiments.planning_study import RiskProtocol, run_risk_study

    protocol = RiskProtocol(n_tasks=2, n_valid_tasks=2, steps=8, success_steps=2, n_samples=16, n_iters=2,
                            model_context=20, stop_margin=0.02, risks=(0.0, 100.0))
    return run_risk_study([0, 1], budget_s=30.0, protocol=protocol, jobs=1, max_steps=3)


def test_small_risk_study_rows_choices_and_failures(small_risk_study):
    from pgm_wm.experiments.planning_study import RISK_POLICIES

    res = small_risk_study
    check_planning_study(res, min_seeds=2)
    assert list(res["policies"]) == list(planning_table(res, n_boot=50)) == list(RISK_POLICIES)
    margin = res["protocol"]["stop_margin"]
    for name, e in res["policies"].items():
        assert np.asarray(e["cost"]).shape == np.asarray(e["failure"]).shape == (2, 2)
        # a failure is an overshoot past the stop, nothing else
        np.testing.assert_array_equal(np.asarray(e["failure"]) == 1.0, np.asarray(e["overshoot"]) > margin)
        learned = name.startswith("CEM through")
        assert np.asarray(e["onplan_coverage"]).shape == ((2, 2, 10) if learned else (2, 0))
        cov = np.asarray(e["onplan_coverage"])
        assert ((cov >= 0) & (cov <= 1)).all()
    assert not np.asarray(res["policies"]["zero commands"]["failure"]).any()
    # the risk weight is the validation argmin (fewest failures, then cost), never read from the test targets
    for name, choices in res["risk_chosen"].items():
        for seed_i, lam in enumerate(choices):
            scores = res["validation"][name][seed_i]
            best = min(scores, key=lambda k: (sum(scores[k]["failure"]), np.mean(scores[k]["cost"])))
            assert lam == float(best)
            if lam == 0.0:   # the risk-averse row is then the plain row, run for run
                assert res["policies"][f"{name}, risk-averse"]["cost"][seed_i] == res["policies"][name]["cost"][seed_i]

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


def test_cli_checks_arguments_before_training(tmp_path, monkeypatch):
    from pgm_wm.experiments import __main__ as cli
    from pgm_wm.experiments import planning_study

    def no_run(*a, **k):
        raise AssertionError("the study ran")

    monkeypatch.setattr(planning_study, "run_planning_study", no_run)
    for argv in (["ch7", "--jobs", "999"], ["ch7", "--seeds", "0"], ["ch7", "--seed-start", "-1"],
                 ["ch7", "--out", "results/ch4_memory_arm.json"]):
        with pytest.raises(SystemExit):
            cli.main(argv + ([] if "--out" in argv else ["--out", str(tmp_path / "x.json")]))

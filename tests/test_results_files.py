"""The committed chapter 4-7 studies in ``results/`` are complete studies of the convergence
protocol (issue 21): at least five seeds, the package-source hash, and for every trained model and
seed the optimizer steps, epochs, learning curve and the stopping rule's verdict; the reference
rows every table needs are present; and the verdicts agree with the stored curves."""
from __future__ import annotations

import numpy as np
import pytest

from pgm_wm.experiments.results import check_study, load_results, results_path
from pgm_wm.experiments.runner import CONVERGENCE_TOL, improvement_over_last_doubling

STUDIES = ["ch4_memory_arm", "ch4_pam_arm", "ch5_hidden_payload_arm", "ch6_slow_payload_arm"]
REFERENCES = ["repeat last", "training mean", "linear ARX (order on validation)"]
SIMULATED = {"ch4_memory_arm", "ch5_hidden_payload_arm", "ch6_slow_payload_arm"}


def _readme_words() -> str:
    """The README with every run of whitespace made one space (its sentences wrap anywhere)."""
    from pathlib import Path

    return " ".join((Path(__file__).resolve().parents[1] / "README.md").read_text().split())


@pytest.fixture(scope="module", params=STUDIES)
def study(request):
    return request.param, load_results(results_path(request.param))


def test_each_study_is_complete(study):
    name, res = study
    check_study(res, min_seeds=5)
    assert len(res["provenance"]["package_hash"]) == 64
    assert res["provenance"]["budget_cpu_s"] >= 120, "a study at a budget below the convergence protocol's"


def test_each_study_has_the_reference_rows(study):
    name, res = study
    for ref in REFERENCES:
        assert ref in res["models"] and not res["models"][ref]["trained"], f"{name}: no {ref!r} row"
    oracles = [n for n in res["models"] if n.startswith("physics oracle")]
    assert bool(oracles) == (name in SIMULATED), f"{name}: oracle rows {oracles}"


def test_stored_verdicts_follow_from_the_stored_curves(study):
    """Recompute every run's improvement over the last doubling from its curve: the stored number
    and the converged flag must follow from it (the curve is thinned, but keeps every new best)."""
    name, res = study
    budget = float(res["provenance"]["budget_cpu_s"])
    for model, entry in res["models"].items():
        if not entry["trained"]:
            continue
        for run in entry["runs"]:
            if run.get("stopped") != "budget":
                continue
            impr = improvement_over_last_doubling(run["curve"], budget)
            assert np.isclose(impr, run["improvement_last_doubling"], rtol=1e-3, atol=1e-6), (name, model)
            assert run["converged"] == (impr < CONVERGENCE_TOL), (name, model)


def test_every_trained_model_took_steps_and_beats_the_training_mean(study):
    """A model that never left its initialization would fail this: the best validation RMSE of every
    trained run is below the training-mean row's validation RMSE."""
    name, res = study
    mean_valid = res["models"]["training mean"]["runs"][0]["best_valid"]
    for model, entry in res["models"].items():
        if entry["trained"]:
            for run in entry["runs"]:
                assert run["steps"] > 100, (name, model, run["steps"])
                assert run["best_valid"] < mean_valid, (name, model, run["best_valid"], mean_valid)


def test_readme_count_of_verdicts_with_a_collapsed_learning_rate():
    """The README's sentence on what *converged* meant before the schedule had a floor is read off
    the study files made without one: how many runs meet the stopping rule and how many of those
    ended with the learning rate below 1e-3 (and how many below 1e-6) of its start. In the files
    made with a floor no run ends below it. The learning rate is recorded in every curve entry."""
    import re

    from pgm_wm.experiments.runner import final_lr_fraction

    met = low = tiny = 0
    unfloored = []
    for name in STUDIES:
        res = load_results(results_path(name))
        floor = res["protocol"].get("lr_min_fraction", 0.0)
        if not floor:
            unfloored.append(name)
        for model in res["models"].values():
            for run in model.get("runs", []) if model["trained"] else []:
                assert all("lr" in c for c in run["curve"]), f"{name}: a curve entry without its learning rate"
                frac = final_lr_fraction(run)
                assert frac >= floor * (1 - 1e-9), f"{name}: a run ended below the protocol's floor"
                if run["converged"] and not floor:
                    met, low, tiny = met + 1, low + (frac < 1e-3), tiny + (frac < 1e-6)
    words = {1: "one", 2: "two", 3: "three", 4: "four"}
    readme = _readme_words()
    if not unfloored:
        assert "made without a floor" not in readme, "the README still counts files made without a floor"
        return
    found = re.search(r"In the (\w+) files? made without a floor, (\d+) of the (\d+) runs that meet it ended with "
                      r"the rate below 10⁻³ of its start \(most below 10⁻⁶\)", readme)
    assert found, "the README no longer states the count"
    assert found[1] == words[len(unfloored)], f"README counts {found[1]} files; made without a floor: {unfloored}"
    assert (int(found[2]), int(found[3])) == (low, met), f"README says {found[2]} of {found[3]}; the files: {low} of {met}"
    assert tiny > met / 2, f"'most below 1e-6' no longer holds: {tiny} of {met}"


def test_the_chapter7_study_is_complete():
    """Chapter 7's closed-loop study: five seeds, Chapter 4's budget, every policy on every task,
    every planning model trained well past its initialization (more than 100 steps, below the
    training-mean row of Chapter 4's study on validation)."""
    from pgm_wm.experiments.planning_study import PLANNING_MODELS, check_planning_study, load_planning_study

    res = load_planning_study(results_path("ch7_memory_arm"))
    check_planning_study(res, min_seeds=5)
    assert res["provenance"]["budget_cpu_s"] >= 240 and len(res["tasks"]) >= 16
    mean_valid = load_results(results_path("ch4_memory_arm"))["models"]["training mean"]["runs"][0]["best_valid"]
    for name in PLANNING_MODELS:
        for run in res["training"][name]:
            assert run["steps"] > 100 and run["best_valid"] < mean_valid, name


def test_the_chapter7_payload_study_is_complete():
    """Chapter 7's payload study: five seeds, Chapter 5's budget, every policy on every task of every
    payload range, every planning model trained well past its initialization (more than 100 steps,
    far below the validation RMSE it started from)."""
    from pgm_wm.experiments.planning_study import (PAYLOAD_MODELS, PAYLOAD_POLICIES, PAYLOAD_REGIMES,
                                                   check_planning_study, load_planning_study)

    res = load_planning_study(results_path("ch7_payload_arm"))
    check_planning_study(res, min_seeds=5)
    assert res["provenance"]["budget_cpu_s"] >= 240 and list(res["policies"]) == list(PAYLOAD_POLICIES)
    assert sorted(set(res["regimes"])) == sorted(PAYLOAD_REGIMES) and len(res["tasks"]) >= 3 * 6
    for name in PAYLOAD_MODELS:
        for run in res["training"][name]:
            assert run["steps"] > 100 and run["best_valid"] < 0.5 * run["curve"][0]["valid"], name


def test_the_chapter7_risk_study_is_complete():
    """Chapter 7's risk study: five seeds, Chapter 4's budget, every policy on every test target with
    its overshoot and failure, a risk weight per seed and learned predictor that is the argmin of the
    stored validation scores, and every planning model trained well past its initialization."""
    from pgm_wm.experiments.planning_study import (PLANNING_MODELS, RISK_POLICIES, check_planning_study,
                                                   load_planning_study)

    res = load_planning_study(results_path("ch7_risk"))
    check_planning_study(res, min_seeds=5)
    assert res["provenance"]["budget_cpu_s"] >= 240 and list(res["policies"]) == list(RISK_POLICIES)
    assert len(res["tasks"]) >= 16 and len(res["valid_tasks"]) >= 6
    margin = res["protocol"]["stop_margin"]
    for name, e in res["policies"].items():
        np.testing.assert_array_equal(np.asarray(e["failure"]) == 1.0, np.asarray(e["overshoot"]) > margin)
    for name, choices in res["risk_chosen"].items():
        for lam, scores in zip(choices, res["validation"][name]):
            assert lam == float(min(scores, key=lambda k: (sum(scores[k]["failure"]), np.mean(scores[k]["cost"]))))
    mean_valid = load_results(results_path("ch4_memory_arm"))["models"]["training mean"]["runs"][0]["best_valid"]
    for name in PLANNING_MODELS:
        for run in res["training"][name]:
            assert run["steps"] > 100 and run["best_valid"] < mean_valid, name


def test_readme_chapter6_verdicts():
    """The README's sentence on who meets the stopping rule in the Chapter 6 study is read off the file."""
    res = load_results(results_path("ch6_slow_payload_arm"))
    met = {n: sum(r["converged"] for r in e["runs"]) for n, e in res["models"].items() if e["trained"]}
    assert met == {"MTS3 (H = 25)": 3, "MTS3 fast level alone": 5, "ac-RKN (Chapter 4)": 2,
                   "HiP-RSSM (Chapter 5), carried": 0, "LSTM": 2, "GRU": 0, "Transformer": 0}, met
    plateau = min(r["best_valid"] for r in res["models"]["MTS3 fast level alone"]["runs"])
    for name, n_stalled in (("MTS3 (H = 25)", 1), ("LSTM", 2)):     # the stalls: converged at the fast level's plateau
        stalled = [r["converged"] for r in res["models"][name]["runs"] if r["best_valid"] > 0.9 * plateau]
        assert stalled == [True] * n_stalled, (name, stalled)
    readme = _readme_words()
    assert ("MTS3's fast level alone meets it in every seed (a stall at a payload-blind plateau), MTS3 in three seeds "
            "(one of them the same stall), the ac-RKN in two, the LSTM only in the two seeds that stalled") in readme


def test_readme_real_arm_verdicts():
    """The README's sentence on who meets the stopping rule in the real-arm study is read off the file."""
    res = load_results(results_path("ch4_pam_arm"))
    met = {n: sum(r["converged"] for r in e["runs"]) for n, e in res["models"].items() if e["trained"]}
    assert met == {"ac-RKN (difference readout)": 4, "ac-RKN (absolute readout)": 5, "ac-RKN (hybrid readout)": 5,
                   "ac-RKN, ‖A‖≤1": 3, "RKN (actions as obs.)": 4, "LSTM": 2, "GRU": 5, "FFNN": 5}, met
    assert res["protocol"]["lr"] == 3e-3
    assert not any("diverged" in r for e in res["models"].values() for r in e.get("runs", [])), "a run diverged"
    readme = _readme_words()
    assert ("33 of the 40 runs meet it: every seed of the GRU, the FFNN and the absolute and hybrid readouts, four of "
            "the difference readout and of the RKN that reads actions as observations, three of the norm-bounded "
            "ac-RKN and two of the LSTM") in readme
    assert sum(met.values()) == 33 and sum(len(e["runs"]) for e in res["models"].values() if e["trained"]) == 40
    assert "(no run of the real-arm study did)" in readme


def test_readme_chapter4_simulated_verdicts():
    """The README's sentence on the Chapter 4 simulated study is read off the file: only the FFNN meets
    the stopping rule, in every seed and at the floor of its learning rate, and the range it gives for
    how much every other model was still improving per doubling is the range in the file."""
    import re

    from pgm_wm.experiments.runner import final_lr_fraction

    res = load_results(results_path("ch4_memory_arm"))
    runs = {n: e["runs"] for n, e in res["models"].items() if e["trained"]}
    assert all(r["converged"] for r in runs["FFNN"]), "an FFNN seed no longer meets the rule"
    assert all(abs(final_lr_fraction(r) - res["protocol"]["lr_min_fraction"]) < 1e-9 for r in runs["FFNN"])
    assert not any(r["converged"] for n, rs in runs.items() if n != "FFNN" for r in rs), "another model meets the rule"
    impr = [r["improvement_last_doubling"] for n, rs in runs.items() if n != "FFNN" for r in rs]
    found = re.search(r"only the FFNN meets the rule, at its floor, in every seed; every recurrent model was still "
                      r"improving by (\d+) % to (\d+) % per doubling", _readme_words())
    assert found, "the README no longer states the Chapter 4 verdicts"
    assert (int(found[1]), int(found[2])) == (round(100 * min(impr)), round(100 * max(impr))), (found.groups(), impr)

"""The multi-seed statistics and results files of pgm_wm.experiments."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sps

from pgm_wm.experiments.results import (conclusions, load_results, provenance, save_results, summarize,
                                        summary_table)
from pgm_wm.experiments.stats import mean_interval, paired_mean_ratio, paired_ratio, rmse_interval


def test_mean_interval_matches_t_interval_for_one_seed():
    """One seed, many windows: the window bootstrap approximates the classical t interval."""
    rng = np.random.default_rng(1)
    x = rng.normal(3.0, 2.0, size=(1, 400))
    iv = mean_interval(x, n_boot=4000, seed=0)
    half = sps.t.ppf(0.975, 399) * x.std(ddof=1) / np.sqrt(400)
    assert iv.point == pytest.approx(x.mean())
    assert iv.lo == pytest.approx(x.mean() - half, abs=0.04)
    assert iv.hi == pytest.approx(x.mean() + half, abs=0.04)


def test_interval_coverage_close_to_nominal():
    """Over 300 simulated experiments (5 seeds with a seed effect, 40 windows) the 95 % interval
    of the grand mean covers the true mean at a rate near 0.95 (a two-level bootstrap with only 5
    seeds undercovers somewhat; a one-level window bootstrap would cover far less)."""
    rng = np.random.default_rng(2)
    hits = 0
    for _ in range(300):
        seed_effect = rng.normal(0.0, 0.5, size=(5, 1))
        x = 1.0 + seed_effect + rng.normal(0.0, 1.0, size=(5, 40))
        hits += not mean_interval(x, n_boot=400, seed=int(rng.integers(1 << 30))).excludes(1.0)
    assert 0.80 <= hits / 300 <= 0.99


def test_rmse_interval_is_sqrt_of_mean_and_orders():
    sq = np.full((3, 10), 4.0)
    iv = rmse_interval(sq)
    assert (iv.point, iv.lo, iv.hi) == (2.0, 2.0, 2.0)
    rng = np.random.default_rng(3)
    sq = rng.gamma(2.0, 1.0, size=(5, 50))
    iv = rmse_interval(sq, seed=1)
    assert iv.lo <= iv.point <= iv.hi
    assert iv.point == pytest.approx(np.sqrt(sq.mean()))
    assert rmse_interval(sq, seed=1) == iv          # deterministic for a seed


def test_paired_ratio_exact_cases_and_pairing():
    rng = np.random.default_rng(4)
    a = rng.gamma(2.0, 1.0, size=(1, 60))
    iv = paired_ratio(a, 4.0 * a)                    # same windows, errors doubled: ratio exactly 1/2
    assert iv.point == pytest.approx(0.5) and iv.lo == pytest.approx(0.5) and iv.hi == pytest.approx(0.5)
    # windows vary a lot, the model difference is small but consistent: pairing resolves it
    w = rng.gamma(0.5, 4.0, size=(1, 200))
    b = w * 1.1
    assert paired_ratio(w, b, seed=0).hi < 1.0
    # unpaired intervals of the two RMSEs overlap although the paired ratio is clear
    assert rmse_interval(w).hi > rmse_interval(b).lo


def test_paired_mean_ratio_exact_cases_pairing_and_relation_to_paired_ratio():
    rng = np.random.default_rng(5)
    a1 = rng.gamma(2.0, 1.0, size=(1, 40))
    iv = paired_mean_ratio(a1, 2.5 * a1)              # one seed, same tasks, costs times 2.5: exactly 0.4
    assert (iv.point, iv.lo, iv.hi) == pytest.approx((0.4, 0.4, 0.4))
    # a ratio of means is the square of paired_ratio applied to the same numbers as squared errors
    a = rng.gamma(2.0, 1.0, size=(3, 40))
    b = rng.gamma(2.0, 1.0, size=(3, 40))
    pm, pr = paired_mean_ratio(a, b, seed=3), paired_ratio(a, b, seed=3)
    assert (pm.point, pm.lo, pm.hi) == pytest.approx((pr.point ** 2, pr.lo ** 2, pr.hi ** 2))
    # tasks vary a lot, the difference is small but consistent: pairing resolves it
    w = rng.gamma(0.5, 4.0, size=(1, 150))
    assert paired_mean_ratio(w, 1.1 * w).hi < 1.0 and mean_interval(w).hi > mean_interval(1.1 * w).lo
    with pytest.raises(ValueError, match="^values_b"):
        paired_mean_ratio(np.ones((2, 3)), np.ones((2, 4)))
    with pytest.raises(ValueError, match="^values_a"):
        paired_mean_ratio(-np.ones((2, 3)), np.ones((2, 3)))


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="^values"):
        mean_interval(np.zeros(5))
    with pytest.raises(ValueError, match="^sq_err"):
        rmse_interval(-np.ones((2, 3)))
    with pytest.raises(ValueError, match="^values"):
        mean_interval(np.array([[1.0, np.nan]]))
    with pytest.raises(ValueError, match="^sq_err_b"):
        paired_ratio(np.ones((2, 3)), np.ones((2, 4)))
    with pytest.raises(ValueError, match="^level"):
        mean_interval(np.ones((2, 3)), level=1.5)


def _fake_results(rng: np.random.Generator) -> dict:
    horizons = [1, 10]
    base = rng.gamma(2.0, 1.0, size=(1, 2, 30))
    return {
        "chapter": "test", "horizons": horizons, "scale": 1.0, "units": "u",
        "provenance": provenance(budget_cpu_s=1.0, seeds=[0, 1, 2], wall_s=0.0),
        "models": {
            "good": {"sq_err": np.repeat(base, 3, 0) * 0.5, "nll": np.zeros((3, 2, 30))},
            "bad": {"sq_err": np.repeat(base, 3, 0), "nll": np.ones((3, 2, 30))},
            "same": {"sq_err": np.repeat(base, 3, 0) * 0.5 * (1 + 1e-9), "nll": np.zeros((3, 2, 30))},
        },
    }


def test_results_round_trip_table_and_conclusions(tmp_path):
    rng = np.random.default_rng(5)
    res = _fake_results(rng)
    path = save_results(tmp_path / "r.json", res)
    back = load_results(path)
    assert back["provenance"]["seeds"] == [0, 1, 2] and len(back["provenance"]["commit"]) > 0
    np.testing.assert_allclose(np.asarray(back["models"]["bad"]["sq_err"]), res["models"]["bad"]["sq_err"], rtol=1e-6)
    summ = summarize(back, n_boot=200)
    assert summ["good"]["rmse"][0].point == pytest.approx(np.sqrt(res["models"]["good"]["sq_err"][:, 0].mean()), rel=1e-6)
    table = summary_table(back, summ)
    assert table.count("\n") == 1 + 3 and "k = 10" in table
    text = conclusions(back, ["good", "bad"], n_boot=200)
    assert len(text) == 2 and all("good has the lowest RMSE" in s and "survives" in s for s in text)
    tie = conclusions(back, ["good", "same"], n_boot=200)
    assert all("not distinguishable" in s for s in tie)


def test_results_files_are_checked(tmp_path):
    with pytest.raises(ValueError, match="^path"):
        load_results(tmp_path / "missing.json")
    res = _fake_results(np.random.default_rng(6))
    res["models"]["bad"]["sq_err"] = np.ones((3, 2, 7))
    with pytest.raises(ValueError, match="^results"):
        save_results(tmp_path / "x.json", res)
    with pytest.raises(ValueError, match="^candidates"):
        conclusions(_fake_results(np.random.default_rng(7)), ["good", "nope"])


def test_report_renders_a_saved_file(tmp_path, monkeypatch):
    import pgm_wm.experiments.results as results

    monkeypatch.setattr(results, "_REPO", tmp_path)
    res = _fake_results(np.random.default_rng(8))
    for e in res["models"].values():
        e["trained"] = True
    save_results(results.results_path("demo"), res)
    text = results.report("demo", ["good", "bad"])
    assert "| good |" in text and "At k = 10, good has the lowest RMSE" in text and "Produced by" in text

"""The multi-seed experiment runner on a tiny synthetic system with a known best predictor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pgm_wm.baselines import LinearARX, RepeatLast, TrainingMean
from pgm_wm.datasets import SequenceData, split_sequences
from pgm_wm.experiments.results import conclusions, load_results
from pgm_wm.experiments.runner import Experiment, ModelSpec, Protocol, Splits, run_experiment, score


def _linear_system(n: int = 60, T: int = 40, seed: int = 0) -> Splits:
    """o_{t+1} = 0.9 o_t + 0.5 a_t + small noise: the order-1 ARX model is (nearly) the oracle."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, T, 1))
    o = np.zeros((n, T, 1))
    o[:, 0] = rng.normal(size=(n, 1))
    for t in range(T - 1):
        o[:, t + 1] = 0.9 * o[:, t] + 0.5 * a[:, t] + 0.01 * rng.normal(size=(n, 1))
    parts = split_sequences(SequenceData.from_arrays(o, a), (0.6, 0.2, 0.2), seed=0)
    return Splits(*parts)


SPLITS = _linear_system()
PROTOCOL = Protocol(context_len=5, horizon=10, horizons=(1, 5, 10), eval_stride=15, batch_size=8)


def _references() -> dict[str, ModelSpec]:
    def fitted(make):
        return ModelSpec(lambda s: make(*s.normalized("train")), trained=False)

    return {
        "arx": fitted(lambda o, a, v: LinearARX.fit(o, a, order=1, valid=v)),
        "repeat": fitted(lambda o, a, v: RepeatLast.fit(o, v)),
        "mean": fitted(lambda o, a, v: TrainingMean.fit(o, v)),
    }


def test_score_shapes_units_and_known_ordering():
    splits = SPLITS
    sq = {}
    for name, spec in _references().items():
        s, nll = score(spec.build(splits), splits, PROTOCOL)
        assert s.shape == nll.shape == (3, 2 * splits.test.n_sequences)   # 2 windows of 15 per sequence
        assert np.isfinite(s).all() and np.isfinite(nll).all() and (s >= 0).all()
        sq[name] = s
    # the (near-)oracle ARX beats repeat-last and the mean at every horizon, by a wide margin
    assert (sq["arx"].mean(1) < 0.2 * sq["repeat"].mean(1)).all()
    assert (sq["arx"].mean(1) < 0.2 * sq["mean"].mean(1)).all()
    # errors are in original units: rescaling the data by 10 scales squared errors by 100
    train = SequenceData.from_arrays(10 * splits.train.obs, splits.train.actions)
    big = Splits(train, *(SequenceData.from_arrays(10 * d.obs, d.actions, stats=train.stats)
                          for d in (splits.valid, splits.test)))
    s_big, _ = score(_references()["repeat"].build(big), big, PROTOCOL)
    np.testing.assert_allclose(s_big, 100 * sq["repeat"], rtol=1e-3)


def test_run_experiment_trains_scores_and_writes(tmp_path):
    from pgm_wm.builders import build_baseline

    models = dict(_references())
    models["gru"] = ModelSpec(lambda s: build_baseline("gru", 1, 1, hidden=8, predict_differences=False))
    exp = Experiment("tiny", "tiny linear system", lambda: SPLITS, models, PROTOCOL)
    run_experiment(exp, seeds=[0, 1], budget_s=0.3, out_path=str(tmp_path / "tiny.json"), log=lambda s: None)
    back = load_results(tmp_path / "tiny.json")
    runs = back["models"]["gru"]["runs"]
    assert len(runs) == 2 and all(r["epochs"] >= 1 and r["cpu_s"] > 0 for r in runs)
    g = np.asarray(back["models"]["gru"]["sq_err"])
    assert g.shape[0] == 2 and not np.array_equal(g[0], g[1])       # two seeds, two training runs
    assert back["provenance"]["seeds"] == [0, 1] and back["provenance"]["budget_cpu_s"] == 0.3
    sq = np.asarray(back["models"]["arx"]["sq_err"])
    assert sq.shape[0] == 2 and np.array_equal(sq[0], sq[1])       # deterministic rows repeat per seed
    text = conclusions(back, ["arx", "repeat", "mean"], n_boot=200)
    assert all(s.startswith(f"At k = {h}, arx has the lowest RMSE") for s, h in zip(text, PROTOCOL.horizons))
    with pytest.raises(ValueError, match="^models"):
        run_experiment(exp, [0], 0.1, models=["nope"])
    with pytest.raises(ValueError, match="^seeds"):
        run_experiment(exp, [], 0.1)


def test_protocol_checks():
    with pytest.raises(ValueError, match="^horizons"):
        Protocol(context_len=5, horizon=10, horizons=(11,), eval_stride=5)
    with pytest.raises(ValueError, match="^context_len"):
        Protocol(context_len=0, horizon=10, horizons=(1,), eval_stride=5)


def test_oracle_rows_are_scored_on_the_runner_windows():
    from pgm_wm.experiments.runner import score_oracle, test_windows

    def perfect(p: Protocol):
        wo, _ = test_windows(SPLITS, p)
        target = SPLITS.train.denormalize_obs(wo[:, p.context_len:])
        return target + 0.1, target

    sq = score_oracle(ModelSpec(oracle=perfect), SPLITS, PROTOCOL)
    np.testing.assert_allclose(sq, 0.01, rtol=1e-4)                      # a constant error of 0.1
    shifted = ModelSpec(oracle=lambda p: tuple(x[1:] for x in perfect(p)))   # one window missing
    with pytest.raises(ValueError, match="^oracle"):
        score_oracle(shifted, SPLITS, PROTOCOL)
    with pytest.raises(ValueError, match="^build"):
        ModelSpec()


def test_a_model_with_its_own_training_gets_the_same_budget_seed_and_validation():
    from pgm_wm.builders import build_baseline
    from pgm_wm.experiments.runner import train_model, validation_rmse
    from pgm_wm.training import FitHistory

    calls = {}

    def own_train(model, splits, protocol, seed, budget_s, valid_fn, max_steps=None):
        calls.update(seed=seed, budget=budget_s, protocol=protocol, valid=valid_fn(),
                     reference=validation_rmse(model, splits, protocol))
        curve = [{"step": 30, "epoch": 2, "cpu_s": 0.1, "wall_s": 0.1, "valid": calls["valid"], "train": 0.8}]
        return FitHistory(train_loss=[1.0, 0.9, 0.8], valid_loss=[calls["valid"]], curve=curve)

    spec = ModelSpec(lambda s: build_baseline("gru", 1, 1, hidden=8, predict_differences=False), train=own_train)
    exp = Experiment("tiny", "tiny", lambda: SPLITS, {"own": spec}, PROTOCOL)
    _, info = train_model(exp, "own", seed=4, budget_s=0.7)
    assert calls["seed"] == 4 and calls["budget"] == 0.7 and calls["protocol"] is PROTOCOL
    assert calls["valid"] == pytest.approx(calls["reference"])          # the generic validation windows
    assert info["epochs"] == 3 and info["best_valid"] == calls["valid"]
    assert info["steps"] == 30 and info["curve"][0]["valid"] == calls["valid"]


def test_score_dims_score_only_those_dimensions():
    """A 2-d system whose second dimension is 10x larger: scoring dimension 0 alone equals the
    squared error of that dimension computed by hand, and differs from the all-dimension score."""
    from dataclasses import replace

    rng = np.random.default_rng(1)
    o = np.cumsum(rng.normal(size=(40, 30, 2)), axis=1) * np.array([1.0, 10.0])
    parts = split_sequences(SequenceData.from_arrays(o, rng.normal(size=(40, 30, 1))), (0.6, 0.2, 0.2), seed=0)
    splits = Splits(*parts)
    p_all = Protocol(context_len=5, horizon=10, horizons=(1, 10), eval_stride=15)
    p_one = replace(p_all, score_dims=(0,))
    model = RepeatLast.fit(splits.normalized("train")[0], splits.train.valid)
    s_all, _ = score(model, splits, p_all)
    s_one, nll_one = score(model, splits, p_one)
    obs = splits.test.obs
    windows = np.stack([obs[:, :15].numpy(), obs[:, 15:30].numpy()], 1).reshape(-1, 15, 2)   # per sequence
    by_hand = (windows[:, [5, 14], 0] - windows[:, [4], 0]) ** 2            # repeat-last, dim 0
    np.testing.assert_allclose(s_one, by_hand.T, rtol=1e-4, atol=1e-6)
    assert s_all.mean() > 10 * s_one.mean() and np.isfinite(nll_one).all()
    with pytest.raises(ValueError, match="^score_dims"):
        Protocol(context_len=5, horizon=10, horizons=(1,), eval_stride=5, score_dims=())
    with pytest.raises(ValueError, match="^score_dims"):
        score(model, splits, replace(p_all, score_dims=(2,)))


def test_validation_choice_uses_validation_scores_only():
    """The pick follows best_valid, whatever the test errors say, and the sentence lists all."""
    from pgm_wm.experiments.results import validation_choice

    def entry(valids, test_err):
        return {"runs": [{"best_valid": v} for v in valids], "sq_err": np.full((len(valids), 1, 3), test_err)}

    res = {"models": {"a": entry([0.3, 0.5], 0.01), "b": entry([0.2, 0.4], 9.0), "c": entry([float("nan"), 0.1], 0.0)}}
    best, sentence = validation_choice(res, ["a", "b", "c"])
    assert best == "b" and "a 0.4" in sentence and "b 0.3" in sentence and "2 seeds" in sentence
    assert validation_choice(res, ["a", "c"])[0] == "a"            # a NaN validation score never wins
    with pytest.raises(ValueError, match="^variants"):
        validation_choice(res, ["a"])
    with pytest.raises(ValueError, match="^variants"):
        validation_choice(res, ["a", "zzz"])
    res["models"]["r"] = {"runs": [{"epochs": 0}], "sq_err": np.zeros((1, 1, 3))}
    with pytest.raises(ValueError, match="^variants"):
        validation_choice(res, ["a", "r"])


# ----------------------------------------------------------------------------- convergence protocol
def test_improvement_over_the_last_doubling_against_its_definition():
    from pgm_wm.experiments.runner import CONVERGENCE_TOL, improvement_over_last_doubling

    curve = [{"cpu_s": c, "valid": v} for c, v in ((1, 1.0), (4, 0.5), (5, 0.6), (9, 0.45), (10, 0.49))]
    # best by 5 s: 0.5; best by 10 s: 0.45 -> 10 % improvement over the last doubling
    assert improvement_over_last_doubling(curve, 10.0) == pytest.approx(0.1)
    assert improvement_over_last_doubling(curve, 8.0) == pytest.approx(0.0)      # best by 4 and by 8: 0.5
    assert improvement_over_last_doubling(curve, 1.0) == float("inf")           # nothing by 0.5 s
    assert np.isnan(improvement_over_last_doubling(curve, 0.5))                  # nothing at all
    inf = [{"cpu_s": 1, "valid": float("inf")}, {"cpu_s": 2, "valid": 0.3}]
    assert improvement_over_last_doubling(inf, 2.0) == float("inf")
    assert 0 < CONVERGENCE_TOL < 0.1


def test_thinned_curve_keeps_the_ends_every_new_best_and_every_test_checkpoint():
    from pgm_wm.experiments.runner import _thin

    rng = np.random.default_rng(0)
    curve = [{"step": 10 * i, "cpu_s": 0.1 * i, "valid": float(1 / (i + 1) + 0.05 * rng.random())}
             for i in range(1, 2000)]
    for i in (5, 700, 1500):
        curve[i]["test"] = 1.0
    kept = _thin(curve, n=40)
    assert kept[0] == curve[0] and kept[-1] == curve[-1] and len(kept) < len(curve) / 4
    assert sum("test" in e for e in kept) == 3
    best, bests = np.inf, []
    for e in curve:
        if e["valid"] < best:
            best = e["valid"]
            bests.append(e["step"])
    assert set(bests) <= {e["step"] for e in kept}


def _tiny_gru_experiment(checkpoints=(0.0, 0.05)):
    from dataclasses import replace

    from pgm_wm.builders import build_baseline

    p = replace(PROTOCOL, valid_every=2, curve_checkpoints_s=checkpoints)
    models = {"gru": ModelSpec(lambda s: build_baseline("gru", 1, 1, hidden=8, predict_differences=False)),
              **_references()}
    return Experiment("tiny", "tiny", lambda: SPLITS, models, p)


def test_train_model_records_a_learning_curve_steps_and_the_verdict():
    from pgm_wm.experiments.runner import improvement_over_last_doubling, train_model

    exp = _tiny_gru_experiment()
    _, info = train_model(exp, "gru", seed=0, budget_s=1e6, max_steps=9)
    assert info["steps"] == 9 and info["epochs"] >= 1
    steps = [e["step"] for e in info["curve"]]
    assert steps == [2, 4, 6, 8, 9]                                   # every valid_every steps and the end
    assert "test" in info["curve"][0] and all(np.isfinite(e["valid"]) for e in info["curve"])
    assert info["best_valid"] == min(e["valid"] for e in info["curve"])
    assert info["improvement_last_doubling"] == improvement_over_last_doubling(info["curve"], 1e6)
    assert info["converged"] == (info["improvement_last_doubling"] < 0.02)


def test_equal_steps_runs_are_reproducible_and_seed_parts_merge_to_the_whole(tmp_path):
    from pgm_wm.experiments.results import check_study, merge_results

    exp = _tiny_gru_experiment()
    whole = run_experiment(exp, [0, 1], 1e6, jobs=1, log=lambda s: None, max_steps=6)
    a = run_experiment(exp, [1], 1e6, jobs=1, log=lambda s: None, max_steps=6)
    b = run_experiment(exp, [0], 1e6, jobs=1, log=lambda s: None, max_steps=6)
    merged = merge_results([a, b])
    assert merged["provenance"]["seeds"] == [0, 1]
    for name in whole["models"]:
        np.testing.assert_allclose(merged["models"][name]["sq_err"], whole["models"][name]["sq_err"], rtol=1e-6)
    assert [r["steps"] for r in merged["models"]["gru"]["runs"]] == [6, 6]
    check_study(merged, min_seeds=2)
    with pytest.raises(ValueError, match="seeds"):
        check_study(merged, min_seeds=3)
    with pytest.raises(ValueError, match="overlap"):
        merge_results([a, a])
    broken = {**merged, "models": {**merged["models"], "gru": {**merged["models"]["gru"], "runs": [
        {k: v for k, v in r.items() if k != "curve"} for r in merged["models"]["gru"]["runs"]]}}}
    with pytest.raises(ValueError, match="curve"):
        check_study(broken, min_seeds=2)


def test_package_source_hash_tracks_the_source_and_the_note_says_so(tmp_path):
    import shutil

    import pgm_wm
    from pgm_wm.experiments.results import package_note, package_source_hash, provenance

    src = tmp_path / "pgm_wm"
    shutil.copytree(pgm_wm.__path__[0], src, ignore=shutil.ignore_patterns("__pycache__"))
    h0 = package_source_hash(src)
    assert h0 == package_source_hash()
    (src / "rkn.py").write_text((src / "rkn.py").read_text() + "\n# a change\n")
    assert package_source_hash(src) != h0
    here = {"provenance": provenance()}
    assert here["provenance"]["package_hash"] == h0 and package_note(here) is None
    # a file without per-file code hashes: only the source hash can be compared
    other = {"provenance": {k: v for k, v in here["provenance"].items() if k != "code_hashes"} | {"package_hash": "0" * 64}}
    assert "differs" in package_note(other)
    assert "did not record" in package_note({"provenance": {"date": "then"}})


def test_code_fingerprint_ignores_documentation_but_not_code():
    from pgm_wm.experiments.results import code_fingerprint

    base = 'def f(x):\n    """doc"""\n    return x + 1\n\nA = 2\n"""attribute doc"""\n'
    same = ('# a comment\ndef f(x):\n    """another, longer\n    docstring"""\n\n    return (x + 1)  # why\n\n\n'
            'A = 2\n')
    assert code_fingerprint(base) == code_fingerprint(same)
    assert code_fingerprint(base) != code_fingerprint(base.replace("x + 1", "x + 2"))
    assert code_fingerprint(base) != code_fingerprint(base.replace("A = 2", "A = 3"))
    # a function left with only its docstring still parses as a function that does nothing
    assert code_fingerprint('def g():\n    """only doc"""\n') == code_fingerprint("def g():\n    pass\n")


def test_package_note_lists_the_files_whose_code_changed(monkeypatch):
    from pgm_wm.experiments import results as R

    here = {"provenance": R.provenance()}
    now = here["provenance"]["code_hashes"]
    assert "experiments/results.py" in now and len(now) > 20
    assert R.changed_code(here) == [] and R.package_note(here) is None
    # another source hash but the same code (a documentation edit): no note
    doc_only = {"provenance": {**here["provenance"], "package_hash": "0" * 64}}
    assert R.changed_code(doc_only) == [] and R.package_note(doc_only) is None
    # code changed in one file, and a file that exists no more: both named; a file added since is not
    then = {**now, "rkn.py": "1" * 64, "gone.py": "2" * 64}
    then.pop("planning.py")
    changed = {"provenance": {**doc_only["provenance"], "code_hashes": then}}
    assert R.changed_code(changed) == ["gone.py", "rkn.py"]
    note = R.package_note(changed)
    assert "`pgm_wm/rkn.py`" in note and "`pgm_wm/gone.py`" in note and "planning.py" not in note
    assert "2 package files" in note


def test_committed_studies_record_the_code_that_made_them():
    import json

    for path in sorted(Path(__file__).resolve().parents[1].glob("results/*.json")):
        prov = json.loads(path.read_text())["provenance"]
        for p in [prov, *prov.get("parts", [])]:
            hashes = p.get("code_hashes")
            assert isinstance(hashes, dict) and len(hashes) > 20, path.name
            assert all(len(h) == 64 for h in hashes.values()), path.name


def test_cli_seed_start_and_merge(tmp_path):
    from pgm_wm.experiments.__main__ import main

    with pytest.raises(SystemExit):
        main(["ch4", "--seeds", "1", "--seed-start", "-1", "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit):
        main(["merge", str(tmp_path / "m.json"), str(tmp_path / "missing.json")])


def test_best_so_far_and_the_learning_curve_figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pgm_wm.plotting import best_so_far, plot_learning_curves

    curve = [{"cpu_s": 1.0, "valid": 3.0}, {"cpu_s": 2.0, "valid": 1.0}, {"cpu_s": 4.0, "valid": 2.0},
             {"cpu_s": 8.0, "valid": float("inf")}, {"cpu_s": 9.0, "valid": 0.5}]
    np.testing.assert_array_equal(best_so_far(curve, [0.5, 1.0, 3.0, 8.5, 10.0]), [np.nan, 3.0, 1.0, 1.0, 0.5])
    exp = _tiny_gru_experiment()
    res = run_experiment(exp, [0, 1], 1e6, jobs=1, log=lambda s: None, max_steps=6)
    fig, ax = plt.subplots()
    plot_learning_curves(ax, res)
    labels = [t.get_text() for t in ax.legend().get_texts()]
    assert labels[0] == "gru" and sum("(reference)" in s for s in labels) == 3
    assert len(ax.collections) == 1                       # one band (the trained model over its seeds)
    plt.close(fig)


def test_learning_curves_by_step_end_where_each_model_stopped():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pgm_wm.plotting import plot_learning_curves

    def run(last):
        steps = np.geomspace(1, last, 6)
        return {"curve": [{"step": float(t), "cpu_s": float(t), "valid": 1.0 / t} for t in steps]}

    res = {"models": {"slow": {"trained": True, "runs": [run(10), run(12)]},
                      "fast": {"trained": True, "runs": [run(100), run(90)]}}}
    fig, ax = plt.subplots()
    plot_learning_curves(ax, res, x="step")
    ends = {line.get_label(): line.get_xdata().max() for line in ax.lines}
    assert ends["slow"] <= 10 and 80 < ends["fast"] <= 90      # the shortest run of each model
    plt.close(fig)


def test_paired_ratios_per_horizon_equal_paired_ratio():
    from pgm_wm.experiments.results import paired_ratios
    from pgm_wm.experiments.stats import paired_ratio

    rng = np.random.default_rng(0)
    res = {"horizons": [1, 5], "models": {m: {"sq_err": rng.gamma(2.0, 1.0, size=(3, 2, 20))} for m in "abc"}}
    out = paired_ratios(res, "a", ["b", "c"], n_boot=200)
    assert set(out) == {"b", "c"} and all(len(v) == 2 for v in out.values())
    a, c = np.asarray(res["models"]["a"]["sq_err"]), np.asarray(res["models"]["c"]["sq_err"])
    assert out["c"][1] == paired_ratio(a[:, 1], c[:, 1], n_boot=200)
    with pytest.raises(ValueError, match="^ours"):
        paired_ratios(res, "a", ["z"])


def test_stored_models_load_back_to_the_same_predictions(tmp_path):
    from pgm_wm.experiments.runner import load_trained, model_path, test_windows

    exp = _tiny_gru_experiment()
    res = run_experiment(exp, [3], 1e6, jobs=1, log=lambda s: None, max_steps=4, save_models=tmp_path)
    assert model_path(tmp_path, "tiny", "gru", 3).is_file()
    assert not model_path(tmp_path, "tiny", "arx", 3).exists()          # reference rows are not stored
    model = load_trained(exp, "gru", 3, tmp_path)
    again, _ = score(model, SPLITS, exp.protocol)
    np.testing.assert_allclose(again, res["models"]["gru"]["sq_err"][0], rtol=1e-5)
    assert test_windows(SPLITS, exp.protocol)[0].shape[0] == again.shape[1]
    with pytest.raises(ValueError, match="^name"):
        load_trained(exp, "gru", 4, tmp_path)


def test_plot_horizon_errors_draws_the_summary():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pgm_wm.experiments.results import summarize
    from pgm_wm.plotting import plot_horizon_errors

    rng = np.random.default_rng(1)
    res = {"horizons": [1, 5, 10], "units": "mrad", "scale": 1e3,
           "models": {"net": {"trained": True, "sq_err": rng.gamma(2.0, 1e-6, size=(3, 3, 12))},
                      "arx": {"trained": False, "sq_err": rng.gamma(2.0, 1e-6, size=(3, 3, 12))}}}
    fig, ax = plt.subplots()
    s = summarize(res)
    plot_horizon_errors(ax, res, summary=s)
    lines = {line.get_label(): line for line in ax.lines}
    np.testing.assert_allclose(lines["net"].get_ydata(), [iv.point for iv in s["net"]["rmse"]])
    assert lines["arx"].get_linestyle() == "--" and len(ax.collections) == 1     # a band for the trained model only
    assert "mrad" in ax.get_ylabel()
    with pytest.raises(ValueError, match="^models"):
        plot_horizon_errors(ax, res, ["lstm"], summary=s)
    plt.close(fig)


def test_train_model_applies_the_protocols_learning_rate_floor():
    """With lr_patience 1 the study's schedule halves the rate after every validation without a
    new best: over 40 validations it falls below its start without a floor, and never below
    lr_min_fraction * lr with one (here 0.5, so at most one halving shows)."""
    from dataclasses import replace

    from pgm_wm.experiments.runner import train_model

    def lrs(fraction: float) -> list[float]:
        exp = _tiny_gru_experiment()
        exp = replace(exp, protocol=replace(exp.protocol, valid_every=1, lr_patience=1, lr_min_fraction=fraction))
        _, info = train_model(exp, "gru", seed=0, budget_s=1e6, max_steps=40)
        return [e["lr"] for e in info["curve"]]

    lr = PROTOCOL.lr
    free, floored = lrs(0.0), lrs(0.5)
    assert min(free) < 0.5 * lr
    assert min(floored) == pytest.approx(0.5 * lr) and max(floored) == pytest.approx(lr)
    with pytest.raises(ValueError, match="^lr_min_fraction"):
        replace(PROTOCOL, lr_min_fraction=1.5)


def test_final_lr_fraction_reads_the_rate_at_the_end_of_the_curve():
    from pgm_wm.experiments.runner import final_lr_fraction, train_model

    assert final_lr_fraction({"curve": [{"lr": 4e-3}, {"lr": 2e-3}, {"lr": 1e-3}]}) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="^run"):
        final_lr_fraction({"curve": []})
    with pytest.raises(ValueError, match="^run"):
        final_lr_fraction({"curve": [{"valid": 1.0}]})
    _, info = train_model(_tiny_gru_experiment(), "gru", seed=0, budget_s=1e6, max_steps=4)
    assert final_lr_fraction(info) == 1.0                                 # no schedule in the tiny protocol


def test_a_diverged_run_never_counts_as_converged_and_the_table_says_so():
    """A run that fit ended at a non-finite value (``stopped == "diverged"``) has a flat curve
    after its last finite step; the verdict must not read that as convergence."""
    from pgm_wm.builders import build_baseline
    from pgm_wm.experiments.results import training_table
    from pgm_wm.experiments.runner import train_model
    from pgm_wm.training import FitHistory

    def own_train(model, splits, protocol, seed, budget_s, valid_fn, max_steps=None):
        v = valid_fn()
        curve = [{"step": s, "epoch": 0, "cpu_s": c, "wall_s": c, "valid": v, "train": 0.5}
                 for s, c in ((10, 0.1), (20, 0.2), (30, 0.3))]
        for _ in curve[1:]:
            valid_fn()
        return FitHistory(train_loss=[0.5], valid_loss=[v] * 3, curve=curve, stopped=stopped,
                          diverged="loss_fn: failed at epoch 0: var: variances must be finite" if stopped == "diverged"
                          else None)

    spec = ModelSpec(lambda s: build_baseline("gru", 1, 1, hidden=8, predict_differences=False), train=own_train)
    exp = Experiment("tiny", "tiny", lambda: SPLITS, {"own": spec}, PROTOCOL)
    runs = []
    for stopped in ("diverged", "budget"):
        _, info = train_model(exp, "own", seed=0, budget_s=0.5)
        assert info["improvement_last_doubling"] == 0.0 and info["stopped"] == stopped
        assert info["converged"] is (stopped != "diverged") and ("diverged" in info) is (stopped == "diverged")
        runs.append(info)
    table = training_table({"models": {"own": {"trained": True, "runs": runs}}})
    assert "| 1/2 (1 diverged) |" in table
    table = training_table({"models": {"own": {"trained": True, "runs": runs[1:]}}})
    assert "| 1/1 |" in table and "diverged" not in table

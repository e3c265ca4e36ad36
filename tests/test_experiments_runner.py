"""The multi-seed experiment runner on a tiny synthetic system with a known best predictor."""

from __future__ import annotations

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

    def own_train(model, splits, protocol, seed, budget_s, valid_fn):
        calls.update(seed=seed, budget=budget_s, protocol=protocol, valid=valid_fn(),
                     reference=validation_rmse(model, splits, protocol))
        return FitHistory(train_loss=[1.0, 0.9, 0.8], valid_loss=[calls["valid"]])

    spec = ModelSpec(lambda s: build_baseline("gru", 1, 1, hidden=8, predict_differences=False), train=own_train)
    exp = Experiment("tiny", "tiny", lambda: SPLITS, {"own": spec}, PROTOCOL)
    _, info = train_model(exp, "own", seed=4, budget_s=0.7)
    assert calls["seed"] == 4 and calls["budget"] == 0.7 and calls["protocol"] is PROTOCOL
    assert calls["valid"] == pytest.approx(calls["reference"])          # the generic validation windows
    assert info["epochs"] == 3 and info["best_valid"] == calls["valid"]


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

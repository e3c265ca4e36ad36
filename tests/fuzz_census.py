"""Census of issue 13's input classes (not collected by pytest): run
``PYTHONPATH=. python tests/fuzz_census.py`` and read the counts

tried / clear (ValueError naming the argument) / wrong name (ValueError naming another argument)
/ silent (no error on invalid input) / NaN (non-finite output, no error) / crash (other exception),

and, for valid inputs, ok / NaN / crash. Each case is ``(expected argument name or None for a
valid input, thunk)``."""

from __future__ import annotations

import re
import sys
from collections import Counter

import torch

sys.path.insert(0, "tests")
from _fuzz import corrupt, gen, pos, randn, spd  # noqa: E402
from pgm_wm import builders  # noqa: E402
from pgm_wm.aggregation import bayesian_aggregation, set_update  # noqa: E402
from pgm_wm.beliefs import DiagGaussian, FactorizedBelief  # noqa: E402
from pgm_wm.factorized import factorized_filter, factorized_predict, factorized_update  # noqa: E402
from pgm_wm.gaussian import Gaussian, condition, log_density  # noqa: E402
from pgm_wm.kalman import kalman_filter, kf_predict, kf_update  # noqa: E402
from pgm_wm.metrics import gaussian_nll, rmse  # noqa: E402

KINDS = ["nan", "inf", "float16", "bfloat16", "mixed", "int", "shape"]


def outputs(x):
    if isinstance(x, torch.Tensor):
        return [x]
    if isinstance(x, (tuple, list)):
        return [t for y in x for t in outputs(y)]
    return [t for k in ("mean", "cov", "var", "var_upper", "var_lower", "cov_side") for t in
            ([getattr(x, k)] if isinstance(getattr(x, k, None), torch.Tensor) else [])] + (
        outputs(x.posterior) if hasattr(x, "posterior") else [])


def cases():
    for seed in range(3):
        for dt in (torch.float32, torch.float64):
            g = gen(seed)
            n, m = 2, 2
            v = dict(mean=randn(g, n, dtype=dt), cov=spd(g, n, dt), F=0.5 * randn(g, n, n, dtype=dt), Q=spd(g, n, dt),
                     H=randn(g, m, n, dtype=dt), R=spd(g, m, dt), y=randn(g, 3, 5, m, dtype=dt))
            fns = {
                "kalman_filter": (("y", "mean", "cov", "F", "H", "Q", "R"),
                                  lambda a: kalman_filter(a["y"], Gaussian(a["mean"], a["cov"]), a["F"], a["H"], a["Q"], a["R"])),
                "kf_predict": (("mean", "cov", "F", "Q"), lambda a: kf_predict(Gaussian(a["mean"], a["cov"]), a["F"], a["Q"])),
                "kf_update": (("mean", "cov", "H", "R"), lambda a: kf_update(Gaussian(a["mean"], a["cov"]), a["H"], a["R"], a["y"][0, 0])),
                "condition": (("mean", "cov", "H", "R"), lambda a: condition(Gaussian(a["mean"], a["cov"]), a["H"], a["R"], a["y"][0, 0])),
                "log_density": (("mean", "cov"), lambda a: log_density(a["y"][0, 0, :n], a["mean"], a["cov"])),
            }
            alias = {"mean": ("init.mean", "prior.mean", "mean"), "cov": ("init.cov", "prior.cov", "cov")}
            for fname, (args, fn) in fns.items():
                yield None, (lambda fn=fn, v=v: fn(v))
                for a in args:
                    for k in KINDS:
                        w = dict(v)
                        w[a] = corrupt(v[a], k)
                        yield alias.get(a, (a,)) + (("any",) if k in ("mixed", "shape") else ()), (lambda fn=fn, w=w: fn(w))
            # factorized / aggregation / metrics
            su, sl = pos(g, 2, m, dtype=dt), pos(g, 2, m, dtype=dt)
            fv = dict(mean=randn(g, 2, 2 * m, dtype=dt), su=su, sl=sl, ss=0.3 * (su * sl).sqrt(),
                      w=randn(g, 2, m, dtype=dt), wv=pos(g, 2, m, dtype=dt), r=randn(g, 2, 4, m, dtype=dt),
                      rv=pos(g, 2, 4, m, dtype=dt), target=randn(g, 2, m, dtype=dt))
            A = torch.eye(2 * m, dtype=dt) * 0.9
            ffns = {
                "factorized_update": (("mean", "su", "sl", "ss", "w", "wv"), lambda a: factorized_update(
                    FactorizedBelief(a["mean"], a["su"], a["sl"], a["ss"]), DiagGaussian(a["w"], a["wv"]))),
                "factorized_predict": (("mean", "su"), lambda a: factorized_predict(
                    FactorizedBelief(a["mean"], a["su"], a["sl"], a["ss"]), A[:m, :m], A[:m, m:], A[m:, :m], A[m:, m:],
                    torch.ones(2 * m, dtype=dt))),
                "factorized_filter": (("w", "wv"), lambda a: factorized_filter(
                    FactorizedBelief(a["mean"], a["su"], a["sl"], a["ss"]), A, torch.ones(2 * m, dtype=dt),
                    DiagGaussian(a["w"][:, None], a["wv"][:, None]))),
                "bayesian_aggregation": (("r", "rv"), lambda a: bayesian_aggregation(a["r"], a["rv"])),
                "set_update": (("r", "rv"), lambda a: set_update(DiagGaussian(a["w"], a["wv"]), DiagGaussian(a["r"], a["rv"]))),
                "rmse": (("w", "target"), lambda a: rmse(a["w"], a["target"])),
                "gaussian_nll": (("w", "wv", "target"), lambda a: gaussian_nll(a["w"], a["wv"], a["target"])),
            }
            falias = {"mean": ("prior.mean", "mean"), "su": ("prior.var_upper", "var_upper"),
                      "sl": ("prior.var_lower", "var_lower"), "ss": ("prior.cov_side", "cov_side"),
                      "w": ("observation.mean", "pred", "mean"), "wv": ("observation.var", "var"),
                      "r": ("r", "observation.mean"), "rv": ("r_var", "observation.var"), "target": ("target",)}
            for fname, (args, fn) in ffns.items():
                yield None, (lambda fn=fn, fv=fv: fn(fv))
                for a in args:
                    for k in KINDS:
                        if fname == "rmse" and k in ("nan", "inf"):
                            continue  # a NaN prediction has a NaN error by definition
                        w = dict(fv)
                        w[a] = corrupt(fv[a], k)
                        yield falias[a] + (("any",) if k in ("mixed", "shape") else ()), (lambda fn=fn, w=w: fn(w))
    # models
    torch.manual_seed(0)
    models = {"acrkn": builders.build_acrkn(2, 2, latent_obs_dim=3, hidden=8),
              "hiprssm": builders.build_hiprssm(2, 2, latent_obs_dim=3, task_dim=2, hidden=8),
              "mts3": builders.build_mts3(2, 2, 3, window=3, hidden=(8,)),
              "lstm": builders.build_baseline("lstm", 2, 2, hidden=8, rnn_hidden=8),
              "transformer": builders.build_baseline("transformer", 2, 2, hidden=8)}
    g = gen(0)
    obs, act = randn(g, 2, 6, 2, dtype=torch.float32), randn(g, 2, 6, 2, dtype=torch.float32)
    for mod in models.values():
        yield None, (lambda mod=mod: mod(obs, act))
        for k in KINDS:
            yield ("obs", "any") if k in ("mixed", "shape") else ("obs",), (lambda mod=mod, k=k: mod(corrupt(obs, k), act))
            yield ("actions", "any") if k in ("mixed", "shape") else ("actions",), (lambda mod=mod, k=k: mod(obs, corrupt(act, k)))
        yield ("obs",), (lambda mod=mod: mod(obs[:, :0], act[:, :0]))
        yield ("mask",), (lambda mod=mod: mod(obs, act, torch.ones(2, 5, dtype=torch.bool)))
        yield ("obs",), (lambda mod=mod: mod(obs.double(), act.double()))


def main() -> None:
    c = Counter()
    for names, thunk in cases():
        c["tried"] += 1
        try:
            with torch.no_grad():
                out = thunk()
        except ValueError as err:
            msg = str(err)
            if names is None:
                c["valid: crash"] += 1
            elif "any" in names or any(re.match(re.escape(n), msg) for n in names):
                c["clear"] += 1
            else:
                c["wrong name"] += 1
                print("wrong name:", names, msg[:100])
            continue
        except Exception as err:  # noqa: BLE001
            c["crash" if names is not None else "valid: crash"] += 1
            print("crash:", names, type(err).__name__, str(err)[:100])
            continue
        ok = all(bool(torch.isfinite(t).all()) for t in outputs(out))
        if names is None:
            c["valid: ok" if ok else "valid: NaN"] += 1
        else:
            c["NaN" if not ok else "silent"] += 1
            if True:
                print("no error:", names, "finite" if ok else "NaN")
    for k in ("tried", "valid: ok", "valid: NaN", "valid: crash", "clear", "wrong name", "silent", "NaN", "crash"):
        print(f"{k:>14}: {c[k]}")


if __name__ == "__main__":
    main()

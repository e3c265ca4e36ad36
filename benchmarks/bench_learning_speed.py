"""Validation RMSE reached per CPU second, against batch size and learning rate.

Issue 20 asks for batch sizes and learning rates *chosen by measurement*: sequences per CPU
second (``bench_training.py --batch``) and validation loss reached per CPU second (this script).
Issue 21 asks for the study budget to be measured with one or two seeds before a study is
regenerated. Both questions have the same experiment: train a chapter study's models exactly as
the study does, with one or two protocol fields changed, and look at the validation curves.

For every (model, batch size, learning rate, seed) the model is trained by
:func:`pgm_wm.experiments.runner.train_model`, the study's own training (same data, crops,
imputation masks, warm-up outside the budget, open-loop validation every ``valid_every`` steps,
keep-best, learning-rate halving, the stopping rule's statistic) under the study's protocol with
``batch_size`` and ``lr`` replaced. The output keeps the validation learning curve (CPU seconds,
steps, validation RMSE in the normalized units of the study), the steps, epochs, the best
validation RMSE and the stopping rule's verdict. The runner also records test RMSE at its curve
checkpoints (for the chapters' figures); this script drops it, so nothing here is chosen on, or
reports, test data.

    python benchmarks/bench_learning_speed.py ch4 --models GRU LSTM --configs 32:3e-3 128:6e-3 \
        --budget 240 --seeds 0 --jobs 2 --out benchmarks/results/learning_speed_ch4.json
    python benchmarks/bench_learning_speed.py --table benchmarks/results/learning_speed_ch4.json

``--lr-floor F`` sets the protocol's ``lr_min_fraction`` to ``F``: ``fit`` halves the learning
rate after every ``lr_patience`` validations without improvement, and without a floor the rate
can fall to ``1e-10`` of its start within a long budget, so that a run "converges" because it
has stopped moving. (The runs of ``learning_speed_ch4.json`` with a floor were made before the
package had ``lr_min``, by clamping Adam's rate at ``F`` times its start in the benchmark process:
the same schedule.) Without ``--lr-floor`` the study's own floor applies.

A new run appends to an existing ``--out`` file (runs of the same model, configuration, seed and
budget are replaced), so a long measurement can be split over several calls.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any


def _parse_config(text: str) -> tuple[int, float]:
    """``"128:6e-3"`` -> ``(128, 0.006)``."""
    try:
        batch, lr = text.split(":")
        out = int(batch), float(lr)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--configs: need BATCH:LR such as 128:6e-3, got {text!r}") from exc
    if out[0] < 1 or not (math.isfinite(out[1]) and out[1] > 0):
        raise argparse.ArgumentTypeError(f"--configs: need a positive batch and learning rate, got {text!r}")
    return out


def _run(task: tuple[str, str, int, float, int, float, float | None]) -> dict[str, Any]:
    """Train one (model, batch, lr, seed) for ``budget`` CPU seconds, one thread; the record."""
    import torch

    from pgm_wm.experiments.chapters import EXPERIMENTS
    from pgm_wm.experiments.runner import train_model

    chapter, name, batch, lr, seed, budget, floor = task
    torch.set_num_threads(1)
    exp = EXPERIMENTS[chapter]()
    changes: dict[str, Any] = {"batch_size": batch, "lr": lr}
    if floor is not None:
        changes["lr_min_fraction"] = floor
    exp = dataclasses.replace(exp, protocol=dataclasses.replace(exp.protocol, **changes))
    t0 = time.perf_counter()
    _, info = train_model(exp, name, seed, budget)
    curve = [{k: c[k] for k in ("step", "epoch", "cpu_s", "valid", "lr") if k in c} for c in info["curve"]]
    return {"model": name, "batch_size": batch, "lr": lr, "lr_floor": exp.protocol.lr_min_fraction or None, "seed": seed,
            "budget_cpu_s": budget,
            "wall_s": round(time.perf_counter() - t0, 1),
            **{k: info[k] for k in ("cpu_s", "warm_up_cpu_s", "steps", "epochs", "best_valid", "best_step",
                                    "improvement_last_doubling", "converged")},
            "sequences_per_cpu_s": round(info["steps"] * batch / max(info["cpu_s"] - info["warm_up_cpu_s"], 1e-9), 1),
            "curve": curve}


def _key(run: dict[str, Any]) -> tuple:
    return run["model"], run["batch_size"], run["lr"], run.get("lr_floor"), run["seed"], run["budget_cpu_s"]


def _line(run: dict[str, Any]) -> str:
    return (f"{run['model']:>32} batch {run['batch_size']:>4} lr {run['lr']:g} floor {run['lr_floor']} "
            f"seed {run['seed']}: {run['steps']} steps, best valid {run['best_valid']:.4f}")


def table(results: dict[str, Any], at: tuple[float, ...] = (30.0, 60.0, 120.0, 240.0, 480.0, 960.0)) -> str:
    """A markdown table: per model, configuration and budget (mean over seeds) the best validation
    RMSE reached by each of the CPU times ``at`` (and the largest budget), the steps, the sequences
    per CPU second, and the stopping rule (:func:`pgm_wm.experiments.runner.improvement_over_last_doubling`)
    applied at each of those times as if it were the budget ("–" beyond a run's budget). Nothing in
    the training depends on the budget (the learning rate is halved on validation plateaus, not on
    a schedule), so the first ``B`` seconds of a longer run are the run with budget ``B``."""
    from pgm_wm.experiments.runner import CONVERGENCE_TOL, improvement_over_last_doubling
    from pgm_wm.plotting import best_so_far

    runs = results["runs"]
    longest = max(r["budget_cpu_s"] for r in runs)
    at = tuple(a for a in at if a < longest) + (longest,)
    head = ("| model | batch | lr | lr floor | budget (s) | seeds | " + " | ".join(f"best valid by {a:g} s" for a in at)
            + " | steps | seq / CPU s | final lr / start | " + " | ".join(f"last doubling to {a:g} s" for a in at) + " |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault((r["model"], r["batch_size"], r["lr"], r.get("lr_floor"), r["budget_cpu_s"]), []).append(r)

    def mean(xs: list[float]) -> float:
        return sum(xs) / len(xs)

    for (model, batch, lr, floor, budget), rs in sorted(groups.items(),
                                                        key=lambda g: (g[0][0], g[0][4], g[0][1], g[0][2], g[0][3] or 0)):
        cells, stats = [], []
        for a in at:
            if a > budget:
                cells.append("–")
                stats.append("–")
                continue
            # a run's final validation comes a moment after its budget: at the budget, the whole run
            cells.append(f"{mean([float(best_so_far(r['curve'], [a if a < budget else math.inf])[0]) for r in rs]):.4f}")
            imp = [improvement_over_last_doubling(r["curve"], a) for r in rs]     # as the runner computes it
            stats.append(f"{100 * mean(imp):.1f} % ({sum(i < CONVERGENCE_TOL for i in imp)}/{len(rs)})")
        final_lr = " ".join(f"{r['curve'][-1]['lr'] / r['lr']:.0e}" for r in rs)
        lines.append(f"| {model} | {batch} | {lr:g} | {'none' if floor is None else f'{floor:g} lr'} | {budget:g} | {len(rs)} | " + " | ".join(cells)
                     + f" | {mean([r['steps'] for r in rs]):.0f} | {mean([r['sequences_per_cpu_s'] for r in rs]):.0f}"
                     + f" | {final_lr} | "
                     + " | ".join(stats) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("chapter", nargs="?", help="a study of pgm_wm.experiments.chapters.EXPERIMENTS, e.g. ch4")
    ap.add_argument("--models", nargs="*", help="model names of the study (default: every trained model)")
    ap.add_argument("--configs", nargs="+", type=_parse_config, default=None,
                    help="BATCH:LR pairs (default: the study's own)")
    ap.add_argument("--budget", type=float, default=240.0, help="CPU seconds per run")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--lr-floor", type=float, help="floor of the learning rate, a fraction of its start (default: the study's own)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", help="JSON file (appended to if it exists)")
    ap.add_argument("--table", help="print the table of a results file and exit")
    args = ap.parse_args(argv)
    if args.table:
        print(table(json.loads(Path(args.table).read_text())))
        return 0
    if not args.chapter:
        ap.error("chapter: give a study name (or --table FILE)")

    from pgm_wm.experiments.chapters import EXPERIMENTS
    from pgm_wm.experiments.results import provenance

    if args.chapter not in EXPERIMENTS:
        ap.error(f"chapter: unknown study {args.chapter!r} (known: {', '.join(EXPERIMENTS)})")
    exp = EXPERIMENTS[args.chapter]()
    names = args.models or [n for n, s in exp.models.items() if s.trained]
    for n in names:
        if n not in exp.models or not exp.models[n].trained:
            ap.error(f"--models: {n!r} is not a trained model of {args.chapter}")
    configs = args.configs or [(exp.protocol.batch_size, exp.protocol.lr)]
    if args.lr_floor is not None and not 0 < args.lr_floor < 1:
        ap.error(f"--lr-floor: need a fraction in (0, 1), got {args.lr_floor}")
    tasks = [(args.chapter, n, b, lr, s, args.budget, args.lr_floor) for n in names for b, lr in configs
             for s in args.seeds]

    out_path = Path(args.out) if args.out else None
    results: dict[str, Any] = {"study": exp.name, "protocol": dataclasses.asdict(exp.protocol), "runs": [],
                               "provenance": []}
    if out_path is not None and out_path.exists():
        results = json.loads(out_path.read_text())
        if results["study"] != exp.name:
            ap.error(f"--out: {out_path} holds study {results['study']!r}, not {exp.name!r}")
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    new: list[dict[str, Any]] = []
    if args.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("fork").Pool(args.jobs) as pool:
            for run in pool.imap_unordered(_run, tasks):
                print(_line(run), flush=True)
                new.append(run)
    else:
        for task in tasks:
            new.append(_run(task))
            print(_line(new[-1]), flush=True)
    done = {_key(r) for r in new}
    results["runs"] = [r for r in results["runs"] if _key(r) not in done] + new
    prov = provenance(budget_cpu_s=args.budget, seeds=args.seeds, jobs=args.jobs, configs=[list(c) for c in configs],
                      lr_floor=args.lr_floor,
                      models=names, load_avg_start=round(load, 2), load_avg_end=round(os.getloadavg()[0], 2),
                      wall_s=round(time.perf_counter() - t0, 1))
    prov.pop("code_hashes")          # the package hash identifies the code; the per-file list is for studies
    results["provenance"].append(prov)
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

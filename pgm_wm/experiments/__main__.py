"""``python -m pgm_wm.experiments NAME [--seeds 5] [--seed-start 0] [--budget 60] [--jobs 2] [--models A B]
[--max-steps N] [--out F] [--force]``: run a chapter's multi-seed experiment and write
``results/NAME.json`` (see :mod:`pgm_wm.experiments.runner`); ``python -m pgm_wm.experiments merge
OUT PART...`` merges parts run with different seeds; ``python -m pgm_wm.experiments ch7 [--seeds 5] [--budget 240]
[--jobs 2] [--tasks 16] [--out F] [--force]`` runs Chapter 7's closed-loop planning study
(:mod:`pgm_wm.experiments.planning_study`), ``ch7_payload`` (same options, ``--tasks`` per payload
regime) its payload study, ``ch7_risk`` (same options) its risk study. Every argument and the output path are checked before any
training; the file is written atomically; a committed results file is only replaced with
``--force``."""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .chapters import EXPERIMENTS
from .results import (check_output_path, conclusions, load_results, merge_results, provenance_text, save_results,
                      summary_table, training_table)
from .runner import run_experiment


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from err
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _budget(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected CPU seconds, got {text!r}") from err
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive finite number of CPU seconds, got {text!r}")
    return value


def merge_main(argv: list[str]) -> int:
    """``python -m pgm_wm.experiments merge OUT PART PART ... [--force]``: one results file from
    runs of the same study with different seeds (:func:`pgm_wm.experiments.results.merge_results`)."""
    parser = argparse.ArgumentParser(prog="python -m pgm_wm.experiments merge", description=merge_main.__doc__)
    parser.add_argument("out", help="the merged results file")
    parser.add_argument("parts", nargs="+", help="results files of the same study, disjoint seeds")
    parser.add_argument("--force", action="store_true", help="overwrite a committed results file")
    args = parser.parse_args(argv)
    try:
        check_output_path(args.out, force=args.force)
        merged = merge_results([load_results(p) for p in args.parts])
    except ValueError as err:
        parser.error(str(err))
    save_results(args.out, merged)
    print(f"merged {len(args.parts)} files, seeds {merged['provenance']['seeds']}: {args.out}")
    return 0


@dataclass(frozen=True)
class PlanningStudyCommand:
    """One Chapter 7 study on the command line: its protocol class, default results file, runner,
    the paired cost ratio printed as its headline (policy against rivals), which protocol field
    ``--tasks`` sets, and an optional printer of study-specific lines."""

    protocol: type
    default_out: str
    run: Callable[..., dict[str, Any]]
    headline: tuple[str, tuple[str, ...]]
    tasks_field: str = "n_tasks"
    tasks_help: str = "test targets per seed"
    extra: Callable[[dict[str, Any]], None] | None = None


def _print_risk_lines(res: dict[str, Any]) -> None:
    for name, e in res["policies"].items():
        print(f"{name:45s} failures {np.mean(e['failure']):.2f}  overshoot {1e3 * np.mean(e['overshoot']):.0f} mrad")
    print("risk weights chosen on validation targets:", res["risk_chosen"])


def planning_study_commands() -> dict[str, PlanningStudyCommand]:
    """The Chapter 7 studies by command name (imports :mod:`pgm_wm.experiments.planning_study`)."""
    from . import planning_study as ps

    return {
        "ch7": PlanningStudyCommand(ps.PlanningProtocol, "ch7_memory_arm.json", ps.run_planning_study,
                                    ("CEM through the ac-RKN", ("CEM through the ARX model", "CEM through the GRU"))),
        "ch7_payload": PlanningStudyCommand(ps.PayloadProtocol, "ch7_payload_arm.json", ps.run_payload_study,
                                            ("CEM through the HiP-RSSM", ("CEM through the ac-RKN",
                                                                          "CEM + true-payload simulator")),
                                            tasks_field="n_per_regime", tasks_help="tasks per payload regime"),
        "ch7_risk": PlanningStudyCommand(ps.RiskProtocol, "ch7_risk.json", ps.run_risk_study,
                                         ("CEM through the ac-RKN, risk-averse", ("CEM through the ac-RKN",)),
                                         extra=_print_risk_lines),
    }


def ch7_main(argv: list[str], study: str = "ch7") -> int:
    """``python -m pgm_wm.experiments ch7 ...``: Chapter 7's closed-loop study on the memory arm
    (:func:`pgm_wm.experiments.planning_study.run_planning_study`, ``results/ch7_memory_arm.json``);
    ``python -m pgm_wm.experiments ch7_payload ...``: its payload study
    (:func:`pgm_wm.experiments.planning_study.run_payload_study`, ``results/ch7_payload_arm.json``);
    ``python -m pgm_wm.experiments ch7_risk ...``: its risk study
    (:func:`pgm_wm.experiments.planning_study.run_risk_study`, ``results/ch7_risk.json``), unless
    ``--out`` says otherwise."""
    from . import planning_study as ps

    cmd = planning_study_commands()[study]
    parser = argparse.ArgumentParser(prog=f"python -m pgm_wm.experiments {study}", description=ch7_main.__doc__)
    parser.add_argument("--seeds", type=_positive_int, default=5, help="number of seeds; default 5")
    parser.add_argument("--seed-start", type=int, default=0, help="first seed (default 0)")
    parser.add_argument("--budget", type=_budget, default=240.0,
                        help="CPU seconds of training per model and seed (default 240, the chapters' studies)")
    parser.add_argument("--max-steps", type=_positive_int, default=None, help="also stop training after this many steps")
    parser.add_argument("--tasks", type=_positive_int, default=getattr(cmd.protocol, cmd.tasks_field),
                        help=cmd.tasks_help)
    parser.add_argument("--steps", type=_positive_int, default=cmd.protocol.steps, help="control steps per task")
    parser.add_argument("--jobs", type=_positive_int, default=1,
                        help=f"parallel processes (each one thread); at most {os.cpu_count() or 1} here")
    parser.add_argument("--out", default=None, help=f"output file (default results/{cmd.default_out})")
    parser.add_argument("--force", action="store_true", help="overwrite a committed results file")
    args = parser.parse_args(argv)
    if args.jobs > (os.cpu_count() or 1):
        parser.error(f"argument --jobs: {args.jobs} processes but this machine has {os.cpu_count()} CPUs")
    if args.seed_start < 0:
        parser.error("argument --seed-start: must be >= 0")
    out = args.out or str(Path(__file__).resolve().parents[2] / "results" / cmd.default_out)
    try:
        check_output_path(out, force=args.force)
        protocol = cmd.protocol(**{cmd.tasks_field: args.tasks}, steps=args.steps,
                                success_steps=min(cmd.protocol.success_steps, args.steps))
    except ValueError as err:
        parser.error(f"argument --out: {err}" if "out" in str(err)[:4] else str(err))
    res = cmd.run(range(args.seed_start, args.seed_start + args.seeds), args.budget, out,
                  protocol=protocol, jobs=args.jobs, max_steps=args.max_steps)
    for name, row in ps.planning_table(res, n_boot=500).items():
        print(f"{name:32s} cost {row['cost'].format()}  success {row['success'].format('.2f')}  "
              f"final error {row['final_error'].format('.3g', 1e3)} mrad")
    policy, rivals = cmd.headline
    for rival, iv in ps.planning_ratios(res, policy, list(rivals), n_boot=500).items():
        print(f"cost ratio {policy} / {rival}: {iv.format()}")
    if cmd.extra is not None:
        cmd.extra(res)
    print(f"written: {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "merge":
        return merge_main(argv[1:])
    if argv and argv[0] in planning_study_commands():
        return ch7_main(argv[1:], argv[0])
    parser = argparse.ArgumentParser(prog="python -m pgm_wm.experiments", description=__doc__)
    parser.add_argument("name", choices=sorted(EXPERIMENTS), help="which chapter's experiment")
    parser.add_argument("--seeds", type=_positive_int, default=5, help="number of seeds; default 5")
    parser.add_argument("--seed-start", type=int, default=0,
                        help="first seed (default 0): --seeds 3 --seed-start 5 runs seeds 5, 6, 7 (merge the parts "
                             "with `python -m pgm_wm.experiments merge`)")
    parser.add_argument("--save-models", default=None,
                        help="folder where every trained model's parameters are stored (runner.model_path)")
    parser.add_argument("--max-steps", type=_positive_int, default=None,
                        help="also stop every model after this many optimizer steps (equal-steps comparison)")
    parser.add_argument("--budget", type=_budget, default=60.0, help="CPU seconds of training per model and seed")
    parser.add_argument("--jobs", type=_positive_int, default=1,
                        help=f"parallel processes (each one thread); at most {os.cpu_count() or 1} here")
    parser.add_argument("--models", nargs="+", default=None, help="only these models (default: all)")
    parser.add_argument("--out", default=None, help="output file (default results/<experiment>.json)")
    parser.add_argument("--force", action="store_true", help="overwrite a committed results file")
    args = parser.parse_args(argv)
    if args.jobs > (os.cpu_count() or 1):
        parser.error(f"argument --jobs: {args.jobs} processes but this machine has {os.cpu_count()} CPUs")
    exp = EXPERIMENTS[args.name]()
    if args.models is not None:
        unknown = [m for m in args.models if m not in exp.models]
        if unknown:
            parser.error(f"argument --models: unknown model(s) {', '.join(map(repr, unknown))}; known: "
                         f"{', '.join(map(repr, exp.models))}")
        if len(set(args.models)) != len(args.models):
            parser.error("argument --models: a model is named twice")
    out = args.out or str(Path(__file__).resolve().parents[2] / "results" / f"{exp.name}.json")
    try:
        check_output_path(out, force=args.force)
    except ValueError as err:
        parser.error(f"argument --out: {err}")
    if args.seed_start < 0:
        parser.error("argument --seed-start: must be >= 0")
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    res = run_experiment(exp, seeds, args.budget, out, jobs=args.jobs, models=args.models, max_steps=args.max_steps,
                         save_models=args.save_models)
    print(summary_table(res))
    print(training_table(res))
    if len(res["models"]) >= 2:
        for sentence in conclusions(res):
            print("-", sentence)
    else:
        print("- one model only: no comparison to state")
    print(provenance_text(res))
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

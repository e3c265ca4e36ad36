"""``python -m pgm_wm.experiments NAME [--seeds 5] [--budget 60] [--jobs 2]``: run a chapter's
multi-seed experiment and write ``results/NAME.json`` (see :mod:`pgm_wm.experiments.runner`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .chapters import EXPERIMENTS
from .results import conclusions, provenance_text, summary_table
from .runner import run_experiment


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pgm_wm.experiments", description=__doc__)
    parser.add_argument("name", choices=sorted(EXPERIMENTS), help="which chapter's experiment")
    parser.add_argument("--seeds", type=int, default=5, help="number of seeds (0, 1, ...); default 5")
    parser.add_argument("--budget", type=float, default=60.0, help="CPU seconds of training per model and seed")
    parser.add_argument("--jobs", type=int, default=1, help="parallel processes (each one thread)")
    parser.add_argument("--models", nargs="*", default=None, help="only these models (default: all)")
    parser.add_argument("--out", default=None, help="output file (default results/<experiment>.json)")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error("--seeds: need at least 1")
    exp = EXPERIMENTS[args.name]()
    out = args.out or str(Path(__file__).resolve().parents[2] / "results" / f"{exp.name}.json")
    res = run_experiment(exp, list(range(args.seeds)), args.budget, out, jobs=args.jobs, models=args.models)
    print(summary_table(res))
    for sentence in conclusions(res):
        print("-", sentence)
    print(provenance_text(res))
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

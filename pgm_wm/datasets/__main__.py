"""Command line: ``python -m pgm_wm.datasets build [--only NAME ...] [--out DIR]``, ``... check``
(verify ``SHA256SUMS``) or ``... report`` (the linear checks of :mod:`.diagnostics`)."""

from __future__ import annotations

import argparse
import sys

from ._io import read_sha256sums, sha256_file
from .build import build_all
from .loader import DATASET_NAMES, data_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pgm_wm.datasets",
                                     description="Build or check the bundled datasets.")
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="regenerate the data files and SHA256SUMS")
    b.add_argument("--only", nargs="+", choices=DATASET_NAMES, help="datasets to rebuild (default: all)")
    b.add_argument("--out", default=None, help="output folder (default: $PGM_WM_DATA or <repo>/data)")
    c = sub.add_parser("check", help="verify the files against SHA256SUMS")
    c.add_argument("--dir", default=None, help="data folder (default: $PGM_WM_DATA or <repo>/data)")
    sub.add_parser("report", help="print the linear checks of pgm_wm.datasets.diagnostics")
    args = parser.parse_args(argv)
    if args.command == "build":
        build_all(args.only, args.out)
        return 0
    if args.command == "report":
        from .diagnostics import report

        report()
        return 0
    folder = data_dir() if args.dir is None else args.dir
    bad = 0
    for name, digest in read_sha256sums(folder).items():
        ok = sha256_file(f"{folder}/{name}") == digest
        bad += not ok
        print(f"{name}: {'OK' if ok else 'MISMATCH'}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

"""Command line: ``python -m pgm_wm.datasets build [--only NAME ...] [--out DIR]``, ``... check``
(verify ``SHA256SUMS``) or ``... report`` (the linear checks of :mod:`.diagnostics`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._io import read_sha256sums, sha256_file
from .build import build_all
from .loader import DATASET_NAMES, FILENAMES, data_dir, restore_command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pgm_wm.datasets",
                                     description="Build or check the bundled datasets.")
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="regenerate the data files and SHA256SUMS")
    b.add_argument("--only", nargs="+", choices=DATASET_NAMES, help="datasets to rebuild (default: all)")
    b.add_argument("--out", default=None, help="output folder (default: $PGM_WM_DATA or <repo>/data)")
    b.add_argument("--pam-source", default=None,
                   help="pam_arm_subset.npz to convert (default: $PGM_WM_PAM_SOURCE or shared/data/)")
    c = sub.add_parser("check", help="verify the files against SHA256SUMS")
    c.add_argument("--dir", default=None, help="data folder (default: $PGM_WM_DATA or <repo>/data)")
    sub.add_parser("report", help="print the checks of pgm_wm.datasets.diagnostics and .structure")
    args = parser.parse_args(argv)
    if args.command == "build":
        build_all(args.only, args.out, pam_source=args.pam_source)
        return 0
    if args.command == "report":
        from . import diagnostics, structure

        diagnostics.report()
        structure.report()
        return 0
    return check(Path(data_dir() if args.dir is None else args.dir))


def check(folder: Path) -> int:
    """Print one verdict per file of ``folder/SHA256SUMS``; 0 when all match, else 1 (no traceback)."""
    try:
        sums = read_sha256sums(folder)
    except (OSError, ValueError) as err:
        print(f"cannot read {folder / 'SHA256SUMS'}: {err}\n"
              f"rebuild the data and the checksums with `python -m pgm_wm.datasets build`")
        return 1
    bad = []
    for filename, digest in sums.items():
        path = folder / filename
        if not path.is_file():
            verdict = "MISSING"
        else:
            try:
                verdict = "OK" if sha256_file(path) == digest else "MISMATCH"
            except OSError as err:
                verdict = f"UNREADABLE ({err})"
        print(f"{filename}: {verdict}")
        if verdict != "OK":
            bad.append(filename)
    if bad:
        print(f"{len(bad)} of {len(sums)} files missing or corrupt: {', '.join(bad)}")
        for name in (n for n, f in FILENAMES.items() if f in bad):
            print(f"  restore {FILENAMES[name]} with `{restore_command(name)}`")
        return 1
    print(f"all {len(sums)} files match SHA256SUMS")
    return 0


if __name__ == "__main__":
    sys.exit(main())

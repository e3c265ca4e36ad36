#!/usr/bin/env python
"""Remove outputs, execution counts and saved widget state from notebooks, in place.

The chapter notebooks are committed output-free (``tests/test_book_notebooks.py`` checks
it). Run this before committing, or install it as a git filter once, so that ``git add``
stores the cleaned version while your working copy keeps its outputs::

    python scripts/clear_notebooks.py notebooks/*.ipynb        # clean in place
    python scripts/clear_notebooks.py --check notebooks/*.ipynb  # exit 1 if any is dirty
    python scripts/clear_notebooks.py --install-git-filter     # once per clone

The filter reads a notebook on stdin and writes the cleaned notebook to stdout
(``--stdin``). Uses only the standard library (no nbconvert/nbstripout download).
Cell sources, cell metadata (tags) and the notebook's kernelspec are kept; the JSON is
written with one-space indentation and a trailing newline, as JupyterLab writes it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DROP_CELL_METADATA = ("execution", "collapsed", "scrolled")


def clean(nb: dict) -> dict:
    for cell in nb.get("cells", []):
        if cell.get("cell_type") == "code":
            cell["outputs"] = []
            cell["execution_count"] = None
        for key in DROP_CELL_METADATA:
            cell.get("metadata", {}).pop(key, None)
    nb.get("metadata", {}).pop("widgets", None)
    return nb


def dumps(nb: dict) -> str:
    return json.dumps(nb, indent=1, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="*", type=Path)
    parser.add_argument("--check", action="store_true", help="only report; exit 1 if dirty")
    parser.add_argument("--stdin", action="store_true", help="filter stdin to stdout")
    parser.add_argument("--install-git-filter", action="store_true",
                        help="configure this clone's git to clean notebooks on `git add`")
    args = parser.parse_args(argv)
    if args.install_git_filter:
        script = "python scripts/clear_notebooks.py --stdin"
        subprocess.run(["git", "config", "filter.clear-notebooks.clean", script], check=True,
                       cwd=ROOT)
        subprocess.run(["git", "config", "filter.clear-notebooks.smudge", "cat"], check=True,
                       cwd=ROOT)
        attributes = ROOT / ".git" / "info" / "attributes"
        line = "notebooks/*.ipynb filter=clear-notebooks\n"
        attributes.parent.mkdir(parents=True, exist_ok=True)
        text = attributes.read_text() if attributes.exists() else ""
        if line not in text:
            attributes.write_text(text + line)
        print("clear_notebooks.py: git now strips outputs from notebooks/*.ipynb on `git add` "
              "(your working copies keep theirs)")
        return 0
    if args.stdin:
        sys.stdout.write(dumps(clean(json.loads(sys.stdin.read()))))
        return 0
    dirty = []
    for path in args.paths:
        text = path.read_text(encoding="utf-8")
        cleaned = dumps(clean(json.loads(text)))
        if json.loads(cleaned) != json.loads(text):
            dirty.append(path)
            if not args.check:
                path.write_text(cleaned, encoding="utf-8")
    verb = "has outputs" if args.check else "cleaned"
    for path in dirty:
        print(f"clear_notebooks.py: {path} {verb}")
    return 1 if (args.check and dirty) else 0


if __name__ == "__main__":
    sys.exit(main())

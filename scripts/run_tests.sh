#!/usr/bin/env bash
# Run the whole test suite: set up .venv, lint with ruff (rules in pyproject.toml), then run the
# unit tests in tests/ and execute every chapter notebook in notebooks/ with nbmake, in one
# pytest session.
# Exits non-zero on any failure, and also when a chapter listed in _toc.yml is missing
# or pytest collects nothing.
#
# Usage: bash scripts/run_tests.sh [extra pytest arguments]
set -euo pipefail

source "$(dirname "${BASH_SOURCE[0]}")/setup_env.sh"   # cd's to the repository root

# Every notebook listed in the book's table of contents must exist.
missing=0
for nb in $(grep -oE 'notebooks/[A-Za-z0-9_.-]+' _toc.yml); do
    if [ ! -f "$nb.ipynb" ] && [ ! -f "$nb" ]; then
        echo "[run_tests] ERROR: $nb.ipynb is listed in _toc.yml but does not exist" >&2
        missing=1
    fi
done
n_tests=$(find tests -name 'test_*.py' | wc -l)
n_notebooks=$(find notebooks -maxdepth 1 -name '*.ipynb' | wc -l)
echo "[run_tests] $n_tests test files in tests/, $n_notebooks notebooks in notebooks/"

# Batch runs: no progress bars, and no live ipywidgets (a cell that opens widget comms can make
# nbclient wait forever; chapter 1 shows a static grid instead, see its slider cell).
export PGM_WM_PROGRESS=0 PGM_WM_WIDGETS=0

# Lint first (about a second): a failure here stops before the long pytest run.
if ! ruff check --quiet .; then
    echo "[run_tests] FAILED: ruff found the problems above (rules in pyproject.toml [tool.ruff])" >&2
    exit 1
fi
echo "[run_tests] ruff: clean"

start=$(date +%s)
status=0
python -m pytest tests notebooks --nbmake --nbmake-timeout=600 "$@" || status=$?
elapsed=$(( $(date +%s) - start ))

if [ "$status" -eq 5 ]; then
    echo "[run_tests] FAILED: pytest collected no tests (exit 5)" >&2
    exit 5
fi
if [ "$status" -ne 0 ]; then
    echo "[run_tests] FAILED (pytest exit $status) after ${elapsed}s" >&2
    exit "$status"
fi
if [ "$missing" -ne 0 ] || [ "$n_tests" -eq 0 ] || [ "$n_notebooks" -eq 0 ]; then
    echo "[run_tests] FAILED: tests passed, but test files or chapter notebooks are missing" >&2
    exit 1
fi
echo "[run_tests] OK: all tests and notebooks passed in ${elapsed}s"

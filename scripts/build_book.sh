#!/usr/bin/env bash
# Build the book: set up .venv, vendor MathJax + the widget manager, then execute every
# notebook and render the HTML into _build/html/index.html. Works offline.
# Exits non-zero if any notebook cell raises or Sphinx emits any warning.
#
# Usage: bash scripts/build_book.sh
set -euo pipefail

source "$(dirname "${BASH_SOURCE[0]}")/setup_env.sh"   # cd's to the repository root

start=$(date +%s)
python scripts/vendor_assets.py

# Rendered pages show results, not progress: pgm_wm's training loops draw no tqdm bar
# when PGM_WM_PROGRESS=0 (interactive runs in JupyterLab keep their bars). The executing
# kernels inherit this environment.
export PGM_WM_PROGRESS=0
# no live ipywidgets in batch execution (nbclient can wait forever on widget comms); the page
# shows chapter 1's static grid instead
export PGM_WM_WIDGETS=0

# --all: rebuild every page from scratch, so every notebook is executed on every build
#        (execute_notebooks: force only executes the pages Sphinx re-reads).
# -W --keep-going: any Sphinx warning (broken reference, unknown citation key, ...) makes
#        the build fail after all of them are reported. A notebook cell that raises stops
#        the build at once (execute.raise_on_error in _config.yml).
# Each kernel logs "Kernel is running over TCP without encryption" when it starts (the
# kernel and the build talk over loopback only); that line is dropped from the log, all
# other output (warnings, errors) is shown unchanged.
set +e
jupyter-book build . --all -W --keep-going 2>&1 \
    | grep --line-buffered -v "Kernel is running over TCP without encryption"
codes=("${PIPESTATUS[@]}")
set -e
status=${codes[0]}

elapsed=$(( $(date +%s) - start ))
if [ "$status" -ne 0 ]; then
    echo "[build_book] FAILED (exit $status) after ${elapsed}s; see the warnings/errors above" >&2
    exit "$status"
fi
if [ ! -f _build/html/index.html ]; then
    echo "[build_book] FAILED: _build/html/index.html was not produced" >&2
    exit 1
fi
# The rendered pages must not fetch scripts, styles or fonts from any server.
python scripts/check_offline.py _build/html
echo "[build_book] OK in ${elapsed}s: open _build/html/index.html"

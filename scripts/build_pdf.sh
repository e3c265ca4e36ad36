#!/usr/bin/env bash
# Build the whole book as one PDF, offline: Jupyter Book's LaTeX builder (XeLaTeX, settings in
# _config.yml under "latex:") with Debian's TeX Live. Like build_book.sh it sets up .venv and
# executes every chapter, so the PDF shows the outputs of this run. The result is
# _build/pgm_wm_book.pdf; if the HTML book has been built (_build/html), the PDF is also
# copied next to its pages, where the introduction's download link points.
#
# Needs (Debian 12; texlive-xetex pulls in texlive-latex-extra and -recommended):
#   apt-get install -y --no-install-recommends latexmk texlive-xetex texlive-latex-extra \
#       texlive-fonts-recommended fonts-freefont-otf fonts-dejavu-core
#
# Usage: bash scripts/build_pdf.sh                # execute every chapter, then typeset
#        bash scripts/build_pdf.sh --no-execute   # typeset the pages without running them, a
#            quick check of the LaTeX side; the result, without any cell output, is
#            _build/pgm_wm_book_no_outputs.pdf and is not copied next to the HTML pages
set -euo pipefail

execute=force
case "${1:-}" in
    "") ;;
    --no-execute) execute=off ;;
    *) echo "usage: bash scripts/build_pdf.sh [--no-execute]" >&2; exit 2 ;;
esac

missing=()
for tool in latexmk xelatex; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
if [ "${#missing[@]}" -ne 0 ]; then
    echo "[build_pdf] ERROR: ${missing[*]} not found. Install Debian's TeX packages:" >&2
    echo "  apt-get install -y --no-install-recommends latexmk texlive-xetex texlive-latex-extra \\" >&2
    echo "      texlive-fonts-recommended fonts-freefont-otf fonts-dejavu-core" >&2
    exit 2
fi

source "$(dirname "${BASH_SOURCE[0]}")/setup_env.sh"   # cd's to the repository root

start=$(date +%s)
# Same environment as build_book.sh: no progress bars, no live widgets in batch execution.
export PGM_WM_PROGRESS=0 PGM_WM_WIDGETS=0

# The book's _config.yml, with the chosen execution mode; relative paths made absolute so that
# the copy can live in _build/.
mkdir -p _build
config=_build/pdf_config.yml
python - "$execute" "$config" <<'PY'
import sys
from pathlib import Path

import yaml

execute, out = sys.argv[1], Path(sys.argv[2])
root = Path.cwd()
cfg = yaml.safe_load((root / "_config.yml").read_text(encoding="utf-8"))
cfg["execute"]["execute_notebooks"] = execute
sphinx = cfg["sphinx"]
sphinx["local_extensions"] = {k: str(root / v) for k, v in sphinx["local_extensions"].items()}
conf = sphinx["config"]
conf["latex_additional_files"] = [str(root / f) for f in conf.get("latex_additional_files", [])]
out.write_text(yaml.safe_dump(cfg, sort_keys=False, allow_unicode=True), encoding="utf-8")
PY

rm -rf _build/latex   # a clean LaTeX run (stale .idx/.aux files from another run confuse latexmk)
set +e
jupyter-book build . --all --builder pdflatex --config "$config" 2>&1 \
    | grep --line-buffered -v "Kernel is running over TCP without encryption"
status=${PIPESTATUS[0]}
set -e
elapsed=$(( $(date +%s) - start ))
pdf=_build/latex/pgm_wm_book.pdf
if [ "$status" -ne 0 ] || [ ! -s "$pdf" ]; then
    echo "[build_pdf] FAILED (exit $status) after ${elapsed}s; the LaTeX log is _build/latex/pgm_wm_book.log" >&2
    exit 1
fi
if [ "$execute" = off ]; then
    result=_build/pgm_wm_book_no_outputs.pdf
    cp "$pdf" "$result"
else
    result=_build/pgm_wm_book.pdf
    cp "$pdf" "$result"
    if [ -d _build/html ]; then
        cp "$pdf" _build/html/pgm_wm_book.pdf   # the introduction's download link
    fi
fi
size=$(du -h "$result" | cut -f1)
echo "[build_pdf] OK in ${elapsed}s (execution: $execute): $result ($size)"

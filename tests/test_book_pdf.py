"""The book builds as one PDF (``bash scripts/build_pdf.sh``) where Debian's TeX is installed.

Runs ``bash scripts/build_pdf.sh --no-execute``: every page of the book, through Jupyter
Book's LaTeX builder and XeLaTeX, without executing the chapters (that is what the full
command adds, at the cost of a second run of every notebook; ``build_book.sh`` already
executes them). Checks that the script succeeds, that the result is a PDF of the whole book
(every chapter's title and the bibliography are in the typeset LaTeX source) and that LaTeX
resolved every cross-reference and had a glyph for every character. Skipped, with the
command that installs TeX, where ``latexmk`` or ``xelatex`` is missing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TEX_MISSING = [tool for tool in ("latexmk", "xelatex") if shutil.which(tool) is None]


@pytest.mark.skipif(bool(TEX_MISSING), reason=(
    f"{' and '.join(TEX_MISSING)} not installed: apt-get install -y --no-install-recommends latexmk "
    "texlive-xetex texlive-latex-extra texlive-fonts-recommended fonts-freefont-otf fonts-dejavu-core"))
def test_the_book_builds_as_one_pdf():
    proc = subprocess.run(["bash", "scripts/build_pdf.sh", "--no-execute"], cwd=ROOT,
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    pdf = ROOT / "_build" / "pgm_wm_book_no_outputs.pdf"
    assert pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 200_000
    tex = (ROOT / "_build" / "latex" / "pgm_wm_book.tex").read_text(encoding="utf-8")
    tex = tex.replace(r"\sphinxhyphen{}", "-")
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        title = "".join(json.loads(nb.read_text(encoding="utf-8"))["cells"][0]["source"]).splitlines()[0]
        assert title.lstrip("# ").strip() in tex, f"{nb.name}: chapter title missing from the PDF"
    assert r"\begin{thebibliography}" in tex or "bibitem" in tex
    log = (ROOT / "_build" / "latex" / "pgm_wm_book.log").read_text(encoding="utf-8", errors="replace")
    # the log of latexmk's last LaTeX run: every reference resolved, every character typeset
    assert "There were undefined references" not in log and "undefined on input line" not in log
    assert "Missing character" not in log, "a character has no glyph in the PDF's fonts"

"""The rendered book fits its column: scripts/check_overflow.py in headless Chromium.

* ``test_checker_detects_overflow``: the checker itself, on two small hand-written pages
  (one with a too-long code line, a too-wide table and a wrapped line; one that fits), so
  a checker that always reports "fine" fails here.
* ``test_built_book_fits``: every page of ``_build/html`` at 1400 px and 390 px meets the
  book's criterion (see ``check_overflow.failures``), and at 390 px no display equation is
  wider than the column (count 0). Skipped when the book has not been
  built (``bash scripts/build_book.sh``) or Chromium is not installed.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "_build" / "html"

spec = importlib.util.spec_from_file_location("check_overflow", ROOT / "scripts" / "check_overflow.py")
check_overflow = importlib.util.module_from_spec(spec)
sys.modules["check_overflow"] = check_overflow
spec.loader.exec_module(check_overflow)

needs_chromium = pytest.mark.skipif(check_overflow.find_chromium() is None,
                                    reason="chromium is not installed (apt-get install chromium)")

PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"><style>
body {{ margin: 0; }} .bd-article {{ width: 400px; padding: 0; }}
pre {{ font-family: monospace; font-size: 14px; padding: 4px; margin: 0; }}
</style></head><body><div class="bd-article">
<div class="cell_input"><div class="highlight"><pre>{code}</pre></div></div>
<div class="cell_output"><pre style="white-space: pre-wrap">{wrapped}</pre></div>
<table><tr>{cells}</tr></table>
</div></body></html>"""


@needs_chromium
def test_checker_detects_overflow(tmp_path):
    wide = tmp_path / "wide"
    narrow = tmp_path / "narrow"
    for folder, n_chars, n_cells, cell in ((wide, 120, 12, "column_{}_with_a_long_name"), (narrow, 20, 2, "c{}")):
        folder.mkdir()
        (folder / "index.html").write_text(PAGE.format(
            code="x = 1\n" + "y" * n_chars + "\nz = 2",
            wrapped="w " * 200,                                  # wraps: never an overflow
            cells="".join(f"<td>{cell.format(i)}</td>" for i in range(n_cells))),
            encoding="utf-8")
    (wide_result,) = check_overflow.run(wide, [800])
    (narrow_result,) = check_overflow.run(narrow, [800])
    assert not wide_result.error and not narrow_result.error
    assert wide_result.code_blocks == 1 and wide_result.code_lines == 1
    assert wide_result.report["code"][0]["kind"] == "input"
    assert wide_result.tables_over == 1 and wide_result.tables_unhinted == 1
    assert narrow_result.code_lines == 0 and narrow_result.tables_over == 0
    assert check_overflow.failures([narrow_result], desktop=800) == []
    assert len(check_overflow.failures([wide_result], desktop=800)) == 2


@needs_chromium
@pytest.mark.skipif(not (BUILD / "index.html").is_file(),
                    reason="the book is not built (bash scripts/build_book.sh)")
def test_built_book_fits():
    results = check_overflow.run(BUILD, [1400, 390])
    assert len({r.page for r in results}) >= 10, "expected every page of the book"
    # Phone width: no display equation wider than the column (the fitting script may shrink
    # an equation; what still does not fit is counted here, scrollable or not).
    phone = [r for r in results if r.width == 390 and not r.error]
    wide_at_phone = {r.page: r.eq_over for r in phone if r.eq_over}
    assert sum(r.eq_over for r in phone) == 0, f"display equations wider than 390 px: {wide_at_phone}"
    problems = check_overflow.failures(results, desktop=1400)
    assert not problems, "\n".join(problems)

"""Checks of the built book (``_build/html``, made by ``bash scripts/build_book.sh``) and of
the sources it is built from.

Over the built pages (skipped when the book has not been built):

* every chapter's numbered headings carry the chapter's number and are unique;
* a chapter's prose names another chapter's section or equation number ("Section 3.2",
  "Eq. (1.2)", "(3.4 ...") only in a link to that chapter or in a sentence that names the
  chapter ("Chapter 3"), so that no number of another chapter is used by accident; and every
  referenced section or equation number exists in the chapter it belongs to;
* no stderr output of a chapter (where Python prints warnings) contains a ``Warning``;
* every figure is stored at twice the pixel size it is displayed at;
* the API reference has one page per public ``pgm_wm`` module, each linked from its index;
* the bibliography page has exactly one entry per BibTeX key.

Over the sources (always): every BibTeX key in ``book/references.bib`` is cited somewhere
(``{cite}`` roles in ``book/*.md``, citation links in the chapters) and every cited key exists.
"""

from __future__ import annotations

import json
import os
import re
import struct
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BUILD = Path(os.environ.get("PGM_WM_BUILD_DIR", ROOT / "_build" / "html"))   # another build to check
CHAPTERS = sorted((BUILD / "notebooks").glob("[0-9][0-9]_*.html"))

built = pytest.mark.skipif(not (BUILD / "index.html").is_file(),
                           reason="the book is not built (bash scripts/build_book.sh)")


def chapter_number(path: Path) -> int:
    return int(path.name[:2])


def soup(path: Path):
    from bs4 import BeautifulSoup

    return BeautifulSoup(path.read_text(encoding="utf-8"), "html.parser")


def article(page):
    return page.select_one("article.bd-article") or page.select_one("main") or page


def headings(page) -> list[str]:
    """The text of every heading of a page's article (h1-h4), without the "#" permalink."""
    out = []
    for h in article(page).find_all(["h1", "h2", "h3", "h4"]):
        for a in h.select("a.headerlink"):
            a.decompose()
        out.append(" ".join(h.get_text(" ").split()))
    return out


NUMBERED = re.compile(r"^(\d+)\.(\d+)(?:\.(\d+))?\s")


def section_numbers(page) -> list[str]:
    """The numbers of a page's numbered headings ("6.3.1 Fast predict ..." -> "6.3.1")."""
    return [m.group(0).strip() for h in headings(page) if (m := NUMBERED.match(h + " "))]


def equation_numbers(page) -> set[str]:
    """The numbers of a page's labelled display equations ("1.2", ...)."""
    found = (re.match(r"\((\d+\.\d+)\)", e.get_text().strip()) for e in article(page).select("span.eqno"))
    return {m.group(1) for m in found if m}


# ----------------------------------------------------------------------------- numbering
@built
def test_there_are_seven_chapters():
    assert [chapter_number(p) for p in CHAPTERS] == [1, 2, 3, 4, 5, 6, 7]


@built
@pytest.mark.parametrize("path", CHAPTERS, ids=lambda p: p.stem)
def test_section_numbers_are_the_chapters_own_and_unique(path):
    page = soup(path)
    numbers = section_numbers(page)
    n = chapter_number(path)
    assert headings(page)[0].startswith(f"{n}. "), headings(page)[0]
    assert numbers, "no numbered section"
    assert all(num.split(".")[0] == str(n) for num in numbers), numbers
    duplicates = sorted({num for num in numbers if numbers.count(num) > 1})
    assert not duplicates, f"section numbers used twice: {duplicates}"


REFERENCE = re.compile(
    r"(?P<kind>Sections?|§|Eqs?\.)\s*\(?(?P<ch>\d+)\.(?P<sec>\d+(?:\.\d+)?)\)?"   # Section 3.2, Eq. (1.2)
    r"|(?<![\w.])\((?P<bch>\d)\.(?P<bsec>\d+)(?=\)|,|\s+and\b)")                    # a bare "(3.4 and ..."


def prose_blocks(page):
    """Paragraphs, list items and table cells of a chapter's text (no code, no math)."""
    art = article(page)
    for junk in art.select("div.cell_input, pre, div.math, span.math, script, style, mjx-container"):
        junk.decompose()
    return art.find_all(["p", "li", "td", "th", "dd", "dt"])


def sentence_around(text: str, start: int, end: int) -> str:
    left = max(text.rfind(". ", 0, start), 0)
    right = text.find(". ", end)
    return text[left:right if right >= 0 else len(text)]


def cross_chapter_problems(path: Path, chapter_pages: dict[int, object]) -> list[str]:
    n = chapter_number(path)
    sections = {k: set(section_numbers(p)) for k, p in chapter_pages.items()}
    equations = {k: equation_numbers(p) for k, p in chapter_pages.items()}
    problems = []
    for block in prose_blocks(soup(path)):
        if block.find(["p", "li", "td"]):       # only the innermost blocks, each once
            continue
        text = " ".join(block.get_text(" ").split())
        links = [(" ".join(a.get_text(" ").split()), a.get("href", "")) for a in block.find_all("a")]
        for m in REFERENCE.finditer(text):
            ch = int(m.group("ch") or m.group("bch"))
            sec = m.group("sec") or m.group("bsec")
            kind = m.group("kind") or "("
            ref = f"{ch}.{sec}"
            if ch not in chapter_pages:
                continue
            if kind.startswith("Eq") and ref not in equations[ch]:
                problems.append(f"{path.stem}: 'Eq. ({ref})' is not an equation of chapter {ch}")
            if kind.startswith("Sec") or kind == "§":
                if not any(s == ref or s.startswith(ref + ".") for s in sections[ch]):
                    problems.append(f"{path.stem}: 'Section {ref}' does not exist in chapter {ch}")
            if ch == n:
                continue
            target = f"{ch:02d}_"
            linked = any(ref in t and target in href for t, href in links)
            # a bare "(3.4" must be a link; "Section 3.2" or "Eq. (3.3)" may name the chapter instead
            named = kind != "(" and re.search(rf"\bChapter {ch}\b|\bChapters? [\d, and]*\b{ch}\b",
                                              sentence_around(text, m.start(), m.end()))
            if not (linked or named):
                problems.append(f"{path.stem}: {m.group(0)!r} refers to chapter {ch} without naming it: "
                                f"...{sentence_around(text, m.start(), m.end())[-160:].strip()}")
    return problems


@built
@pytest.mark.parametrize("path", CHAPTERS, ids=lambda p: p.stem)
def test_references_to_other_chapters_say_which_chapter(path):
    pages = {chapter_number(p): soup(p) for p in CHAPTERS}
    problems = cross_chapter_problems(path, pages)
    assert not problems, "\n".join(problems)


def test_cross_chapter_check_catches_a_stray_number(tmp_path):
    """The check itself, on two hand-written chapter pages: in chapter 6, "Section 3.2 of
    Chapter 3" and a linked "Eq. (3.3)" are fine; a bare "(3.4 and Chapter 3's)" or "(3.4)"
    (meant: 6.3.4) and "Section 3.2" alone are not, and a section that does not exist is
    reported."""
    def page(title, body):
        return (f"<html><body><article class='bd-article'><h1>{title}</h1>{body}</article></body></html>")

    (tmp_path / "03_rkn.html").write_text(page("3. RKN", "<h2>3.2 The update</h2><h2>3.4 Precision</h2>"
                                                         "<div class='math'><span class='eqno'>(3.3)</span></div>"))
    six = tmp_path / "06_mts3.html"
    six.write_text(page("6. MTS3", "<h2>6.3 Deriving</h2><h3>6.3.4 Task update</h3>"
                                   "<p>the updates (3.4 and Chapter 3's) are exact.</p>"
                                   "<p>the updates (3.4) and the aggregation are exact too.</p>"
                                   "<p>summarizes the window's actions (Section 3.2).</p>"
                                   "<p>as in <a href='03_rkn.html#equation-x'>Eq. (3.3)</a>.</p>"
                                   "<p>see Section 6.3.7.</p>"
                                   "<p>as in Section 3.2 of Chapter 3.</p>"))
    pages = {3: soup(tmp_path / "03_rkn.html"), 6: soup(six)}
    problems = cross_chapter_problems(six, pages)
    assert len(problems) == 4, problems
    assert sum("without naming it" in p for p in problems) == 3
    assert any("'Section 6.3.7' does not exist" in p for p in problems)


# ----------------------------------------------------------------------------- leaks
@built
@pytest.mark.parametrize("path", CHAPTERS, ids=lambda p: p.stem)
def test_no_warning_reaches_a_page(path):
    page = soup(path)
    stderr = [" ".join(o.get_text(" ").split())[:300] for o in article(page).select(".output.stderr, .stderr")]
    warned = [s for s in stderr if "Warning" in s or "Traceback" in s]
    assert not warned, f"warnings printed into the page: {warned}"


@built
@pytest.mark.parametrize("path", CHAPTERS, ids=lambda p: p.stem)
def test_no_raw_docstring_in_printed_source(path):
    """Package source shown in a chapter comes without its reST docstrings."""
    text = article(soup(path)).get_text()
    assert ":math:`" not in text and "Args:\n" not in text


# ----------------------------------------------------------------------------- figures
def png_size(path: Path) -> tuple[int, int]:
    with path.open("rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n", path
    return struct.unpack(">II", head[16:24])


@built
@pytest.mark.parametrize("path", CHAPTERS, ids=lambda p: p.stem)
def test_figures_are_stored_at_twice_their_display_size(path):
    page = soup(path)
    images = [img for img in article(page).select(".cell_output img") if img["src"].endswith(".png")]
    assert images, "no figure"
    for img in images:
        width, height = png_size((path.parent / img["src"]).resolve())
        m = re.search(r"width:\s*([\d.]+)px", img.get("style", "")) or re.match(r"([\d.]+)(px)?$", img.get("width", ""))
        assert m, f"{img['src']}: no display width (not a retina figure)"
        shown = float(m.group(1))
        assert abs(width - 2 * shown) <= 2, f"{img['src']}: {width} px stored for {shown} px shown"


# ----------------------------------------------------------------------------- API reference
@built
def test_api_reference_has_one_page_per_module():
    sys.path.insert(0, str(ROOT / "book" / "_ext"))
    from pgm_api import public_modules

    modules = public_modules()
    pages = {p.stem for p in (BUILD / "book" / "api").glob("pgm_wm*.html")}
    assert pages == set(modules)
    index = (BUILD / "book" / "api.html").read_text(encoding="utf-8")
    for name in modules:
        assert f'href="api/{name}.html' in index, f"{name} is not linked from the index page"
    # the index is short: it lists modules, the signatures live on the module pages
    assert index.count('class="sig sig-object') == 0
    kalman = (BUILD / "book" / "api" / "pgm_wm.kalman.html").read_text(encoding="utf-8")
    assert 'id="pgm_wm.kalman.kalman_filter"' in kalman


# ----------------------------------------------------------------------------- bibliography
def bib_keys() -> set[str]:
    text = (ROOT / "book" / "references.bib").read_text(encoding="utf-8")
    return set(re.findall(r"^@\w+\{([^,\s]+),", text, re.M))


def cited_keys() -> set[str]:
    keys = set()
    for md in (ROOT / "book").glob("*.md"):
        for group in re.findall(r"\{cite(?::[a-z]+)?\}`([^`]+)`", md.read_text(encoding="utf-8")):
            keys.update(k.strip() for k in group.split(","))
    for nb in (ROOT / "notebooks").glob("*.ipynb"):
        cells = json.loads(nb.read_text(encoding="utf-8"))["cells"]
        text = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")
        keys.update(re.findall(r"\]\(\.\./book/references\.md#([\w-]+)\)", text))
        assert not re.search(r"\{cite(?::[a-z]+)?\}`", text), (
            f"{nb.name}: a {{cite}} role shows as a raw key in JupyterLab; write "
            "[Label](../book/references.md#key) (book/_ext/readable_refs.py)")
    return keys


def test_bibliography_is_complete_and_minimal():
    listed, cited = bib_keys(), cited_keys()
    assert cited - listed == set(), f"cited but not in references.bib: {sorted(cited - listed)}"
    assert listed - cited == set(), f"in references.bib but cited nowhere: {sorted(listed - cited)}"


@built
def test_bibliography_page_lists_every_entry_once():
    page = (BUILD / "book" / "references.html").read_text(encoding="utf-8")
    ids = re.findall(r'id="bib-([\w-]+)"', page)
    assert sorted(ids) == sorted(bib_keys())


# ----------------------------------------------------------------------------- datasets named in the READMEs
def notebook_text(number: int) -> str:
    (path,) = (ROOT / "notebooks").glob(f"{number:02d}_*.ipynb")
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    return "\n".join("".join(c["source"]) for c in cells)


def readme_chapter_datasets() -> dict[int, set[str]]:
    """Chapter number -> the dataset names in the Data column of README.md's chapter table."""
    rows = {}
    for line in (ROOT / "README.md").read_text(encoding="utf-8").splitlines():
        m = re.match(r"\|\s*(\d)\. [^|]+\|[^|]+\|[^|]+\|([^|]+)\|\s*$", line)
        if m:
            rows[int(m.group(1))] = set(re.findall(r"`(\w+)`", m.group(2)))
    return rows


def test_readme_names_the_datasets_each_chapter_loads():
    from pgm_wm.datasets import DATASET_NAMES as DATASETS

    rows = readme_chapter_datasets()
    assert sorted(rows) == [1, 2, 3, 4, 5, 6, 7]
    for n, names in rows.items():
        text = notebook_text(n)
        loaded = set(re.findall(r'load\("(\w+)"', text))
        assert names <= set(DATASETS), f"chapter {n}: unknown dataset in README: {names - set(DATASETS)}"
        assert loaded <= names, f"chapter {n} loads {sorted(loaded - names)}, README does not say so"
        for name in names:
            assert f'"{name}"' in text or f"`{name}`" in text, f"README: chapter {n} does not use {name}"


def test_data_readme_says_which_chapter_uses_each_file():
    from pgm_wm.datasets import DATASET_NAMES as DATASETS

    rows = readme_chapter_datasets()
    used = {name: {n for n, names in rows.items() if name in names} for name in DATASETS}
    table = (ROOT / "data" / "README.md").read_text(encoding="utf-8")
    for name in DATASETS:
        m = re.search(rf"^\| `{name}`(?: \(real\))? \| ([^|]+) \|", table, re.M)
        assert m, f"data/README.md has no row for {name}"
        stated = {int(c) for c in re.findall(r"^\s*(\d)(?:,\s*(\d))?", m.group(1))[0] if c} \
            if re.match(r"\s*\d", m.group(1)) else set()
        assert stated == used[name], f"{name}: data/README.md says chapters {stated}, README.md {used[name]}"


@pytest.mark.parametrize("number", [1, 2, 3, 4, 5, 6, 7])
def test_chapter_ends_with_key_takeaways_before_the_exercises(number):
    """One "Key takeaways" box on the method, optionally followed by one "Key takeaways on the
    results" box (the chapters with a study), and nothing else between them and the exercises."""
    (path,) = (ROOT / "notebooks").glob(f"{number:02d}_*.ipynb")
    cells = [("".join(c["source"]), c["cell_type"]) for c in json.loads(path.read_text(encoding="utf-8"))["cells"]]
    boxes = [i for i, (s, t) in enumerate(cells) if t == "markdown" and s.startswith(":::{admonition} Key takeaways")]
    results = [i for i in boxes if cells[i][0].startswith(":::{admonition} Key takeaways on the results")]
    box = [i for i in boxes if i not in results]
    exercises = [i for i, (s, t) in enumerate(cells) if t == "markdown" and s.lstrip().startswith("## Exercises")]
    assert len(box) == 1 and len(results) <= 1 and len(exercises) == 1
    assert box[0] < exercises[0] and all(box[0] < i < exercises[0] for i in results)
    between = [s for s, t in cells[box[0] + 1:exercises[0]]]
    assert all(s.startswith("<!--") or s.startswith(":::") for s in between), "only takeaways before the exercises"
    for i in box + results:
        bullets = re.findall(r"^- \*\*", cells[i][0], re.M)
        assert 3 <= len(bullets) <= 7, f"{len(bullets)} takeaways"

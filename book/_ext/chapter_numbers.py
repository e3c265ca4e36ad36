"""Chapter-numbered equations: "(6.2)" instead of "(2)".

Sphinx numbers labelled display equations per page, (1), (2), ... (``math_numfig:
false``), so a reference from chapter 6 to an equation of chapter 1 reads "(2)", which the
reader cannot tell apart from chapter 6's own Eq. (2). With ``math_numfig: true`` Sphinx
would need a numbered toctree, whose automatic section numbers would clash with the
chapter numbers written in the notebooks' headings.

This extension prefixes every labelled equation number of a chapter page with the
chapter's number, read from the page name (``notebooks/06_mts3`` -> chapter 6), both in
the equation's own number and in every ``{eq}`` reference to it (the math domain resolves
references from the numbers stored here, so a reference from another chapter shows the
target's chapter too). Pages that are not chapters keep their per-page numbers.
"""

from __future__ import annotations

import re
from typing import Any

from docutils import nodes
from sphinx.application import Sphinx

CHAPTER_PAGE = re.compile(r"(?:^|/)(\d{1,2})_[^/]*$")


def chapter_of(docname: str) -> int | None:
    """Chapter number of a page name such as ``notebooks/06_mts3`` (None if not a chapter)."""
    match = CHAPTER_PAGE.search(docname)
    return int(match.group(1)) if match else None


def _number_equations(app: Sphinx, doctree: nodes.document) -> None:
    docname = app.env.docname
    chapter = chapter_of(docname)
    if chapter is None:
        return
    domain = app.env.get_domain("math")
    equations = domain.data.setdefault("objects", {})
    for node in doctree.findall(nodes.math_block):
        label, number = node.get("label"), node.get("number")
        if not label or number is None or str(number).startswith(f"{chapter}."):
            continue
        node["number"] = f"{chapter}.{number}"
        if label in equations and equations[label][0] == docname:
            equations[label] = (docname, node["number"])


def setup(app: Sphinx) -> dict[str, Any]:
    app.connect("doctree-read", _number_equations)
    return {"version": "1.0", "parallel_read_safe": False, "parallel_write_safe": True,
            "env_version": 1}

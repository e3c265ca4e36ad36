"""Small fixes for the PDF build (Jupyter Book's LaTeX builder, ``bash scripts/build_pdf.sh``).

MathJax accepts a few TeX spellings that LaTeX rejects; the book's pages and the package's
docstrings are written for MathJax, so for LaTeX output the math is normalised here instead
of in the sources:

* a command used as a bare sub- or superscript, ``\\omega_\\max``, ``x^\\top`` or
  ``n_\\text{heads}``, gets braces, ``\\omega_{\\max}``, ``n_{\\text{heads}}`` (LaTeX stops
  with "Missing { inserted" on ``_\\max``);
* a display formula with alignment marks ``&`` that is not already an environment is wrapped in
  ``aligned``: Sphinx puts every display formula into ``split``, which allows one ``&`` per row,
  and the docstrings' ``.. math::`` blocks align two equations per row.

Only the LaTeX builder is touched; the HTML pages keep their math as written.
"""

from __future__ import annotations

import re
from typing import Any

from docutils import nodes
from sphinx.application import Sphinx

BARE_SCRIPT_COMMAND = re.compile(r"([_^])\s*(\\[A-Za-z]+(?:\{[^{}]*\})*)")   # with its {arguments}


def latex_math(tex: str) -> str:
    """The TeX of one formula with every bare ``_\\cmd`` / ``^\\cmd`` braced."""
    return BARE_SCRIPT_COMMAND.sub(r"\1{\2}", tex)


def latex_display(tex: str) -> str:
    """A display formula that LaTeX's ``split`` accepts (see the module docstring)."""
    tex = latex_math(tex)
    body = tex.strip()
    if "&" in body and not body.startswith("\\begin"):
        return "\\begin{aligned}" + body + "\\end{aligned}"
    return tex


def _fix_math(app: Sphinx, doctree: nodes.document, docname: str) -> None:
    if app.builder.format != "latex":
        return
    for node in list(doctree.findall(lambda n: isinstance(n, (nodes.math, nodes.math_block)))):
        text = node.astext()
        fixed = latex_display(text) if isinstance(node, nodes.math_block) else latex_math(text)
        if fixed != text:
            node.children = [nodes.Text(fixed)]
            if "latex" in node.attributes and isinstance(node["latex"], str):
                node["latex"] = fixed


def setup(app: Sphinx) -> dict[str, Any]:
    app.connect("doctree-resolved", _fix_math)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}

"""References between notebooks that read the same in JupyterLab and in the built book.

JupyterLab renders each notebook on its own: a ``{cite}`` role shows its BibTeX key and an
``{eq}`` or ``{ref}`` role pointing into *another* notebook shows its label ("ⓘ
gauss-marginal"), because neither the bibliography nor the other chapter is known there.
So the chapters write these references as ordinary Markdown links whose text is what a
reader should see, and whose target names the thing referred to:

* a citation: ``[Shaj et al. 2022](../book/references.md#shaj2022hiprssm)``, the link text
  being the entry's label on the references page (``bibstyle_authoryear``);
* an equation of another chapter: ``[Eq. (1.2)](01_kalman_filter.ipynb#gauss-marginal)``;
* a labelled section of another chapter: ``[Section 3.6](03_rkn.ipynb#rkn-objective)``.

In JupyterLab these are plain links with readable text. In the book this post-transform
(which runs just before MyST's own link resolver) turns each into a link to the exact
target: the bibliography entry (whose anchor is ``bib-<key>``, ``bibtex_cite_id`` in
_config.yml), the numbered equation, or the labelled section. It also checks what the text
says, and a mismatch is a build warning (an error with ``-W``): an unknown BibTeX key, a link
text that is not the entry's label, an unknown equation label, or an equation link whose text
does not contain the equation's number in the book, e.g. "(1.2)". So a typed number cannot go
stale. References within one notebook keep using ``{eq}``, which JupyterLab numbers itself.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.nodes import make_id
from sphinx import addnodes
from sphinx.application import Sphinx
from sphinx.transforms.post_transforms import SphinxPostTransform
from sphinx.util import logging
from sphinx.util.nodes import make_refnode

LOGGER = logging.getLogger(__name__)
LATEX_SPECIAL = {"&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{", "}": r"\}",
                 "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "\\": r"\textbackslash{}"}
REFERENCES_DOC = "book/references"


def bib_labels(app: Sphinx) -> dict[str, str]:
    """BibTeX key -> the label the references page shows for it ("Kalman 1960")."""
    cached = getattr(app, "_pgm_bib_labels", None)
    if cached is not None:
        return cached
    from pybtex.database import parse_file

    from bibstyle_authoryear import AuthorYearLabelStyle

    labels: dict[str, str] = {}
    for bibfile in app.config.bibtex_bibfiles:
        data = parse_file(str(Path(app.srcdir) / bibfile))
        for key, entry in data.entries.items():
            labels[key] = AuthorYearLabelStyle._label(entry)
    app._pgm_bib_labels = labels
    return labels


class ReadableReferences(SphinxPostTransform):
    """Resolve (and check) the readable cross-notebook links described in the module docstring."""

    default_priority = 8   # before MyST's resolver (9), which would report them as unknown ids

    def run(self, **kwargs: Any) -> None:
        for node in list(self.document.findall(addnodes.pending_xref)):
            if node.get("reftype") != "myst" or node.get("refdomain") != "doc":
                continue
            target_doc, target_id = node.get("reftarget"), node.get("reftargetid")
            if not target_id:
                continue
            text = node.astext().strip()
            if target_doc == REFERENCES_DOC:
                self._citation(node, target_id, text)
                continue
            equations = self.env.get_domain("math").data.get("objects", {})
            if target_id in equations:
                self._equation(node, target_doc, target_id, text, equations[target_id])
                continue
            labels = self.env.get_domain("std").labels
            if target_id in labels and labels[target_id][0] == target_doc:
                docname, label_id, _ = labels[target_id]
                self._replace(node, docname, label_id)

    def _replace(self, node: addnodes.pending_xref, docname: str, anchor: str) -> None:
        content = nodes.inline("", "", *[c.deepcopy() for c in node[0].children],
                               classes=["std", "std-ref"])
        node.replace_self(make_refnode(self.app.builder, self.env.docname, docname, anchor, content))

    def _replace_latex(self, node: addnodes.pending_xref, command: str) -> None:
        """LaTeX output: a hyperlink to a target the LaTeX writer names its own way (the
        bibliography's ``cite.<doc>:<id>`` anchors, the equations' ``equation:<doc>:<label>``)."""
        text = "".join(LATEX_SPECIAL.get(ch, ch) for ch in node.astext())
        node.replace_self(nodes.raw("", command.replace("@TEXT@", text), format="latex"))

    def _citation(self, node: addnodes.pending_xref, key: str, text: str) -> None:
        labels = bib_labels(self.app)
        if key not in labels:
            LOGGER.warning(f"citation link to an unknown BibTeX key {key!r}", location=node,
                           type="pgm_refs")
            return
        if text != labels[key]:
            LOGGER.warning(f"citation link text {text!r} should be the entry's label {labels[key]!r}",
                           location=node, type="pgm_refs")
        anchor = make_id(f"bib-{key}")
        if self.app.builder.format == "latex":
            self._replace_latex(node, r"\hyperlink{cite.%s:%s}{@TEXT@}" % (REFERENCES_DOC, anchor))
        else:
            self._replace(node, REFERENCES_DOC, anchor)

    def _equation(self, node: addnodes.pending_xref, target_doc: str, label: str, text: str,
                  found: tuple[str, Any]) -> None:
        docname, number = found
        if docname != target_doc:
            LOGGER.warning(f"equation {label!r} is defined in {docname!r}, the link points to {target_doc!r}",
                           location=node, type="pgm_refs")
        if f"({number})" not in text:
            LOGGER.warning(f"link to equation {label!r} says {text!r}, but that equation is ({number})",
                           location=node, type="pgm_refs")
        if self.app.builder.format == "latex":
            self._replace_latex(node, r"\hyperref[\detokenize{equation:%s:%s}]{@TEXT@}" % (docname, label))
        else:
            self._replace(node, docname, make_id(f"equation-{label}"))


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_post_transform(ReadableReferences)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}

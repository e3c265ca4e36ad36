"""The ``pgm-wm-api`` directive: an API reference for every public module of ``pgm_wm``.

The module list is not typed into the page: the directive walks the installed package
(``pkgutil.walk_packages``) when the book is built, so a new module appears in the
reference as soon as it exists. Private modules (a name starting with ``_``) and
``__main__`` are skipped. For each module it emits a section with an ``automodule``
(autodoc, members defined in that module only, so re-exports are documented once, where
they are defined) after an ``autosummary`` table of all modules. ``sphinx.ext.viewcode``
adds the "[source]" links. Everything is read from the local checkout; nothing is fetched.
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles


def public_modules(package: str = "pgm_wm") -> list[str]:
    """Dotted names of the package and all its public submodules, in sorted order."""
    pkg = importlib.import_module(package)
    names = [package]
    for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}."):
        parts = info.name.split(".")
        if any(p.startswith("_") for p in parts[1:]):
            continue
        names.append(info.name)
    return sorted(names)


class PgmWmApi(SphinxDirective):
    has_content = False
    optional_arguments = 1

    def run(self) -> list[nodes.Node]:
        package = self.arguments[0] if self.arguments else "pgm_wm"
        modules = public_modules(package)
        lines = [".. autosummary::", ""]
        lines += [f"   {name}" for name in modules]
        lines.append("")
        for name in modules:
            lines += [name, "-" * len(name), "",
                      f".. automodule:: {name}",
                      "   :members:",
                      "   :show-inheritance:",
                      "   :ignore-module-all:",
                      "   :member-order: bysource",
                      ""]
        container = nodes.section()
        container.document = self.state.document
        nested_parse_with_titles(self.state, StringList(lines, source="pgm-wm-api"), container)
        for name in modules:
            self.env.note_dependency(importlib.import_module(name).__file__)
        return container.children


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive("pgm-wm-api", PgmWmApi)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}

"""The API reference: one page per public module of ``pgm_wm`` and a short index page.

The module list is not typed anywhere: when the build starts (``config-inited``) this
extension walks the installed package (``pkgutil.walk_packages``) and writes one page per
public module, ``book/api/<module>.rst`` (an ``automodule`` of that module: members defined
in it only, so re-exports are documented once, where they are defined). Pages of modules that
no longer exist are deleted, and a page is only rewritten when its text changes. The folder is
generated (git-ignored); ``_toc.yml`` lists it with a glob under the index page
``book/api.rst``. Private modules (a name starting with ``_``) and ``__main__`` are skipped.

The index page uses the ``pgm-wm-api`` directive: a table of all modules with the first line
of each module's docstring, linked to its page. ``sphinx.ext.viewcode`` adds the "[source]"
links. Everything is read from the local checkout; nothing is fetched.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.config import Config
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

API_DIR = "book/api"


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


def module_page(name: str) -> str:
    """The reST source of one module's page."""
    return "\n".join([name, "=" * len(name), "",
                      f".. automodule:: {name}",
                      "   :members:",
                      "   :show-inheritance:",
                      "   :ignore-module-all:",
                      "   :member-order: bysource",
                      ""])


def write_module_pages(srcdir: Path, package: str = "pgm_wm") -> list[Path]:
    """Create or update ``book/api/<module>.rst`` for every public module; remove stale ones."""
    folder = Path(srcdir) / API_DIR
    folder.mkdir(parents=True, exist_ok=True)
    pages = []
    for name in public_modules(package):
        page = folder / f"{name}.rst"
        text = module_page(name)
        if not page.is_file() or page.read_text(encoding="utf-8") != text:
            page.write_text(text, encoding="utf-8")
        pages.append(page)
    for old in folder.glob("*.rst"):
        if old not in pages:
            old.unlink()
    return pages


def _on_config_inited(app: Sphinx, config: Config) -> None:
    write_module_pages(Path(app.srcdir))


class PgmWmApi(SphinxDirective):
    """A table of every public module (first docstring line) with links to the module pages."""

    has_content = False
    optional_arguments = 1

    def run(self) -> list[nodes.Node]:
        package = self.arguments[0] if self.arguments else "pgm_wm"
        modules = public_modules(package)
        lines = [".. autosummary::", ""] + [f"   {name}" for name in modules] + [""]
        container = nodes.section()
        container.document = self.state.document
        nested_parse_with_titles(self.state, StringList(lines, source="pgm-wm-api"), container)
        for name in modules:
            self.env.note_dependency(importlib.import_module(name).__file__)
        return container.children


def setup(app: Sphinx) -> dict[str, Any]:
    app.connect("config-inited", _on_config_inited)
    app.add_directive("pgm-wm-api", PgmWmApi)
    return {"version": "1.1", "parallel_read_safe": True, "parallel_write_safe": True}

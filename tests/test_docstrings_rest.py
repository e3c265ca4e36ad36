"""Every docstring the API reference renders is valid reStructuredText.

The book's build (``bash scripts/build_book.sh``, the README's first command) turns Sphinx
warnings into errors, and a broken docstring once broke it while every test passed (a
definition list with a multi-line inline literal). The test command does not build the book,
so this test parses each docstring that the API pages document (the modules listed by
``public_modules`` of ``book/_ext/pgm_api.py``, the function the build uses to write
``book/api/*.rst``; a clean clone has no generated pages) the way autodoc does: the
napoleon (Google-style) conversion first, then docutils, with Sphinx's cross-reference roles
(``:class:``, ``:meth:`` ...) stood in for by a role that renders literal text. Any docutils
warning or error fails the test with the object's name and the message.
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
from pathlib import Path

import docutils.core
import docutils.nodes
import docutils.utils
import pytest
from docutils.parsers.rst import Directive, directives, roles
from sphinx.ext.napoleon import Config
from sphinx.ext.napoleon.docstring import GoogleDocstring

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "book" / "_ext"))
from pgm_api import public_modules  # noqa: E402  (the build's own module list)

MODULES = public_modules()
SPHINX_ROLES = ("class", "meth", "func", "mod", "attr", "data", "obj", "exc", "ref", "doc", "eq", "cite",
                "cite:p", "cite:t", "term", "numref", "py:class", "py:func", "py:meth", "envvar", "file")


def _literal_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    return [docutils.nodes.literal(rawtext, text)], []


for _role in SPHINX_ROLES:
    roles.register_local_role(_role, _literal_role)


class _SphinxObjectDirective(Directive):
    """Stands in for Sphinx's object directives that napoleon emits (``.. attribute::`` for an
    ``Attributes:`` section): its body is parsed as ordinary reST."""

    required_arguments, optional_arguments, final_argument_whitespace = 0, 1, True
    option_spec = {"type": directives.unchanged, "noindex": directives.flag, "value": directives.unchanged}
    has_content = True

    def run(self):
        node = docutils.nodes.container()
        self.state.nested_parse(self.content, self.content_offset, node)
        return [node]


for _directive in ("attribute", "method", "function", "seealso", "versionadded", "versionchanged"):
    directives.register_directive(_directive, _SphinxObjectDirective)


def documented_objects(modname: str):
    """``(qualified name, docstring)`` for the module and every public member autodoc shows:
    functions and classes defined in the module, and the public methods and properties of
    those classes."""
    module = importlib.import_module(modname)
    yield modname, inspect.getdoc(module)
    for name, obj in vars(module).items():
        if name.startswith("_") or getattr(obj, "__module__", None) != modname:
            continue
        if not (inspect.isfunction(obj) or inspect.isclass(obj)):
            continue
        yield f"{modname}.{name}", inspect.getdoc(obj)
        if inspect.isclass(obj):
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                target = member.__func__ if isinstance(member, (classmethod, staticmethod)) else member
                if inspect.isfunction(target) or isinstance(target, property):
                    yield f"{modname}.{name}.{attr}", inspect.getdoc(target)


def rest_problems(docstring: str) -> list[str]:
    """docutils messages of level warning or worse for one docstring after napoleon."""
    text = str(GoogleDocstring(docstring, Config(napoleon_google_docstring=True, napoleon_numpy_docstring=False,
                                                 napoleon_custom_sections=[("Fields", "params_style")])))
    settings = {"report_level": docutils.utils.Reporter.WARNING_LEVEL, "halt_level": 5, "warning_stream": False,
                "file_insertion_enabled": False, "raw_enabled": False}
    tree = docutils.core.publish_doctree(text, settings_overrides=settings)
    return [re.sub(r"\s+", " ", msg.astext())[:200] for msg in tree.findall(docutils.nodes.system_message)
            if msg["level"] >= docutils.utils.Reporter.WARNING_LEVEL]


def test_the_checker_catches_what_broke_the_build():
    """The kind of docstring that broke the build (a definition-list entry whose inline literal
    spans two lines, as ``FitHistory`` had before 29bcac2) and an unclosed literal are
    reported; a clean docstring with Sphinx roles, math and an ``Args:`` section is not."""
    broken = ('''What fit recorded.

Per validation:
    valid_loss: the validation loss.
    curve: one dict per validation: ``{"step", "epoch",
        "valid"}``; ``cpu_s`` is CPU seconds.
''')
    assert any("Inline literal start-string without end-string" in m for m in rest_problems(broken))
    assert rest_problems("Start ``unclosed literal here.") != []
    assert rest_problems("Uses :class:`pgm_wm.acrkn.AcRKN` and :math:`x^2`, Eq. (1.2).\n\n.. math::\n\n"
                         "    y = x^2\n\nArgs:\n    x: the input, shape ``(B, T)``.\n") == []


def test_the_module_list_is_not_empty():
    """The parametrized test below must have modules to check (it once found none in a clean
    clone, where ``book/api/`` is not generated, and was skipped without failing)."""
    assert len(MODULES) > 20 and "pgm_wm.kalman" in MODULES and "pgm_wm.mts3" in MODULES, MODULES


@pytest.mark.parametrize("modname", MODULES)
def test_docstrings_are_valid_rest(modname):
    found = {name: rest_problems(doc) for name, doc in documented_objects(modname) if doc}
    bad = {name: msgs for name, msgs in found.items() if msgs}
    assert not bad, "\n".join(f"{name}: {msgs}" for name, msgs in bad.items())

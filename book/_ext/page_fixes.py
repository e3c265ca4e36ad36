"""Two small fixes to what every page loads and what the status page shows.

1. No unused thebe scripts.

Jupyter Book 1 always loads the ``sphinx_thebe`` extension, which adds an inline script
(``const THEBE_JS_URL = ...``) and ``sphinx-thebe.js`` to every page even though this book
has no live-code buttons (``launch_buttons.thebe: false``). The inline script can end up
on a page twice, and the browser then reports "Identifier 'THEBE_JS_URL' has already been
declared". Nothing in the book uses thebe, so this extension removes sphinx-thebe's
``env-before-read-docs`` handler that adds the two scripts (its directives stay
registered, so a page that used ``thebe-button`` would still build).

2. A status column readable without an emoji font. myst-nb's ``{nb-exec-table}`` marks a
page that executed without error with the emoji "✅" (and a failed one with "❌"), which
shows as an empty box where no emoji font is installed. The column here reads "ok" or
"failed" instead.
"""

from __future__ import annotations

from typing import Any

from sphinx.application import Sphinx


def _drop_thebe_scripts(app: Sphinx, config: Any) -> None:
    if getattr(config, "thebe_config", {}).get("always_load"):
        return  # someone switched thebe on: leave it alone
    listeners = app.events.listeners.get("env-before-read-docs", [])
    for listener in list(listeners):
        handler = listener.handler
        if getattr(handler, "__module__", "") == "sphinx_thebe" and \
                handler.__name__ == "init_thebe_core":
            app.disconnect(listener.id)


def _plain_status_column() -> None:
    from myst_nb.ext import execution_tables

    execution_tables._key2transform["succeeded"] = lambda ok: "ok" if ok is True else "failed"


def setup(app: Sphinx) -> dict[str, Any]:
    app.connect("config-inited", _drop_thebe_scripts, priority=900)
    _plain_status_column()
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}

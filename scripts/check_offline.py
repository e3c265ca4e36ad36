#!/usr/bin/env python
"""Fail if the built book would load anything from the network when a page is opened.

Scans every ``.html`` file under the build folder (default ``_build/html``) for resources
that a browser fetches automatically (``<script src>``, ``<link href>`` for stylesheets,
fonts, icons and preloads, ``<img>``/``<iframe>``/``<source>``/``<video>``/``<audio>``
``src``) and every ``.css`` file for ``url(...)`` and ``@import``, and reports any that
point at ``http://``, ``https://`` or protocol-relative ``//`` URLs. Plain hyperlinks
(``<a href>``) are fine: they are only followed when the reader clicks them.

Usage: ``python scripts/check_offline.py [BUILD_DIR]``; exit status 1 if anything remote
is found.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path

REMOTE = re.compile(r"^\s*(https?:)?//", re.IGNORECASE)
CSS_URL = re.compile(r"""url\(\s*['"]?([^'")]+)""", re.IGNORECASE)
CSS_IMPORT = re.compile(r"""@import\s+(?:url\()?\s*['"]?([^'");\s]+)""", re.IGNORECASE)
FETCHING_LINK_RELS = {"stylesheet", "icon", "shortcut", "preload", "prefetch", "modulepreload",
                      "manifest", "apple-touch-icon", "preconnect", "dns-prefetch"}


class _ResourceFinder(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.remote: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k.lower(): (v or "") for k, v in attrs}
        urls: list[str] = []
        if tag in {"script", "img", "iframe", "source", "video", "audio", "embed", "track"}:
            urls += [a.get("src", ""), a.get("poster", "")]
            urls += [part.split()[0] for part in a.get("srcset", "").split(",") if part.strip()]
        elif tag == "link":
            rels = set(a.get("rel", "").lower().split())
            if rels & FETCHING_LINK_RELS:
                urls.append(a.get("href", ""))
        elif tag == "object":
            urls.append(a.get("data", ""))
        for url in urls:
            if url and REMOTE.match(url):
                self.remote.append(f"<{tag}> {url}")
        style = a.get("style", "")
        for url in CSS_URL.findall(style):
            if REMOTE.match(url):
                self.remote.append(f"<{tag} style> {url}")


def scan(build_dir: Path) -> list[str]:
    problems: list[str] = []
    for path in sorted(build_dir.rglob("*.html")):
        finder = _ResourceFinder()
        finder.feed(path.read_text(encoding="utf-8", errors="replace"))
        problems += [f"{path.relative_to(build_dir)}: {item}" for item in finder.remote]
    for path in sorted(build_dir.rglob("*.css")):
        text = re.sub(r"/\*.*?\*/", "", path.read_text(encoding="utf-8", errors="replace"),
                      flags=re.S)
        for url in sorted(set(CSS_URL.findall(text) + CSS_IMPORT.findall(text))):
            if REMOTE.match(url):
                problems.append(f"{path.relative_to(build_dir)}: css {url}")
    return problems


def main() -> None:
    build_dir = Path(sys.argv[1] if len(sys.argv) > 1 else "_build/html")
    if not build_dir.is_dir():
        print(f"check_offline.py: error: {build_dir} is not a directory", file=sys.stderr)
        sys.exit(1)
    n_pages = sum(1 for _ in build_dir.rglob("*.html"))
    problems = scan(build_dir)
    if problems:
        print(f"check_offline.py: {len(problems)} remote resource(s) would be loaded:",
              file=sys.stderr)
        for problem in problems:
            print(f"  {problem}", file=sys.stderr)
        sys.exit(1)
    print(f"check_offline.py: OK, {n_pages} pages load no remote scripts, styles, fonts or images")


if __name__ == "__main__":
    main()

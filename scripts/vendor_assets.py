#!/usr/bin/env python
"""Copy the JavaScript the rendered book needs into the git-ignored ``_vendor/`` folder.

The book must render without contacting any CDN, so before each build this script
puts two things next to the sources, where ``_config.yml`` serves them as static files
(``html_static_path: [_vendor]`` -> ``_build/html/_static/...``):

* ``_vendor/mathjax/``: MathJax 3 (``es5/tex-mml-chtml.js`` and the component folders
  it loads at run time: input, output incl. the CHTML web fonts, ui, a11y, adaptors,
  sre) taken from the installed ``django-static-mathjax`` package (MathJax 3.2.2).
* ``_vendor/widgets/``: the Jupyter widgets HTML manager (``embed-amd.js``) and
  RequireJS, unpacked from ``book/_vendor_js/`` (committed, checksummed), plus the three
  Font Awesome web fonts its CSS asks for (copied from the installed pydata-sphinx-theme).

The folder is *not* ``_static/``: Jupyter Book 1 injects every ``.js``/``.css`` found in
``_static`` into every page.

Usage: ``python scripts/vendor_assets.py`` (from anywhere; paths are relative to the
repository root). Works offline; exits non-zero with a message if something is missing
or a checksum does not match.
"""

from __future__ import annotations

import hashlib
import importlib.util
import lzma
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEST = ROOT / "_vendor"
VENDOR_JS = ROOT / "book" / "_vendor_js"

# The MathJax entry point plus every component folder it may load lazily.
MATHJAX_ENTRY = "tex-mml-chtml.js"
MATHJAX_DIRS = ("input", "output", "ui", "a11y", "adaptors", "sre")
MATHJAX_VERSION = "3.2.2"

# (source in book/_vendor_js, name under _vendor/widgets, sha256 of the unpacked file)
WIDGET_FILES = (
    (
        "embed-amd.js.xz",
        "embed-amd.js",
        "ca87dff57c70ffb2658794fde0eab0e27e5f5472a1f5df7ab2b08e1039fc4b72",
    ),
    (
        "require.js",
        "require.js",
        "8215b90000b571bd241d28512c83f59855cecc3158db94b79b2d974c9923b5d2",
    ),
)
# The widget manager's CSS asks for Font Awesome 5 web fonts by content-hashed names next
# to embed-amd.js (webpack public path = the script's folder); the npm tarball ships them,
# the two vendored files do not, so the browser logged three 404s on every page with a
# widget. We serve the Font Awesome web fonts that pydata-sphinx-theme already ships (same
# glyph code points for the icons the built-in widgets use) under those names.
# (hashed name expected by embed-amd.js, Font Awesome file in the theme)
WIDGET_FONTS = (
    ("d878b0a6a1144760244f.woff2", "fa-brands-400.woff2"),
    ("7a3337626410ca2f4071.woff2", "fa-regular-400.woff2"),
    ("1551f4f60c37af51121f.woff2", "fa-solid-900.woff2"),
)
WIDGET_LICENCES = (
    "LICENSE.jupyter-widgets.txt",
    "LICENSE.requirejs.txt",
    "embed-amd.js.THIRD-PARTY-NOTICES.txt",
)


def fail(message: str) -> None:
    print(f"vendor_assets.py: error: {message}", file=sys.stderr)
    sys.exit(1)


def mathjax_es5_dir() -> Path:
    """Locate ``mathjax/static/mathjax/es5`` inside the installed django-static-mathjax."""
    spec = importlib.util.find_spec("mathjax")
    if spec is None or not spec.submodule_search_locations:
        fail(
            "the 'mathjax' package (pip: django-static-mathjax) is not installed; "
            "run `pip install -r requirements.txt`"
        )
    base = Path(list(spec.submodule_search_locations)[0]) / "static" / "mathjax"
    es5 = base / "es5"
    if not (es5 / MATHJAX_ENTRY).is_file():
        fail(f"{es5 / MATHJAX_ENTRY} not found (unexpected django-static-mathjax layout)")
    version = ""
    package_json = base / "package.json"
    if package_json.is_file():
        import json

        version = json.loads(package_json.read_text(encoding="utf-8")).get("version", "")
    if version != MATHJAX_VERSION:
        fail(f"expected MathJax {MATHJAX_VERSION}, found {version!r} in {base}")
    return es5


def copy_mathjax(dest: Path) -> int:
    es5 = mathjax_es5_dir()
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    shutil.copy2(es5 / MATHJAX_ENTRY, dest / MATHJAX_ENTRY)
    for name in MATHJAX_DIRS:
        shutil.copytree(es5 / name, dest / name)
    licence = es5.parent / "LICENSE"
    if licence.is_file():
        shutil.copy2(licence, dest / "LICENSE")
    return sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())


def theme_fontawesome_dir() -> Path:
    """The Font Awesome web fonts shipped with the installed pydata-sphinx-theme."""
    spec = importlib.util.find_spec("pydata_sphinx_theme")
    if spec is None or not spec.submodule_search_locations:
        fail("pydata-sphinx-theme is not installed; run `pip install -r requirements.txt`")
    base = Path(list(spec.submodule_search_locations)[0])
    for candidate in base.rglob("fa-solid-900.woff2"):
        return candidate.parent
    fail(f"no Font Awesome web fonts found under {base}")
    raise AssertionError  # unreachable


def copy_widgets(dest: Path) -> int:
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for source_name, target_name, sha256 in WIDGET_FILES:
        source = VENDOR_JS / source_name
        if not source.is_file():
            fail(f"{source} is missing (it is committed in the repository)")
        data = source.read_bytes()
        if source_name.endswith(".xz"):
            data = lzma.decompress(data)
        digest = hashlib.sha256(data).hexdigest()
        if digest != sha256:
            fail(f"checksum mismatch for {target_name}: expected {sha256}, got {digest}")
        (dest / target_name).write_bytes(data)
    for name in WIDGET_LICENCES:
        shutil.copy2(VENDOR_JS / name, dest / name)
    fonts = theme_fontawesome_dir()
    for target_name, source_name in WIDGET_FONTS:
        shutil.copy2(fonts / source_name, dest / target_name)
    return sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())


def main() -> None:
    DEST.mkdir(exist_ok=True)
    n_math = copy_mathjax(DEST / "mathjax")
    n_widgets = copy_widgets(DEST / "widgets")
    print(
        f"vendor_assets.py: MathJax {MATHJAX_VERSION} -> {DEST / 'mathjax'} "
        f"({n_math / 1e6:.1f} MB); widget manager -> {DEST / 'widgets'} "
        f"({n_widgets / 1e6:.1f} MB)"
    )


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Check that JupyterLab (with the pinned jupyterlab-myst) renders the chapters' MyST markup.

Starts JupyterLab headless on *copies* of the notebooks (in a temporary folder, so no
autosave can write into the tracked files; nothing is executed), opens each chapter in
headless Chromium through the Chrome DevTools protocol, waits until every markdown cell is
rendered, and counts in the rendered markdown:

* **raw MyST leftovers**: text that should have become markup but is shown as typed:
  roles (``{eq}`...```, ``{cite:t}`...```, ``{ref}``...), directive fences (```` ```{note} ````,
  ``:::{dropdown}``), equation labels (``$$ (label)``), target lines (``(label)=``) and
  un-typeset TeX (``$...$``, ``\\begin{...}``);
* what did render: equation references, labelled (numbered) equations, citations,
  admonitions and folded solutions (``<details>`` dropdowns).

Prints one line per notebook and exits 1 if any notebook has a raw-MyST leftover (or did
not finish rendering). With ``--screenshots DIR`` it saves, per notebook, a screenshot of
the first admonition, dropdown, equation reference and numbered equation, to look at.

Usage::

    python scripts/check_jupyterlab.py [NOTEBOOK ...] [--screenshots DIR] [-v]

Needs JupyterLab and jupyterlab-myst (requirements.txt), Chromium (``apt-get install
chromium`` or ``$CHROMIUM``) and ``websocket-client`` (a JupyterLab dependency). Works
offline; JupyterLab and Chromium listen on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from check_overflow import find_chromium  # noqa: E402  (one way to find the browser)

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "pgm-wm-check"

# Runs in the JupyterLab page: is the notebook fully rendered? and what does it show?
PROBE_JS = r"""
(function () {
  var cells = Array.from(document.querySelectorAll(
    ".jp-NotebookPanel:not(.lm-mod-hidden) .jp-Notebook .jp-MarkdownCell"));
  var nb = document.querySelector(".jp-NotebookPanel:not(.lm-mod-hidden) .jp-Notebook");
  var rendered = cells.filter(function (c) {
    return c.querySelector(".jp-MarkdownOutput, .jp-RenderedMarkdown, .myst");
  });
  var pending = document.querySelectorAll(
    ".jp-NotebookPanel:not(.lm-mod-hidden) mjx-container, .jp-NotebookPanel:not(.lm-mod-hidden) .MathJax").length;
  var raw = [];
  var patterns = [
    [/\{(eq|cite|cite:t|cite:p|cite:ts|cite:ps|ref|numref|doc|term|math|download)\}`/, "role"],
    [/^\s*(```|~~~|:::+)\s*\{?[a-z-]*\}?/m, "fence"],
    [/\$\$\s*\([a-z0-9_-]+\)/i, "equation label"],
    [/^\s*\([a-z0-9_-]+\)=\s*$/im, "target"],
    [/(^|[^\\])\$[^$\n]*\\[a-zA-Z]+[^$\n]*\$/, "untypeset $TeX$"],
    [/\\begin\{(aligned|align|split|equation|cases|bmatrix|pmatrix)\}/, "untypeset \\begin"],
  ];
  cells.forEach(function (c, i) {
    var out = c.querySelector(".jp-MarkdownOutput, .jp-RenderedMarkdown, .myst");
    if (!out) return;
    var clone = out.cloneNode(true);
    clone.querySelectorAll("mjx-container, .MathJax, .katex, .katex-display, code, pre, " +
                           "script, style, mjx-assistive-mml")
         .forEach(function (e) { e.remove(); });
    var text = clone.innerText || clone.textContent || "";
    patterns.forEach(function (p) {
      var m = text.match(p[0]);
      if (m) {
        var at = Math.max(0, text.indexOf(m[0]) - 30);
        raw.push({cell: i, kind: p[1], text: text.slice(at, at + 90).replace(/\s+/g, " ")});
      }
    });
  });
  function count(sel) {
    return nb ? nb.querySelectorAll(sel).length : 0;
  }
  return JSON.stringify({
    markdown_cells: cells.length, rendered: rendered.length, raw: raw,
    math: count("mjx-container, .katex"),
    labelled_math: count("[id] .katex-display, [id] mjx-container[display='true']"),
    eq_refs: count("a.hover-link[href^='#'], a[href^='#'][class*='xref']"),
    cites: count("cite, [class*='myst-cite'], a[href*='doi.org'], span[class*='cite']"),
    admonitions: count(".myst-admonition:not(details), aside.admonition"),
    dropdowns: count("details"),
    ids: count("[id]"),
    scroll: nb ? nb.scrollHeight : 0
  });
})()
"""

# Puts the first element matching a selector in view (for a screenshot).
SCROLL_JS = r"""
(function (sel) {
  var nb = document.querySelector(".jp-NotebookPanel:not(.lm-mod-hidden) .jp-Notebook");
  var el = nb && nb.querySelector(sel);
  if (!el) return false;
  el.scrollIntoView({block: "start"});
  var w = nb.closest(".jp-WindowedPanel-outer") || nb;
  w.scrollTop = Math.max(0, w.scrollTop - 40);
  return true;
})(%s)
"""

SHOTS = {
    "admonition": ".myst-admonition:not(details), aside.admonition",
    "dropdown": "details",
    "eqref": "a.hover-link[href^='#']",
    "equation": "[id] .katex-display",
    "cite": "cite, [class*='myst-cite'], span[class*='cite']",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout: float) -> str:
    end = time.time() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return r.read().decode()
        except OSError:
            if time.time() > end:
                raise
            time.sleep(0.5)


class Tab:
    """The smallest Chrome DevTools protocol client: send a command, wait for its reply."""

    def __init__(self, ws_url: str):
        import websocket   # websocket-client, a jupyter_server dependency
        self.ws = websocket.create_connection(ws_url, timeout=120, suppress_origin=True)
        self.n = 0

    def call(self, method: str, **params):
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def eval(self, js: str):
        res = self.call("Runtime.evaluate", expression=js, returnByValue=True)
        return res.get("result", {}).get("value")


def check(notebooks: list[Path], shots: Path | None, verbose: bool,
          timeout: float = 120.0) -> dict[str, dict]:
    chromium = find_chromium()
    if chromium is None:
        raise FileNotFoundError("chromium not found (apt-get install chromium, or set $CHROMIUM)")
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="pgm-jlcheck-") as tmp:
        tmp = Path(tmp)
        work = tmp / "notebooks"
        work.mkdir()
        for nb in notebooks:
            shutil.copy2(nb, work / nb.name)
        settings = tmp / "settings" / "@jupyterlab" / "notebook-extension"
        settings.mkdir(parents=True)
        # render every cell at once (no virtual scrolling), so the probe sees them all
        (settings / "tracker.jupyterlab-settings").write_text('{"windowingMode": "none"}')
        env = dict(os.environ, JUPYTERLAB_SETTINGS_DIR=str(tmp / "settings"),
                   JUPYTERLAB_WORKSPACES_DIR=str(tmp / "ws"), JUPYTER_RUNTIME_DIR=str(tmp / "rt"))
        lab_port, cdp_port = free_port(), free_port()
        lab = subprocess.Popen(
            [sys.executable, "-m", "jupyter", "lab", "--no-browser", "--allow-root",
             f"--ServerApp.token={TOKEN}", f"--port={lab_port}", "--ServerApp.ip=127.0.0.1",
             f"--ServerApp.root_dir={work}", "--LabApp.news_url=",
             "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate"],
            cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=open(tmp / "lab.log", "w"))
        browser = subprocess.Popen(
            [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-extensions", f"--user-data-dir={tmp / 'chromium'}",
             f"--remote-debugging-port={cdp_port}", "--remote-allow-origins=*",
             "--window-size=1400,1000", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait_http(f"http://127.0.0.1:{lab_port}/api/status?token={TOKEN}", 90)
            targets = json.loads(wait_http(f"http://127.0.0.1:{cdp_port}/json", 60))
            page = next(t for t in targets if t.get("type") == "page")
            tab = Tab(page["webSocketDebuggerUrl"])
            tab.call("Page.enable")
            tab.call("Runtime.enable")
            tab.call("Emulation.setDeviceMetricsOverride", width=1400, height=1000,
                     deviceScaleFactor=1, mobile=False)
            for nb in notebooks:
                n_md = sum(1 for c in json.loads(nb.read_text(encoding="utf-8"))["cells"]
                           if c["cell_type"] == "markdown")
                url = (f"http://127.0.0.1:{lab_port}/lab/tree/{nb.name}?token={TOKEN}"
                       "&reset")
                tab.call("Page.navigate", url=url)
                end, rep, stable = time.time() + timeout, {}, 0
                while time.time() < end:
                    time.sleep(2)
                    try:
                        rep = json.loads(tab.eval(PROBE_JS) or "{}")
                    except (RuntimeError, TypeError, ValueError):
                        continue
                    done = rep.get("markdown_cells") == n_md and rep.get("rendered") == n_md
                    stable = stable + 1 if done and rep.get("math", 0) > 0 else 0
                    if stable >= 3:      # three probes in a row agree: typesetting is over
                        break
                rep["expected_markdown_cells"] = n_md
                rep["complete"] = rep.get("rendered") == n_md
                if shots is not None:
                    shots.mkdir(parents=True, exist_ok=True)
                    for name, sel in SHOTS.items():
                        if tab.eval(SCROLL_JS % json.dumps(sel)):
                            time.sleep(0.7)
                            png = tab.call("Page.captureScreenshot", format="png")["data"]
                            (shots / f"{nb.stem}_{name}.png").write_bytes(base64.b64decode(png))
                results[nb.name] = rep
            # the copies' kernels, started by opening the notebooks, end with the server
        finally:
            browser.terminate()
            lab.terminate()
            for p in (browser, lab):
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", type=Path,
                        default=sorted((ROOT / "notebooks").glob("0*.ipynb")))
    parser.add_argument("--screenshots", type=Path, default=None,
                        help="save screenshots of rendered features into this folder")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("-v", "--verbose", action="store_true", help="list every leftover")
    args = parser.parse_args(argv)
    try:
        results = check([p.resolve() for p in args.notebooks], args.screenshots, args.verbose)
    except FileNotFoundError as exc:
        print(f"check_jupyterlab.py: error: {exc}", file=sys.stderr)
        return 2
    print(f"{'notebook':32s} {'md':>4s} {'rend':>4s} {'raw':>4s} {'math':>5s} {'eqref':>5s} "
          f"{'eq#':>4s} {'cite':>4s} {'admon':>5s} {'fold':>4s}")
    bad = 0
    for name, r in results.items():
        print(f"{name:32s} {r.get('expected_markdown_cells', 0):4d} {r.get('rendered', 0):4d} "
              f"{len(r.get('raw', [])):4d} {r.get('math', 0):5d} {r.get('eq_refs', 0):5d} "
              f"{r.get('labelled_math', 0):4d} {r.get('cites', 0):4d} {r.get('admonitions', 0):5d} {r.get('dropdowns', 0):4d}")
        if args.verbose:
            for leftover in r.get("raw", []):
                print(f"      cell {leftover['cell']} {leftover['kind']}: {leftover['text']}")
        bad += len(r.get("raw", [])) + (0 if r.get("complete") else 1)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1), encoding="utf-8")
    total = sum(len(r.get("raw", [])) for r in results.values())
    print(f"TOTAL raw-MyST leftovers: {total}; notebooks not fully rendered: "
          f"{sum(1 for r in results.values() if not r.get('complete'))}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

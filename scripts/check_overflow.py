#!/usr/bin/env python
"""Count the equations, code lines and tables that do not fit in the built book's pages.

Opens every page of the built book (default ``_build/html``) in headless Chromium at a
desktop width (1400 px) and a phone width (390 px), waits until MathJax has typeset the
page and the book's own fitting script (``book/_theme/pgm_wm.js``) has run, and measures
in the browser:

* **display equations** whose typeset formula is wider than its box (``overflow``); those
  that the reader cannot scroll to are ``clipped``;
* **code blocks** (cell inputs and printed outputs) with lines wider than their box, and
  how many such lines there are;
* **tables** wider than the content column: ``hinted`` if they sit in a horizontally
  scrolling box that shows the book's scroll hint, ``clipped`` otherwise;
* **progress widgets** (tqdm bars) and the page's own horizontal overflow;
* the browser console's errors (404s, script errors) while the page loads.

Works offline (``file://`` pages; Chromium is started with networking features off).
Needs Debian's ``chromium`` (``apt-get install chromium``) or ``$CHROMIUM``.

Usage::

    python scripts/check_overflow.py [BUILD_DIR] [--widths 1400,390] [--json OUT.json]
                                     [--pages GLOB] [--strict]

Prints one line per page and width, then the totals. With ``--strict`` the exit status is
1 if the book's criterion (``failures``) is not met: a code line cut off (code scrolls
sideways, so a long line is only a problem where its box does not scroll), a table wider
than the column at the desktop width, or a display equation wider than its box at any width.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import fnmatch
import html
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

# Pages Sphinx generates that carry no book content.
SKIP_PAGES = {"genindex.html", "search.html", "py-modindex.html"}
REPORT_ID = "pgm-overflow-report"

# Measurement code appended to a temporary copy of each page. It waits for MathJax and for
# the book's fitting script, then writes a JSON report into <pre id=REPORT_ID>.
MEASURE_JS = r"""
<script>
(function () {
  "use strict";
  function sleep(ms) { return new Promise(function (r) { setTimeout(r, ms); }); }
  function scrollsX(el) {
    var o = getComputedStyle(el).overflowX;
    return o === "auto" || o === "scroll";
  }
  function scrollAncestor(el, stop) {
    for (var a = el.parentElement; a && a !== stop; a = a.parentElement) {
      if (scrollsX(a)) return a;
    }
    return null;
  }
  function texOf(container) {
    try {
      var items = MathJax.startup.document.getMathItemsWithin(container);
      if (items.length) return items[0].math.replace(/\s+/g, " ").trim().slice(0, 80);
    } catch (e) {}
    return (container.textContent || "").slice(0, 80);
  }
  async function measure() {
    var hasMath = !!document.querySelector('script[src*="mathjax"], script[src*="tex-mml"]');
    for (var i = 0; hasMath && i < 100; i++) {   // wait (virtual time) for MathJax to load
      if (window.MathJax && MathJax.startup && MathJax.startup.promise) break;
      await sleep(50);
    }
    try { if (window.MathJax && MathJax.startup) await MathJax.startup.promise; } catch (e) {}
    var hasFitter = !!document.querySelector('script[src*="pgm_wm.js"]');
    for (var j = 0; hasFitter && j < 60; j++) {   // the book's fitting script marks the body
      if (document.body.dataset.pgmFitted === "1") break;
      await sleep(50);
    }
    await sleep(200);
    var article = document.querySelector(".bd-article") || document.querySelector("main")
                  || document.body;
    var colRight = article.getBoundingClientRect().right;
    var rep = {equations: [], code: [], tables: [], progress: 0, page_overflow: 0,
               n_equations: 0, n_code: 0, n_tables: 0,
               fitted: document.body.dataset.pgmFitted === "1"};
    article.querySelectorAll('mjx-container[display="true"]').forEach(function (c) {
      rep.n_equations += 1;
      var math = c.querySelector("mjx-math");
      if (!math) return;
      var inner = math.getBoundingClientRect();
      var avail = c.clientWidth;
      var over = inner.width > avail + 1 || c.getBoundingClientRect().right > colRight + 1;
      if (!over) return;
      var scroller = scrollsX(c) ? c : scrollAncestor(c, article);
      rep.equations.push({tex: texOf(c), width: Math.round(inner.width),
                          box: Math.round(avail), scrolls: !!scroller});
    });
    article.querySelectorAll("pre").forEach(function (pre) {
      if (pre.id === "pgm-overflow-report") return;
      rep.n_code += 1;
      if (pre.scrollWidth <= pre.clientWidth + 1 &&
          pre.getBoundingClientRect().right <= colRight + 1) return;
      var probe = document.createElement("span");
      probe.textContent = "x".repeat(100);
      probe.style.whiteSpace = "pre";
      pre.appendChild(probe);
      var cw = probe.getBoundingClientRect().width / 100;
      pre.removeChild(probe);
      var cs = getComputedStyle(pre);
      var inner = pre.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight);
      var lines = pre.textContent.split("\n");
      var nWide = lines.filter(function (l) { return l.length * cw > inner + 1; }).length;
      var kind = pre.closest(".cell_output, .output") ? "output" : "input";
      rep.code.push({kind: kind, lines: Math.max(nWide, 1), chars: Math.floor(inner / cw),
                     longest: Math.max.apply(null, lines.map(function (l) { return l.length; })),
                     scrolls: scrollsX(pre),
                     head: lines.find(function (l) { return l.length * cw > inner + 1; }) || ""});
    });
    article.querySelectorAll("table").forEach(function (t) {
      rep.n_tables += 1;
      var scroller = scrollAncestor(t, article);
      var over, hinted = false;
      if (scroller) {
        over = scroller.scrollWidth > scroller.clientWidth + 1;
        // the book's script marks scrolling boxes; its CSS then shows the hint
        hinted = scroller.classList.contains("pgm-scrolls");
      } else {
        over = t.getBoundingClientRect().right > colRight + 1;
      }
      if (over) {
        var head = (t.querySelector("tr") || t).textContent.replace(/\s+/g, " ").trim();
        rep.tables.push({head: head.slice(0, 60), width: Math.round(t.scrollWidth),
                         scrolls: !!scroller, hinted: hinted});
      }
    });
    rep.progress = article.querySelectorAll(
      ".widget-progress, progress, .jupyter-widgets .progress").length;
    rep.page_overflow = Math.max(0, document.documentElement.scrollWidth - window.innerWidth);
    try { await document.fonts.ready; } catch (e) {}
    var errs = (window.__pgmErrors || []).slice();
    document.fonts.forEach(function (f) {
      if (f.status === "error") errs.push("font failed to load: " + f.family);
    });
    rep.console = errs.map(function (m) { return String(m).slice(0, 200); });
    var pre = document.createElement("pre");
    pre.id = "pgm-overflow-report";
    pre.style.display = "none";
    pre.textContent = JSON.stringify(rep);
    document.body.appendChild(pre);
  }
  if (document.readyState === "complete") measure();
  else window.addEventListener("load", measure);
})();
</script>
"""

# Installed first thing in <head>: records script errors, failed resource loads and
# console.error calls from the page's own scripts (headless Chromium does not reliably log
# the console to stderr).
EARLY_JS = r"""<script>window.__pgmErrors = [];
(function () {
  var E = window.__pgmErrors;
  window.addEventListener("error", function (e) {
    var t = e.target;
    if (t && t !== window && (t.src || t.href)) E.push("failed to load " + (t.src || t.href));
    else E.push("script error: " + (e.message || ""));
  }, true);
  window.addEventListener("unhandledrejection", function (e) {
    E.push("unhandled rejection: " + ((e.reason && e.reason.message) || e.reason));
  });
  var ce = console.error;
  console.error = function () {
    E.push("console.error: " + Array.prototype.join.call(arguments, " "));
    return ce.apply(console, arguments);
  };
})();</script>"""

CONSOLE = re.compile(r'CONSOLE\(\d+\)\] "(?P<msg>.*)", source: (?P<src>\S*)')


@dataclass
class PageResult:
    page: str
    width: int
    report: dict = field(default_factory=dict)
    console: list[str] = field(default_factory=list)
    error: str = ""

    # ---- summary numbers -------------------------------------------------------------
    @property
    def eq_over(self) -> int:
        return len(self.report.get("equations", []))

    @property
    def eq_clipped(self) -> int:
        return sum(1 for e in self.report.get("equations", []) if not e["scrolls"])

    @property
    def code_blocks(self) -> int:
        return len(self.report.get("code", []))

    @property
    def code_lines(self) -> int:
        return sum(c["lines"] for c in self.report.get("code", []))

    @property
    def code_clipped_lines(self) -> int:
        return sum(c["lines"] for c in self.report.get("code", []) if not c["scrolls"])

    @property
    def tables_over(self) -> int:
        return len(self.report.get("tables", []))

    @property
    def tables_unhinted(self) -> int:
        return sum(1 for t in self.report.get("tables", []) if not t["hinted"])

    @property
    def progress(self) -> int:
        return int(self.report.get("progress", 0))


def find_chromium() -> str | None:
    for name in (os.environ.get("CHROMIUM", ""), "chromium", "chromium-browser",
                 "google-chrome", "google-chrome-stable"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def chromium_flags(profile: str, width: int) -> list[str]:
    return [
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run",
        "--disable-default-apps", "--disable-extensions", "--mute-audio",
        "--allow-file-access-from-files", f"--user-data-dir={profile}",
        "--enable-logging=stderr", "--v=0", "--hide-scrollbars",
        "--virtual-time-budget=20000", f"--window-size={width},1000", "--dump-dom",
    ]


def measure_page(chromium: str, build_dir: Path, page: Path, width: int,
                 timeout: float = 120.0) -> PageResult:
    rel = page.relative_to(build_dir).as_posix()
    result = PageResult(rel, width)
    text = page.read_text(encoding="utf-8", errors="replace")
    probe_html = text.replace("</body>", MEASURE_JS + "</body>") if "</body>" in text \
        else text + MEASURE_JS
    probe_html = re.sub(r"(<head[^>]*>)", lambda m: m.group(1) + EARLY_JS, probe_html, count=1)
    # The copy sits next to the page so that every relative link resolves the same way.
    fd, probe_name = tempfile.mkstemp(prefix=".overflow-", suffix=".html", dir=page.parent)
    with tempfile.TemporaryDirectory(prefix="pgm-chromium-") as profile:
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(probe_html)
            proc = subprocess.run(
                [chromium, *chromium_flags(profile, width), Path(probe_name).as_uri()],
                capture_output=True, text=True, timeout=timeout,
            )
        except subprocess.TimeoutExpired:
            result.error = f"chromium timed out after {timeout:.0f}s"
            return result
        finally:
            Path(probe_name).unlink(missing_ok=True)
    match = re.search(rf'<pre id="{REPORT_ID}"[^>]*>(.*?)</pre>', proc.stdout, re.S)
    if match is None:
        result.error = "no report (page did not finish loading?)"
    else:
        result.report = json.loads(html.unescape(match.group(1)))
        result.console += [m.replace(Path(probe_name).name, Path(rel).name)
                           for m in result.report.pop("console", [])]
    for line in proc.stderr.splitlines():
        m = CONSOLE.search(line)
        if m:
            src = m.group("src").replace(Path(probe_name).name, Path(rel).name)
            result.console.append(f"{m.group('msg')[:160]} ({Path(src).name})")
        elif "Failed to load resource" in line or "ERR_FILE_NOT_FOUND" in line:
            result.console.append(line.strip()[-160:])
    return result


def list_pages(build_dir: Path, pattern: str | None) -> list[Path]:
    pages = []
    for path in sorted(build_dir.rglob("*.html")):
        rel = path.relative_to(build_dir).as_posix()
        if path.name in SKIP_PAGES or path.name.startswith(".overflow-"):
            continue
        if rel.startswith(("_static/", "_sources/", "_modules/", "_images/")):
            continue
        if pattern and not fnmatch.fnmatch(rel, pattern):
            continue
        head = path.read_text(encoding="utf-8", errors="replace")[:2000].lower()
        if 'http-equiv="refresh"' in head:   # a redirect (the root index.html)
            continue
        pages.append(path)
    return pages


def run(build_dir: Path, widths: list[int], pattern: str | None = None,
        jobs: int = 2) -> list[PageResult]:
    chromium = find_chromium()
    if chromium is None:
        raise FileNotFoundError("chromium not found (apt-get install chromium, or set $CHROMIUM)")
    pages = list_pages(build_dir, pattern)
    tasks = [(page, width) for width in widths for page in pages]
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = [pool.submit(measure_page, chromium, build_dir, p, w) for p, w in tasks]
        return [f.result() for f in futures]


def failures(results: list[PageResult], desktop: int = 1400) -> list[str]:
    """The book's criterion: no code line cut off at any width (a long line must scroll
    sideways, never wrap or disappear); no table wider than the column at the desktop width
    and none without a scroll hint below it; no display equation wider than its box at any
    width; no progress widget anywhere; every page measured."""
    problems = []
    for r in results:
        where = f"{r.page} @ {r.width}px"
        if r.error:
            problems.append(f"{where}: {r.error}")
            continue
        if r.eq_over:
            problems.append(f"{where}: {r.eq_over} display equation(s) wider than the column")
        if r.progress:
            problems.append(f"{where}: {r.progress} progress widget(s)")
        if r.code_clipped_lines:
            problems.append(f"{where}: {r.code_clipped_lines} code line(s) cut off (wider than a box "
                            "that does not scroll)")
        if r.width >= desktop:
            if r.tables_over:
                problems.append(f"{where}: {r.tables_over} table(s) wider than the column")
        elif r.tables_unhinted:
            problems.append(f"{where}: {r.tables_unhinted} wide table(s) without a scroll hint")
    return problems


def print_report(results: list[PageResult], verbose: bool = False) -> None:
    header = (f"{'page':44s} {'px':>5s} {'eq>box':>6s} {'eq.clip':>7s} {'code':>5s} "
              f"{'lines':>5s} {'tables':>6s} {'nohint':>6s} {'tqdm':>4s} {'console':>7s}")
    print(header)
    for r in results:
        if r.error:
            print(f"{r.page:44s} {r.width:5d}  ERROR: {r.error}")
            continue
        print(f"{r.page:44s} {r.width:5d} {r.eq_over:6d} {r.eq_clipped:7d} "
              f"{r.code_blocks:5d} {r.code_lines:5d} {r.tables_over:6d} "
              f"{r.tables_unhinted:6d} {r.progress:4d} {len(r.console):7d}")
        if verbose:
            for e in r.report.get("equations", []):
                print(f"      eq {e['width']}>{e['box']}px: {e['tex']}")
            for c in r.report.get("code", [])[:5]:
                print(f"      {c['kind']} ({c['lines']} lines > {c['chars']} chars): "
                      f"{c['head'][:90]}")
            for t in r.report.get("tables", []):
                print(f"      table {t['width']}px hinted={t['hinted']}: {t['head']}")
            for msg in r.console[:8]:
                print(f"      console: {msg}")
    widths = sorted({r.width for r in results}, reverse=True)
    for w in widths:
        rs = [r for r in results if r.width == w and not r.error]
        print(f"TOTAL @ {w}px over {len(rs)} pages: "
              f"{sum(r.eq_over for r in rs)} display equations wider than their box "
              f"({sum(r.eq_clipped for r in rs)} not scrollable), "
              f"{sum(r.code_lines for r in rs)} code lines in {sum(r.code_blocks for r in rs)} "
              f"blocks wider than their box, {sum(r.tables_over for r in rs)} wide tables "
              f"({sum(r.tables_unhinted for r in rs)} without a scroll hint), "
              f"{sum(r.progress for r in rs)} progress widgets, "
              f"{sum(len(r.console) for r in rs)} console messages")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("build_dir", nargs="?", default="_build/html")
    parser.add_argument("--widths", default="1400,390",
                        help="comma-separated window widths in px (default 1400,390)")
    parser.add_argument("--pages", default=None, help="only pages matching this glob")
    parser.add_argument("--json", default=None, help="write the full results to this file")
    parser.add_argument("--jobs", type=int, default=2, help="parallel browsers (default 2)")
    parser.add_argument("--strict", action="store_true",
                        help="exit 1 if the book's fit criterion is not met")
    parser.add_argument("-v", "--verbose", action="store_true", help="list every offender")
    args = parser.parse_args(argv)
    build_dir = Path(args.build_dir)
    if not (build_dir / "index.html").is_file():
        print(f"check_overflow.py: error: {build_dir}/index.html not found; build the book "
              "first (bash scripts/build_book.sh)", file=sys.stderr)
        return 2
    widths = [int(w) for w in args.widths.split(",") if w.strip()]
    try:
        results = run(build_dir, widths, args.pages, args.jobs)
    except FileNotFoundError as exc:
        print(f"check_overflow.py: error: {exc}", file=sys.stderr)
        return 2
    print_report(results, verbose=args.verbose)
    if args.json:
        Path(args.json).write_text(json.dumps(
            [{"page": r.page, "width": r.width, "error": r.error, "console": r.console,
              **r.report} for r in results], indent=1), encoding="utf-8")
    problems = failures(results, desktop=max(widths))
    if problems:
        print(f"check_overflow.py: {len(problems)} problem(s):")
        for p in problems:
            print(f"  {p}")
    else:
        print("check_overflow.py: OK, everything fits")
    return 1 if (args.strict and problems) else 0


if __name__ == "__main__":
    sys.exit(main())

/* pgm_wm book layout helper (served from the repository, no CDN).
 *
 * After MathJax has typeset the page (and again after every resize):
 *  - a display equation wider than its box is shrunk to fit, down to 55 % of its size;
 *    one that is still too wide scrolls sideways and gets a visible hint;
 *  - numbers in table cells are not broken across lines; a table too wide for its box first
 *    puts the intervals of "value [low, high]" cells on a second line;
 *  - every table, and every code block or printed output, that is still wider than its box
 *    scrolls sideways and shows a hint ("<- scroll sideways ... ->").
 * scripts/check_overflow.py waits for document.body.dataset.pgmFitted === "1".
 */
(function () {
  "use strict";
  var MIN_SCALE = 0.55;

  function article() {
    return document.querySelector(".bd-article") || document.querySelector("main") ||
      document.body;
  }

  function hint(box, on) {
    var prev = box.previousElementSibling;
    var has = prev && prev.classList.contains("pgm-scroll-hint");
    if (on) {
      box.classList.add("pgm-scrolls");
      if (!has) {
        var h = document.createElement("div");
        h.className = "pgm-scroll-hint";
        h.setAttribute("aria-hidden", "true");
        box.parentNode.insertBefore(h, box);
      }
    } else {
      box.classList.remove("pgm-scrolls");
      if (has) prev.remove();
    }
  }

  function fitEquations(root) {
    root.querySelectorAll('mjx-container[display="true"]').forEach(function (c) {
      c.style.fontSize = "";
      var math = c.querySelector("mjx-math");
      if (!math) return;
      var avail = c.clientWidth;
      var width = math.getBoundingClientRect().width;
      var box = c.closest("div.math") || c;
      if (width <= avail + 1 || avail <= 0) { hint(box, false); return; }
      var scale = Math.max(MIN_SCALE, Math.floor((avail / width) * 98) / 100);
      c.style.fontSize = (scale * 100).toFixed(0) + "%";
      var now = math.getBoundingClientRect().width;
      hint(box, now > c.clientWidth + 1);
    });
  }

  function scrollBox(el) {
    for (var a = el.parentElement; a && a !== document.body; a = a.parentElement) {
      var o = getComputedStyle(a).overflowX;
      if (o === "auto" || o === "scroll") return a;
    }
    return null;
  }

  /* Numbers in table cells are never broken across lines: a cell without words (a number,
     "0.093 [0.088, 0.099]", "**1.2**") keeps its line. If a table is then wider than its box,
     each "value [low, high]" cell puts its interval on a second line, in smaller type; only a
     table that still does not fit scrolls sideways (with the hint). */
  var NUMERIC = /^[^A-Za-z]*$|^[\s\d.,\[\]()+\-\u2212\u00b1\u00d7%eE*]+$/;
  var INTERVAL = /^(\S+)\s+(\[[^\]]+\])$/;

  function keepNumbersTogether(t) {
    t.querySelectorAll("td").forEach(function (td) {
      var text = (td.textContent || "").trim();
      if (text && NUMERIC.test(text)) td.classList.add("pgm-num");
    });
  }

  function splitIntervals(t) {
    t.querySelectorAll("td.pgm-num").forEach(function (td) {
      if (td.dataset.pgmSplit) return;
      // the element that holds the text: the cell, or its only child (<p>, <strong>), ...
      var el = td;
      while (el.children.length === 1 && el.childNodes.length === 1) el = el.children[0];
      if (el.children.length) return;
      var m = (el.textContent || "").trim().match(INTERVAL);
      if (!m) return;
      td.dataset.pgmSplit = "1";
      el.textContent = m[1];
      var ci = document.createElement("span");
      ci.className = "pgm-ci";
      ci.textContent = m[2];
      el.appendChild(ci);
    });
  }

  function fitTables(root) {
    root.querySelectorAll("table").forEach(function (t) { keepNumbersTogether(t); });
    root.querySelectorAll("table").forEach(function (t) {
      var box = scrollBox(t);
      if (!box || !root.contains(box)) {
        box = document.createElement("div");
        box.className = "pgm-table-scroll";
        box.style.overflowX = "auto";
        t.parentNode.insertBefore(box, t);
        box.appendChild(t);
      }
      if (box.scrollWidth > box.clientWidth + 1) splitIntervals(t);
      hint(box, box.scrollWidth > box.clientWidth + 1);
    });
  }

  function fitOutputs(root) {
    root.querySelectorAll(".cell_output pre, div.highlight pre").forEach(function (pre) {
      hint(pre, pre.scrollWidth > pre.clientWidth + 1);
    });
  }

  function fitAll() {
    mathjax2Shim();
    var root = article();
    try { fitEquations(root); } catch (e) { console.log("pgm_wm.js equations:", e); }
    try { fitTables(root); } catch (e) { console.log("pgm_wm.js tables:", e); }
    try { fitOutputs(root); } catch (e) { console.log("pgm_wm.js outputs:", e); }
    document.body.dataset.pgmFitted = "1";
  }

  function whenTypeset(fn) {
    var tries = 0;
    (function wait() {
      var mj = window.MathJax;
      if (mj && mj.startup && mj.startup.promise) {
        mj.startup.promise.then(fn, fn);
      } else if (tries++ < 100 && document.querySelector(".math, mjx-container")) {
        setTimeout(wait, 100);
      } else {
        fn();
      }
    })();
  }

  /* The widget manager (embed-amd.js) typesets widget labels with the MathJax 2 call
     MathJax.Hub.Queue(["Typeset", MathJax.Hub, element]); the book loads MathJax 3, which
     has no Hub, so every page with a widget logged an error. Forward the call. */
  function mathjax2Shim() {
    var mj = window.MathJax;
    if (!mj || mj.Hub || !mj.version || String(mj.version).charAt(0) !== "3") return;
    mj.Hub = {
      Queue: function () {
        for (var i = 0; i < arguments.length; i++) {
          var job = arguments[i];
          if (Array.isArray(job) && job[0] === "Typeset" && job[2] && mj.typesetPromise) {
            mj.typesetPromise([job[2]]).catch(function () {});
          }
        }
      }
    };
  }
  document.addEventListener("DOMContentLoaded", mathjax2Shim);
  window.addEventListener("load", mathjax2Shim);

  var timer = null;
  window.addEventListener("resize", function () {
    clearTimeout(timer);
    timer = setTimeout(fitAll, 150);
  });
  if (document.readyState === "loading") {
    document.addEventListener("DOMContentLoaded", function () { whenTypeset(fitAll); });
  } else {
    whenTypeset(fitAll);
  }
})();

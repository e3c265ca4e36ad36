"""Multi-seed results files: what was run, where, with which budget, and what came out.

A results file (JSON, under ``results/``) holds, for one chapter's experiment:

* ``provenance``: the git commit (and whether the tree was dirty), the command, the date, the
  machine (platform, CPU count, torch version and thread count), the training budget in CPU
  seconds per model, the seeds, and the wall time of the whole run;
* ``horizons``: the prediction horizons ``k`` (steps) the errors are reported at;
* ``models``: for every model, per seed, per horizon, per test window, the mean squared error
  (in the units named by ``units`` after multiplying by ``scale``) and optionally the NLL.

Everything a chapter states about the comparison is *computed* from this file
(:func:`summary_table`, :func:`conclusions`), never typed: see :mod:`pgm_wm.experiments.stats`
for the intervals.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .stats import Interval, mean_interval, paired_ratio, rmse_interval

__all__ = [
    "package_source_hash",
    "code_fingerprint",
    "package_code_hashes",
    "changed_code",
    "package_note",
    "merge_results",
    "check_study",
    "training_table",
    "paired_ratios",
    "validation_choice",
    "provenance",
    "save_results",
    "write_json",
    "load_results",
    "summarize",
    "summary_table",
    "conclusions",
    "provenance_text",
    "results_path",
    "report",
    "check_output_path",
    "is_committed",
]

_REPO = Path(__file__).resolve().parents[2]


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=_REPO, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _command() -> str:
    argv = list(sys.argv)
    if argv and argv[0].endswith(os.path.join("experiments", "__main__.py")):
        argv[0] = "-m pgm_wm.experiments"
    return " ".join(["python", *argv])


def package_source_hash(root: str | os.PathLike | None = None) -> str:
    """SHA-256 of the package's source: every ``*.py`` file under ``pgm_wm/`` (its path relative
    to the package and its bytes, in sorted order). Equal hashes mean the same code, whatever the
    commit; a chapter compares the hash in a results file with the installed package's."""
    import hashlib

    pkg = Path(__file__).resolve().parents[1] if root is None else Path(root)
    h = hashlib.sha256()
    for f in sorted(pkg.rglob("*.py")):
        if "__pycache__" in f.parts:
            continue
        h.update(f.relative_to(pkg).as_posix().encode() + b"\0")
        h.update(f.read_bytes() + b"\0")
    return h.hexdigest()


def code_fingerprint(source: str | bytes) -> str:
    """SHA-256 of a module's *code*: its syntax tree with every bare string statement (docstrings,
    attribute docstrings) removed, written back as text by :func:`ast.unparse`; comments,
    blank lines and formatting never reach the tree. Two sources with the same fingerprint run
    the same statements; a documentation-only edit keeps the fingerprint."""
    import ast
    import hashlib

    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if not isinstance(body, list):
            continue
        kept = [b for b in body if not (isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
                                         and isinstance(b.value.value, str))]
        if len(kept) != len(body):
            node.body = kept or [ast.Pass()]
    return hashlib.sha256(ast.unparse(tree).encode()).hexdigest()


def package_code_hashes(root: str | os.PathLike | None = None) -> dict[str, str]:
    """:func:`code_fingerprint` of every ``*.py`` file under ``pgm_wm/`` (or ``root``), keyed by its
    path relative to the package; stored in a results file's provenance as ``code_hashes``."""
    pkg = Path(__file__).resolve().parents[1] if root is None else Path(root)
    return {f.relative_to(pkg).as_posix(): code_fingerprint(f.read_bytes())
            for f in sorted(pkg.rglob("*.py")) if "__pycache__" not in f.parts}


def changed_code(results: Mapping[str, Any]) -> list[str] | None:
    """The package files whose code (:func:`code_fingerprint`) differs from the code that made
    ``results``: files that existed then and changed or were removed since. Files added since are
    not listed (the run could not use them). ``None`` if the file records no ``code_hashes``."""
    then = results.get("provenance", {}).get("code_hashes")
    if not isinstance(then, Mapping):
        return None
    now = package_code_hashes()
    return sorted(f for f, h in then.items() if now.get(f) != h)


def package_note(results: Mapping[str, Any]) -> str | None:
    """``None`` if ``results`` were made by this package's code, else a sentence saying what
    differs (for a chapter to print visibly).

    Same code means the same source (:func:`package_source_hash`) or, where the file records
    per-file ``code_hashes``, no file of the package as it was then has changed code since
    (:func:`changed_code`): edits to docstrings and comments and modules added later cannot change
    the numbers."""
    made = results.get("provenance", {}).get("package_hash")
    if made == package_source_hash():
        return None
    when = results.get("provenance", {}).get("date", "an unknown date")
    if made is None:
        return (f"These results were made on {when} by a package version that did not record its source "
                f"hash, so they may come from other code than the package you are running.")
    changed = changed_code(results)
    if changed == []:
        return None
    if changed is None:
        return (f"These results were made on {when} by package source {made[:12]}, which differs from the "
                f"source installed here ({package_source_hash()[:12]}); regenerate them with the command in their "
                f"provenance to see the numbers of this code.")
    shown = ", ".join(f"`pgm_wm/{f}`" for f in changed[:8]) + (f" and {len(changed) - 8} more" if len(changed) > 8 else "")
    return (f"These results were made on {when}; since then the code (not only the documentation) of "
            f"{len(changed)} package file{'s' if len(changed) > 1 else ''} changed: {shown}. The numbers come from the "
            f"earlier code; regenerate them with the command in their provenance to see the numbers of this code.")


def provenance(**extra: Any) -> dict[str, Any]:
    """Commit, package-source hash, per-file code hashes (:func:`package_code_hashes`), command, date and
    machine of the current run, plus ``extra``."""
    import torch

    # "dirty": tracked files changed other than results/ (the outputs of earlier runs are not code)
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results")
    info: dict[str, Any] = {
        "commit": _git("rev-parse", "HEAD") or "unknown",
        "dirty": bool(status) if status is not None else None,
        "package_hash": package_source_hash(),
        "code_hashes": package_code_hashes(),
        "command": _command(),
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "torch_threads": 1,            # every model trains and is scored with one thread (runner._run_one)
        },
    }
    info.update(extra)
    return info


def _check_results(results: Mapping[str, Any]) -> None:
    for key in ("provenance", "horizons", "models"):
        if key not in results:
            raise ValueError(f"results: missing key {key!r}")
    horizons = list(results["horizons"])
    if not horizons:
        raise ValueError("results: 'horizons' is empty")
    n_windows = None
    for name, entry in results["models"].items():
        sq = np.asarray(entry.get("sq_err"), dtype=np.float64)
        if sq.ndim != 3 or sq.shape[1] != len(horizons):
            raise ValueError(f"results: model {name!r} needs sq_err of shape (seeds, {len(horizons)}, windows), "
                             f"got {sq.shape}")
        if n_windows is None:
            n_windows = sq.shape[2]
        elif sq.shape[2] != n_windows:
            raise ValueError(f"results: model {name!r} was scored on {sq.shape[2]} windows, others on {n_windows}")


def write_json(path: str | os.PathLike, data: Mapping[str, Any]) -> Path:
    """Write ``data`` as JSON, atomically (a failed write leaves the old file as it was), numbers
    rounded to 7 significant digits to keep files small; numpy arrays and scalars become lists and
    numbers."""

    def clean(x: Any) -> Any:
        if isinstance(x, Mapping):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.ndarray):
            return clean(x.tolist())
        if isinstance(x, (float, np.floating)):
            return float(f"{float(x):.7g}")
        if isinstance(x, np.integer):
            return int(x)
        return x

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(clean(data), indent=1) + "\n"
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, p)
    finally:
        if tmp.exists():
            tmp.unlink()
    return p


def save_results(path: str | os.PathLike, results: Mapping[str, Any]) -> Path:
    """Write a prediction study's ``results`` (checked first) with :func:`write_json`."""
    _check_results(results)
    return write_json(path, results)


def is_committed(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a file tracked by the git repository it lies in (False outside one)."""
    p = Path(path).resolve()
    if not p.is_file():
        return False
    try:
        out = subprocess.run(["git", "ls-files", "--error-unmatch", p.name], cwd=p.parent, capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return False
    return out.returncode == 0


def check_output_path(path: str | os.PathLike, force: bool = False) -> Path:
    """Check, before any training, that a results file can be written at ``path``.

    Raises ``ValueError`` (``"out: ..."``) when the path is a folder, its folder cannot be created
    or written, or it is a results file committed to git and ``force`` is False (a smoke run must
    not replace the committed numbers by accident)."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"out: {p} is a folder; give a file name")
    if p.exists() and is_committed(p) and not force:
        raise ValueError(f"out: {p} is a committed results file; pass --force to overwrite it, or --out "
                         f"another file")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        probe = p.with_name(f".{p.name}.{os.getpid()}.probe")
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"out: cannot write into {p.parent} ({type(err).__name__}: {err})") from err
    return p


def merge_results(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One results file from runs of the same experiment with different seeds (e.g. split over
    several sessions): the same experiment, protocol, horizons, budget, test windows and package
    source are required, and the seeds must not overlap. Per model, the seeds' arrays and runs
    are concatenated in seed order; the provenance lists every part's."""
    if len(parts) < 2:
        raise ValueError("parts: need at least two results to merge")
    first = parts[0]
    same = ("experiment", "horizons", "protocol", "units", "scale")
    for i, r in enumerate(parts[1:], 1):
        for key in same:
            if r.get(key) != first.get(key):
                raise ValueError(f"parts: part {i} differs from part 0 in {key!r}")
        for key in ("budget_cpu_s", "package_hash", "max_steps"):
            if r["provenance"].get(key) != first["provenance"].get(key):
                raise ValueError(f"parts: part {i} differs from part 0 in provenance {key!r}")
        if set(r["models"]) != set(first["models"]):
            raise ValueError(f"parts: part {i} has other models than part 0")
    seeds = [list(r["provenance"].get("seeds", [])) for r in parts]
    flat = [s for ss in seeds for s in ss]
    if len(set(flat)) != len(flat):
        raise ValueError(f"parts: the seeds overlap ({seeds})")
    order = np.argsort(flat, kind="stable")
    models: dict[str, Any] = {}
    for name, entry in first["models"].items():
        sq = np.concatenate([np.asarray(r["models"][name]["sq_err"], dtype=np.float64) for r in parts])
        if sq.shape[0] != len(flat):
            raise ValueError(f"parts: model {name!r} does not have one row per seed")
        nll = None
        if entry.get("nll") is not None:
            nll = np.concatenate([np.asarray(r["models"][name]["nll"], dtype=np.float64) for r in parts])[order]
        runs = [run for r in parts for run in r["models"][name].get("runs", [])]
        models[name] = {**entry, "sq_err": sq[order], "nll": nll,
                        "runs": [runs[i] for i in order] if len(runs) == len(flat) else runs}
    prov = {**first["provenance"], "seeds": sorted(flat), "parts": [r["provenance"] for r in parts],
            "wall_s": round(sum(float(r["provenance"].get("wall_s", 0.0)) for r in parts), 1)}
    merged = {**first, "provenance": prov, "models": models}
    _check_results(merged)
    return merged


def check_study(results: Mapping[str, Any], min_seeds: int = 5) -> None:
    """Raise ``ValueError`` unless ``results`` is a complete study of the convergence protocol:
    at least ``min_seeds`` seeds, the package-source hash, and for every trained model and seed
    the optimizer steps, epochs, the learning curve (validation RMSE, with test RMSE at the
    checkpoints) and the stopping rule's verdict."""
    _check_results(results)
    prov = results["provenance"]
    if len(prov.get("seeds", [])) < min_seeds:
        raise ValueError(f"results: {len(prov.get('seeds', []))} seeds, need at least {min_seeds}")
    if not prov.get("package_hash"):
        raise ValueError("results: no package_hash in the provenance")
    for name, entry in results["models"].items():
        if not entry.get("trained", True):
            continue
        runs = entry.get("runs", [])
        if len(runs) != len(prov["seeds"]):
            raise ValueError(f"results: model {name!r} has {len(runs)} runs for {len(prov['seeds'])} seeds")
        for i, run in enumerate(runs):
            for key in ("steps", "epochs", "curve", "converged", "improvement_last_doubling", "best_valid"):
                if key not in run:
                    raise ValueError(f"results: model {name!r}, run {i} has no {key!r}")
            curve = run["curve"]
            if len(curve) < 3 or not all({"step", "cpu_s", "valid"} <= set(e) for e in curve):
                raise ValueError(f"results: model {name!r}, run {i} has no usable learning curve")
            if not any("test" in e for e in curve):
                raise ValueError(f"results: model {name!r}, run {i} has no test checkpoint on its curve")


def training_table(results: Mapping[str, Any]) -> str:
    """Markdown: per trained model, the median over seeds of its optimizer steps, epochs and
    best validation RMSE, and how many seeds met the stopping rule (the best validation RMSE
    improved by less than 2 % over the last doubling of the budget) and how many diverged (their
    training ended at a non-finite loss or output; they keep their best validated parameters and
    never count as converged)."""
    from ..plotting import markdown_table

    rows = []
    for name, entry in results["models"].items():
        runs = entry.get("runs", [])
        if not entry.get("trained", True) or not runs or "steps" not in runs[0]:
            continue
        med = lambda key: float(np.median([float(r[key]) for r in runs]))  # noqa: E731
        impr = [float(r["improvement_last_doubling"]) for r in runs]
        rows.append([name, f"{med('steps'):.0f}", f"{med('epochs'):.0f}", f"{med('best_valid'):.4g}",
                     f"{100 * float(np.median(impr)):.1f} %", f"{sum(bool(r['converged']) for r in runs)}/{len(runs)}"
                     + (f" ({n_div} diverged)" if (n_div := sum("diverged" in r for r in runs)) else "")])
    return markdown_table(rows, ["model", "steps", "epochs", "valid RMSE (normalized)",
                                 "improvement, last doubling", "converged"])


def load_results(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a results file written by :func:`save_results`."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"path: no results file at {p} (regenerate it with `python -m pgm_wm.experiments`)")
    results = json.loads(p.read_text())
    _check_results(results)
    return results


def summarize(results: Mapping[str, Any], n_boot: int = 2000, seed: int = 0) -> dict[str, dict[str, list[Interval]]]:
    """Per model: ``{"rmse": [Interval per horizon], "nll": [...]}`` (``nll`` only if stored).

    RMSEs are in the file's units (``scale`` applied)."""
    scale = float(results.get("scale", 1.0))
    out: dict[str, dict[str, list[Interval]]] = {}
    for name, entry in results["models"].items():
        sq = np.asarray(entry["sq_err"], dtype=np.float64) * scale**2
        rows = {"rmse": [rmse_interval(sq[:, i], n_boot, seed=seed) for i in range(sq.shape[1])]}
        if entry.get("nll") is not None:
            nll = np.asarray(entry["nll"], dtype=np.float64)
            rows["nll"] = [mean_interval(nll[:, i], n_boot, seed=seed) for i in range(nll.shape[1])]
        out[name] = rows
    return out


def summary_table(results: Mapping[str, Any], summary: Mapping[str, Any] | None = None,
                  fmt: str = ".3g") -> str:
    """Markdown table: one row per model, ``RMSE [95 % interval]`` per horizon, then the NLL
    averaged over horizons where stored."""
    from ..plotting import markdown_table

    summary = summarize(results) if summary is None else summary
    horizons = list(results["horizons"])
    has_nll = any("nll" in s for s in summary.values())
    header = ["model"] + [f"k = {h}" for h in horizons] + (["NLL (mean over k)"] if has_nll else [])
    rows = []
    for name, s in summary.items():
        row = [name] + [iv.format(fmt) for iv in s["rmse"]]
        if has_nll:
            row.append(format(float(np.mean([iv.point for iv in s["nll"]])), fmt) if "nll" in s else "–")
        rows.append(row)
    return markdown_table(rows, header)


def conclusions(results: Mapping[str, Any], candidates: Sequence[str] | None = None, n_boot: int = 2000,
                seed: int = 0) -> list[str]:
    """One computed sentence per horizon: which model has the lowest RMSE, its ratio to the
    runner-up with a paired interval, and whether the ordering survives that interval.

    ``candidates`` restricts the comparison (default: every model in the file)."""
    names = list(results["models"]) if candidates is None else list(candidates)
    if len(names) < 2:
        raise ValueError("candidates: need at least two models to compare")
    for n in names:
        if n not in results["models"]:
            raise ValueError(f"candidates: unknown model {n!r}")
    sq = {n: np.asarray(results["models"][n]["sq_err"], dtype=np.float64) for n in names}
    sentences = []
    for i, h in enumerate(results["horizons"]):
        order = sorted(names, key=lambda n: float(sq[n][:, i].mean()))
        best, second = order[0], order[1]
        ratio = paired_ratio(sq[best][:, i], sq[second][:, i], n_boot, seed=seed)
        verdict = ("the whole interval lies below 1, so this ordering survives the intervals"
                   if ratio.hi < 1.0 else "the interval contains 1, so the two are not distinguishable here")
        sentences.append(f"At k = {h}, {best} has the lowest RMSE; its ratio to the runner-up {second} is "
                         f"{ratio.format('.3f')} ({verdict}).")
    return sentences


def validation_choice(results: Mapping[str, Any], variants: Sequence[str]) -> tuple[str, str]:
    """Pick one of ``variants`` (e.g. three readouts of one model) by validation alone: the one
    with the lowest mean, over seeds, of the open-loop validation RMSE of its selected epoch
    (``runs[i]["best_valid"]``, normalized units). The test split plays no part. Returns
    ``(name, sentence)``; the sentence gives every variant's mean validation RMSE."""
    if len(variants) < 2:
        raise ValueError("variants: need at least two models to choose from")
    scores = {}
    for n in variants:
        if n not in results["models"]:
            raise ValueError(f"variants: unknown model {n!r}")
        vals = [r.get("best_valid") for r in results["models"][n]["runs"]]
        if any(v is None for v in vals):
            raise ValueError(f"variants: {n!r} has no validation score (not a trained model?)")
        scores[n] = float(np.mean(vals))
    best = min(scores, key=lambda n: scores[n] if math.isfinite(scores[n]) else math.inf)
    listed = "; ".join(f"{n} {v:.4g}" for n, v in scores.items())
    return best, (f"Chosen on validation, never on the test split: {best} has the lowest mean validation "
                  f"open-loop RMSE of its selected epoch over {len(results['models'][best]['runs'])} seeds "
                  f"(normalized units: {listed}).")


def paired_ratios(results: Mapping[str, Any], ours: str, rivals: Sequence[str], n_boot: int = 2000,
                  seed: int = 0) -> dict[str, list[Interval]]:
    """Per rival and horizon, RMSE(``ours``) / RMSE(rival) with the paired interval of
    :func:`~pgm_wm.experiments.stats.paired_ratio` (test windows resampled jointly, seeds
    independently); below 1 means ``ours`` has the lower error."""
    models = results["models"]
    for name in (ours, *rivals):
        if name not in models:
            raise ValueError(f"ours: unknown model {name!r}; known: {', '.join(models)}")
    sq = {n: np.asarray(models[n]["sq_err"], dtype=np.float64) for n in (ours, *rivals)}   # (seeds, horizons, windows)
    return {n: [paired_ratio(sq[ours][:, j], sq[n][:, j], n_boot=n_boot, seed=seed)
                for j in range(len(results["horizons"]))] for n in rivals}


def provenance_text(results: Mapping[str, Any]) -> str:
    """One paragraph describing how and where the file was produced."""
    p = results["provenance"]
    mach = p.get("machine", {})
    commit = str(p.get("commit", "unknown"))[:10] + (" (uncommitted changes)" if p.get("dirty") else "")
    seeds = p.get("seeds", [])
    n_win = np.asarray(next(iter(results["models"].values()))["sq_err"]).shape[2]
    parts = p.get("parts") or [p]      # a merged file (merge_results): every part's command and date
    made = " and ".join(f"`{q.get('command', '?')}` on {q.get('date', '?')}" for q in parts)
    return (f"Produced by {made}{' (merged)' if len(parts) > 1 else ''} at commit {commit}, on "
            f"{mach.get('cpu_count', '?')} CPUs ({mach.get('platform', '?')}, torch {mach.get('torch', '?')}, "
            f"{mach.get('torch_threads', '?')} thread(s)); {len(seeds)} seeds, a training budget of "
            f"{p.get('budget_cpu_s', '?')} CPU seconds per model, {n_win} test windows; the whole run took "
            f"{p.get('wall_s', '?')} s.")


def results_path(name: str) -> Path:
    """``results/<name>.json`` of this checkout (where ``python -m pgm_wm.experiments`` writes)."""
    return _REPO / "results" / f"{name}.json"


def report(name: str, candidates: Sequence[str] | None = None, fmt: str = ".3g") -> str:
    """Markdown for a chapter: the multi-seed table with intervals, one computed sentence per
    horizon comparing ``candidates`` (default: the trained models), one per horizon comparing the
    best candidate with the best reference row that is not an oracle (repeat-last, training mean,
    linear ARX), and the provenance."""
    res = load_results(results_path(name))
    models = res["models"]
    if candidates is None:
        candidates = [n for n, e in models.items() if e.get("trained", True)]
    references = [n for n, e in models.items() if not e.get("trained", True) and "oracle" not in n]
    seeds = len(res["provenance"].get("seeds", []))
    units = f" ({res['units']})" if res.get("units") else ""
    lines = [f"**{res.get('title', name)}: test RMSE{units} at horizon k, mean over {seeds} seeds and the test "
             f"windows, with 95 % bootstrap intervals (seeds × windows).**", "", summary_table(res, fmt=fmt), "",
             "Among the trained models:", ""]
    lines += [f"* {s}" for s in conclusions(res, candidates)]
    if references:
        lines += ["", "Against the reference rows:", ""]
        scale = float(res.get("scale", 1.0))
        for i, h in enumerate(res["horizons"]):
            sq = {n: np.asarray(models[n]["sq_err"], dtype=np.float64)[:, i] for n in [*candidates, *references]}
            best = min(candidates, key=lambda n: float(sq[n].mean()))
            ref = min(references, key=lambda n: float(sq[n].mean()))
            ratio = paired_ratio(sq[best], sq[ref])
            word = "beats" if ratio.hi < 1.0 else "loses to" if ratio.lo > 1.0 else "is not distinguishable from"
            lines.append(f"* At k = {h}, the best trained model ({best}, {math.sqrt(sq[best].mean()) * scale:{fmt}}) "
                         f"{word} the best reference row ({ref}, {math.sqrt(sq[ref].mean()) * scale:{fmt}}): "
                         f"ratio {ratio.format('.3f')}.")
    lines += ["", provenance_text(res)]
    return "\n".join(lines)

"""Plot and table helpers shared by the chapter notebooks.

The helpers here are presentation only: they never compute a model quantity themselves.
Chapters add their own helpers at the end of this file (one function per plot kind).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["to_numpy", "plot_belief", "markdown_table"]


def to_numpy(x: Any) -> np.ndarray:
    """Convert a tensor/array-like to a numpy array (detached, on CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def plot_belief(
    ax: Any,
    t: Any,
    mean: Any,
    var: Any,
    label: str = "belief",
    color: str | None = None,
    n_std: float = 2.0,
) -> None:
    """Plot a 1-D belief: the mean as a line and a ``± n_std`` standard-deviation band.

    Args:
        ax: a matplotlib axis. t: ``(T,)`` time stamps. mean, var: ``(T,)``; ``var`` is a variance.
    """
    t, mean, var = to_numpy(t), to_numpy(mean), to_numpy(var)
    if np.any(var < 0):
        raise ValueError("var: variances must be non-negative")
    std = np.sqrt(var)
    (line,) = ax.plot(t, mean, label=label, color=color)
    ax.fill_between(
        t, mean - n_std * std, mean + n_std * std, color=line.get_color(), alpha=0.2,
        label=f"{label} ±{n_std:g}σ",
    )


def markdown_table(
    rows: Sequence[Sequence[Any]],
    header: Sequence[str],
    floatfmt: str = ".4g",
    diverged_above: float | None = None,
) -> str:
    """Format rows as a Markdown table (display with ``IPython.display.Markdown``).

    Floats are formatted with ``floatfmt``; everything else with ``str``. Every row must have
    as many cells as ``header``. With ``diverged_above`` (a positive threshold), a float that
    is not finite or whose magnitude exceeds it is written as "diverged" instead of a number
    such as ``inf`` or ``2.05e+11`` (for error metrics of runs that blew up).
    """
    if diverged_above is not None and not (diverged_above > 0 and math.isfinite(diverged_above)):
        raise ValueError(f"diverged_above: expected a positive finite threshold, got {diverged_above!r}")

    def fmt(v: Any) -> str:
        if isinstance(v, (float, np.floating)):
            if diverged_above is not None and not (abs(float(v)) <= diverged_above):
                return "diverged"
            return format(float(v), floatfmt)
        if hasattr(v, "item") and getattr(v, "ndim", 1) == 0:
            return fmt(v.item())
        return str(v)

    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise ValueError(f"rows: row {i} has {len(r)} cells, header has {len(header)}")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- Chapter 2 helpers
__all__ += ["plot_curves", "plot_gaussian_density"]


def plot_curves(
    ax: Any,
    x: Any,
    curves: dict[str, Any],
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    bands: dict[str, tuple[Any, Any]] | None = None,
    marker: str = "o",
    styles: dict[str, dict] | None = None,
) -> None:
    """Plot several named curves ``y(x)`` on one axis, with optional shaded ``(low, high)`` bands.

    Args:
        ax: a matplotlib axis. x: ``(K,)``. curves: name -> ``(K,)`` values.
        bands: name -> ``(low, high)``, each ``(K,)``, drawn in the curve's colour.
        styles: name -> extra keyword arguments for ``ax.plot`` (e.g. ``{"ls": "--"}``).
    """
    x = to_numpy(x)
    for name, y in curves.items():
        y = to_numpy(y)
        if y.shape != x.shape:
            raise ValueError(f"curves: {name!r} has shape {y.shape}, x has {x.shape}")
        kw = {"marker": marker, **((styles or {}).get(name, {}))}
        (line,) = ax.plot(x, y, label=name, **kw)
        if bands and name in bands:
            lo, hi = (to_numpy(b) for b in bands[name])
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend()


def plot_gaussian_density(
    ax: Any, grid: Any, mean: float, var: float, label: str = "", **kwargs: Any
) -> None:
    """Plot the 1-D density of ``N(mean, var)`` on ``grid`` (``var`` is a variance)."""
    if var <= 0:
        raise ValueError(f"var: must be > 0, got {var}")
    g = to_numpy(grid)
    dens = np.exp(-0.5 * (g - mean) ** 2 / var) / np.sqrt(2 * np.pi * var)
    ax.plot(g, dens, label=label, **kwargs)


# ----------------------------------------------------------------------------- Chapter 4 helpers
__all__ += ["plot_rollout"]


def plot_rollout(
    axes: Any,
    t: Any,
    truth: Any,
    preds: dict[str, tuple[Any, Any | None]],
    context_end: float | None = None,
    dim_labels: Sequence[str] | None = None,
    n_std: float = 2.0,
) -> None:
    """Open-loop rollouts against the ground truth, one axis per output dimension (Chapter 4).

    Args:
        axes: a sequence of ``d`` matplotlib axes. t: ``(T,)`` time stamps. truth: ``(T, d)``.
        preds: ``{name: (mean (T, d), var (T, d) or None)}``; a variance adds a ``± n_std`` band.
        context_end: where the observed context ends (drawn as a dashed vertical line).
    """
    t, truth = to_numpy(t), to_numpy(truth)
    if truth.ndim != 2 or truth.shape[0] != t.shape[0]:
        raise ValueError(f"truth: expected shape ({t.shape[0]}, d), got {truth.shape}")
    d = truth.shape[1]
    if len(axes) != d:
        raise ValueError(f"axes: need {d} axes, got {len(axes)}")
    for j, ax in enumerate(axes):
        ax.plot(t, truth[:, j], color="k", lw=1.5, label="ground truth")
        for name, (mean, var) in preds.items():
            mean = to_numpy(mean)
            if mean.shape != truth.shape:
                raise ValueError(f"preds: {name!r} has shape {mean.shape}, truth has {truth.shape}")
            if var is None:
                ax.plot(t, mean[:, j], lw=1.0, label=name)
            else:
                plot_belief(ax, t, mean[:, j], to_numpy(var)[:, j], label=name, n_std=n_std)
        if context_end is not None:
            ax.axvline(context_end, color="gray", ls="--", lw=1)
        if dim_labels is not None:
            ax.set_ylabel(dim_labels[j])
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, ncol=2)


# ----------------------------------------------------------------------------- Chapter 3 helpers
__all__ += ["shade_missing", "plot_image_strip"]


def shade_missing(ax: Any, t: Any, valid: Any, color: str = "0.85", label: str | None = "missing frame") -> None:
    """Shade the time spans where ``valid`` (``(T,)`` bool) is False; each step covers ``t ± Δ/2``."""
    t, valid = to_numpy(t).astype(float), to_numpy(valid).astype(bool)
    if t.shape != valid.shape or t.ndim != 1:
        raise ValueError(f"valid: expected the shape of t {t.shape}, got {valid.shape}")
    half = 0.5 * (float(np.median(np.diff(t))) if t.size > 1 else 1.0)
    first = True
    for i in np.flatnonzero(~valid):
        ax.axvspan(t[i] - half, t[i] + half, color=color, lw=0, zorder=0,
                   label=label if first and label else None)
        first = False


def plot_image_strip(ax: Any, frames: Any, image_shape: Sequence[int], titles: Sequence[str] | None = None,
                     gap: int = 1) -> None:
    """Show flattened grayscale frames ``(n, H*W)`` side by side on one axis (values in [0, 1])."""
    frames = to_numpy(frames)
    H, W = int(image_shape[0]), int(image_shape[1])
    if frames.ndim != 2 or frames.shape[1] != H * W:
        raise ValueError(f"frames: expected shape (n, {H * W}), got {frames.shape}")
    n = frames.shape[0]
    canvas = np.ones((H, n * (W + gap) - gap))
    for i in range(n):
        canvas[:, i * (W + gap): i * (W + gap) + W] = frames[i].reshape(H, W)
    ax.imshow(canvas, cmap="gray", vmin=0.0, vmax=1.0)
    ax.set_yticks([])
    if titles is not None:
        if len(titles) != n:
            raise ValueError(f"titles: need {n} titles, got {len(titles)}")
        ax.set_xticks([i * (W + gap) + W / 2 - 0.5 for i in range(n)])
        ax.set_xticklabels(titles, fontsize=7)
    else:
        ax.set_xticks([])


# ----------------------------------------------------------------------------- Chapter 6 helpers
__all__ += ["mark_windows"]


def mark_windows(ax: Any, start: float, stop: float, width: float, label: str | None = "window boundary",
                 **kwargs: Any) -> None:
    """Draw thin vertical lines at ``start, start + width, ...`` up to ``stop`` (e.g. the boundaries
    of the slow time scale's windows, where the slow level reconfigures the fast one)."""
    if width <= 0:
        raise ValueError(f"width: must be positive, got {width}")
    style = {"color": "tab:purple", "ls": ":", "lw": 0.8, "alpha": 0.7, **kwargs}
    for i, x in enumerate(np.arange(start, stop + 1e-9 * width, width)):
        ax.axvline(x, label=label if i == 0 else None, **style)


# ----------------------------------------------------------------------------- Chapter 5 helpers
__all__ += ["plot_graphical_model", "plot_latent_scatter", "plot_task_over_time"]


def plot_graphical_model(
    ax: Any,
    nodes: dict[str, tuple[float, float, str, str]],
    edges: Sequence[tuple[str, str]],
    radius: float = 0.32,
    plates: Sequence[tuple[float, float, float, float, str]] = (),
) -> None:
    """Draw a small directed graphical model (Bayesian network) with matplotlib.

    Args:
        nodes: name -> ``(x, y, tex_label, kind)`` with ``kind`` ``"latent"`` (white circle),
            ``"observed"`` (shaded circle) or ``"known"`` (small shaded square, e.g. an action).
        edges: ``(parent, child)`` pairs, drawn as arrows between the node borders.
        plates: ``(x0, y0, width, height, label)`` rectangles (e.g. around a context set).
    """
    from matplotlib.patches import Circle, FancyArrowPatch, Rectangle

    for x0, y0, w, h, label in plates:
        ax.add_patch(Rectangle((x0, y0), w, h, fill=False, lw=1, ls="--", ec="0.4"))
        ax.text(x0, y0 + h + 0.05, label, ha="left", va="bottom", fontsize=9, color="0.3")
    for name, (x, y, label, kind) in nodes.items():
        if kind not in ("latent", "observed", "known"):
            raise ValueError(f"nodes: kind of {name!r} must be latent/observed/known, got {kind!r}")
        if kind == "known":
            s = 0.75 * radius
            ax.add_patch(Rectangle((x - s, y - s), 2 * s, 2 * s, fc="0.8", ec="k", lw=1.2, zorder=2))
        else:
            ax.add_patch(Circle((x, y), radius, fc="0.8" if kind == "observed" else "white", ec="k",
                                lw=1.2, zorder=2))
        ax.text(x, y, label, ha="center", va="center", fontsize=11, zorder=3)
    for a, b in edges:
        if a not in nodes or b not in nodes:
            raise ValueError(f"edges: unknown node in edge ({a!r}, {b!r})")
        (xa, ya), (xb, yb) = nodes[a][:2], nodes[b][:2]
        d = np.hypot(xb - xa, yb - ya)
        ua, ub = radius / d, 1 - radius / d
        ax.add_patch(FancyArrowPatch((xa + ua * (xb - xa), ya + ua * (yb - ya)),
                                     (xa + ub * (xb - xa), ya + ub * (yb - ya)),
                                     arrowstyle="-|>", mutation_scale=12, lw=1.2, color="k", zorder=1))
    xs = [v[0] for v in nodes.values()]
    ys = [v[1] for v in nodes.values()]
    xs += [x0 for x0, *_ in plates] + [x0 + w for x0, _, w, *_ in plates]
    ys += [y0 + h + 0.3 for _, y0, _, h, _ in plates]
    ax.set_xlim(min(xs) - 2 * radius, max(xs) + 2 * radius)
    ax.set_ylim(min(ys) - 2 * radius, max(ys) + 2 * radius)
    ax.set_aspect("equal")
    ax.axis("off")


def plot_latent_scatter(ax: Any, xy: Any, values: Any, label: str = "", cmap: str = "viridis",
                        markers: Any = None, **kwargs: Any) -> Any:
    """Scatter a 2-D embedding ``xy: (n, 2)`` coloured by ``values: (n,)`` and add a colorbar.

    ``markers`` (optional ``(n,)`` array of group names) draws each group with its own marker
    (``o``, ``^``, ``s``, ...) on a shared colour scale. Returns the colorbar.
    """
    xy, values = to_numpy(xy), to_numpy(values)
    if xy.ndim != 2 or xy.shape[1] != 2 or values.shape != (xy.shape[0],):
        raise ValueError(f"values: expected xy (n, 2) and values (n,), got {xy.shape} and {values.shape}")
    vmin, vmax = float(values.min()), float(values.max())
    groups = [None] if markers is None else list(dict.fromkeys(np.asarray(markers).tolist()))
    shapes = ["o", "^", "s", "D", "v", "P"]
    sc = None
    for i, g in enumerate(groups):
        sel = np.ones(len(values), bool) if g is None else np.asarray(markers) == g
        sc = ax.scatter(xy[sel, 0], xy[sel, 1], c=values[sel], cmap=cmap, vmin=vmin, vmax=vmax,
                        marker=shapes[i % len(shapes)], label=g, **{"s": 14, "alpha": 0.8, **kwargs})
    cb = ax.figure.colorbar(sc, ax=ax)
    cb.set_label(label)
    if markers is not None:
        ax.legend(fontsize=8)
    return cb


def plot_task_over_time(
    axes: Sequence[Any],
    t_windows: Any,
    latent: Any,
    t: Any,
    truth: Any,
    latent_std: Any = None,
    latent_label: str = "task latent",
    truth_label: str = "ground truth",
) -> None:
    """A latent task summary per window (top) against the ground-truth hidden parameter (bottom).

    Args:
        axes: two matplotlib axes. t_windows: ``(J,)`` window start times; latent: ``(J,)`` one value
            per window, drawn as a step held over the window; latent_std: optional ``(J,)`` band.
        t: ``(T,)`` time stamps; truth: ``(T,)`` the true parameter. Every change of ``truth`` is
            marked by a dotted vertical line in both panels.
    """
    tw, lat, t, truth = to_numpy(t_windows), to_numpy(latent), to_numpy(t), to_numpy(truth)
    if lat.shape != tw.shape or truth.shape != t.shape:
        raise ValueError(f"latent: expected shapes latent {tw.shape} and truth {t.shape}, got {lat.shape}, {truth.shape}")
    if len(axes) != 2:
        raise ValueError(f"axes: need 2 axes, got {len(axes)}")
    step = float(tw[1] - tw[0]) if tw.size > 1 else 1.0
    edges = np.append(tw, tw[-1] + step)
    axes[0].stairs(lat, edges, baseline=None, color="C0", lw=2, label=latent_label)
    if latent_std is not None:
        sd = to_numpy(latent_std)
        axes[0].stairs(lat + 2 * sd, edges, baseline=lat - 2 * sd, fill=True, color="C0", alpha=0.2,
                       label="±2σ")
    axes[1].plot(t, truth, color="C3", lw=2, label=truth_label)
    for s in t[1:][np.diff(truth) != 0]:
        for ax in axes:
            ax.axvline(s, color="k", ls=":", lw=1)
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axes[0].set_ylabel(latent_label)
    axes[1].set_ylabel(truth_label)
    axes[1].set_xlabel("time [s]")


# ----------------------------------------------------------------------------- Chapter 1 helpers
__all__ += ["plot_filter_1d"]


def plot_filter_1d(
    ax: Any,
    t: Any,
    obs: Any,
    valid: Any,
    beliefs: dict[str, tuple[Any, Any]],
    truth: Any | None = None,
    n_std: float = 2.0,
    shade: bool = True,
) -> None:
    """One coordinate of a filtering problem: observations, optional truth, beliefs with bands.

    Args:
        ax: a matplotlib axis. t: ``(T,)`` time stamps. obs: ``(T,)`` observations (only the
            entries where ``valid`` (``(T,)`` bool) is True are drawn). truth: ``(T,)`` or None.
        beliefs: ``{label: (mean (T,), var (T,))}``, each drawn as a line with a ``± n_std`` band.
        shade: shade the steps with a missing observation.
    """
    t, obs, valid = to_numpy(t), to_numpy(obs), to_numpy(valid).astype(bool)
    if obs.shape != t.shape or valid.shape != t.shape:
        raise ValueError(f"obs: expected obs and valid of shape {t.shape}, got {obs.shape} and {valid.shape}")
    if shade and not valid.all():
        shade_missing(ax, t, valid, label="missing observation")
    if truth is not None:
        ax.plot(t, to_numpy(truth), color="k", lw=1.2, label="true value")
    ax.plot(t[valid], obs[valid], ".", color="0.35", ms=4, label="observation")
    for name, (mean, var) in beliefs.items():
        plot_belief(ax, t, mean, var, label=name, n_std=n_std)
    ax.grid(alpha=0.3)


# ----------------------------------------------------------------------------- Book-wide helpers
__all__ += ["source_without_docstrings", "show_source", "use_book_figures"]


def source_without_docstrings(obj: Any) -> str:
    """The source code of a function or class with every docstring removed.

    Comments, blank lines and the code itself are kept exactly as written; only the string
    literals that are the first statement of the object (and of each function or class nested
    in it) are dropped, so the printed code is what runs and nothing else. A body that consisted
    of a docstring alone becomes ``...``.

    Args:
        obj: a function, method or class whose source ``inspect.getsource`` can find.
    Returns:
        The dedented source text, ending with a newline.
    """
    import ast
    import inspect
    import textwrap

    try:
        source = textwrap.dedent(inspect.getsource(obj))
    except (TypeError, OSError) as exc:
        raise ValueError(f"obj: no source code available for {obj!r} ({exc})") from None
    lines = source.splitlines(keepends=True)
    drop: set[int] = set()   # 0-based line numbers to remove
    stub: dict[int, str] = {}  # a line to put in place of a docstring that was the whole body
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        first = node.body[0]
        if not (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)):
            continue
        start, end = first.lineno - 1, first.end_lineno   # the docstring's lines [start, end)
        head = lines[start][: first.col_offset]
        if lines[start][: first.col_offset].strip() or lines[end - 1][first.end_col_offset:].strip():
            continue   # the docstring shares a line with other code; leave it in place
        drop.update(range(start, end))
        if len(node.body) == 1:
            stub[start] = head + "...\n"
    out = []
    for i, line in enumerate(lines):
        if i in stub:
            out.append(stub[i])
        elif i not in drop:
            out.append(line)
    text = "".join(out)
    return text if text.endswith("\n") else text + "\n"


def show_source(*objs: Any) -> Any:
    """Display the source of functions or classes, without their docstrings, as a highlighted
    Python block (an ``IPython.display.Markdown`` object: the book and JupyterLab render it as
    code). Used where the package's code *is* the lesson, e.g. the Kalman update of chapter 1.

    Args:
        objs: one or more functions or classes (see :func:`source_without_docstrings`).
    Returns:
        The ``Markdown`` object (shown when it is a cell's last expression).
    """
    from IPython.display import Markdown

    if not objs:
        raise ValueError("objs: give at least one function or class")
    body = "\n\n".join(source_without_docstrings(obj).rstrip("\n") for obj in objs)
    return Markdown(f"```python\n{body}\n```")


def use_book_figures() -> None:
    """Render this notebook's matplotlib figures at twice the pixel density ("retina" PNGs).

    Each inline figure is saved at 2x its ``dpi`` and tagged with its 1x width and height, so a
    figure keeps its size on the page and in JupyterLab but stays sharp on high-resolution
    screens and when zoomed. Call once, in a chapter's import cell. Outside an IPython shell
    (e.g. plain ``python``) nothing is changed.
    """
    from IPython import get_ipython

    if get_ipython() is None:
        return
    from matplotlib_inline.backend_inline import set_matplotlib_formats

    set_matplotlib_formats("retina")


__all__ += ["best_so_far", "plot_learning_curves"]


def best_so_far(curve: Sequence[Mapping[str, float]], grid: Any, key: str = "valid", x: str = "cpu_s") -> np.ndarray:
    """The lowest ``key`` recorded at ``x <= g`` for every ``g`` of ``grid`` (``nan`` before the
    first record): the validation RMSE a run selected by keep-best would have had with a budget
    ``g``. ``curve`` is a learning curve of :func:`pgm_wm.experiments.runner.train_model`."""
    xs = np.array([e[x] for e in curve], dtype=np.float64)
    vs = np.array([e[key] for e in curve], dtype=np.float64)
    order = np.argsort(xs, kind="stable")
    xs, best = xs[order], np.minimum.accumulate(np.where(np.isfinite(vs[order]), vs[order], np.inf))
    idx = np.searchsorted(xs, np.asarray(grid, dtype=np.float64), side="right") - 1
    out = np.where(idx >= 0, best[np.clip(idx, 0, None)], np.nan)
    return np.where(np.isinf(out), np.nan, out)


def plot_learning_curves(ax: Any, results: Mapping[str, Any], models: Sequence[str] | None = None,
                         references: Sequence[str] | None = None, x: str = "cpu_s", n_grid: int = 200) -> None:
    """Validation RMSE (normalized units, lowest so far) against CPU seconds (``x="cpu_s"``) or
    optimizer steps (``x="step"``) for the trained ``models`` of a results file: the median over
    seeds as a line, the range over seeds as a band, each model's line ending where its shortest
    run ends (a model that took fewer steps in the same budget is not drawn flat beyond them); the
    ``references`` (rows fitted in closed form, the physics oracle) as horizontal dashed lines at
    their validation RMSE. Log-log axes."""
    import warnings

    entries = results["models"]
    if models is None:
        models = [n for n, e in entries.items() if e.get("trained", True)]
    if references is None:
        references = [n for n, e in entries.items() if not e.get("trained", True)]
    top = max(max(e[x] for e in r["curve"]) for n in models for r in entries[n]["runs"])
    low = min(min(e[x] for e in r["curve"]) for n in models for r in entries[n]["runs"])
    grid = np.geomspace(max(low, 1e-3), top, n_grid)
    for n in models:
        runs = entries[n]["runs"]
        g = grid[grid <= min(r["curve"][-1][x] for r in runs)]
        curves = np.stack([best_so_far(r["curve"], g, x=x) for r in runs])
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)       # grid points before a run's first record
            med = np.nanmedian(curves, 0)
            lo, hi = np.nanmin(curves, 0), np.nanmax(curves, 0)
        (line,) = ax.plot(g, med, lw=1.6, label=n)
        ax.fill_between(g, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
    styles = iter([(0, (4, 2)), (0, (1, 1.5)), (0, (6, 2, 1, 2)), (0, (2, 2))] * 3)
    for n in references:
        v = entries[n]["runs"][0].get("best_valid") if entries[n].get("runs") else None
        if v is not None and np.isfinite(v):
            ax.axhline(v, color="0.35", lw=1.1, ls=next(styles), label=f"{n} (reference)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training CPU seconds" if x == "cpu_s" else "optimizer steps")
    ax.set_ylabel("validation RMSE, lowest so far (normalized)")
    ax.grid(alpha=0.3, which="both")


__all__ += ["plot_horizon_errors"]


def plot_horizon_errors(ax: Any, results: Mapping[str, Any], models: Sequence[str] | None = None, *,
                        summary: Mapping[str, Any], logy: bool = True) -> None:
    """RMSE against the prediction horizon ``k`` for ``models`` of a multi-seed results file (all
    by default): the point estimate as a line, its 95 % interval over seeds and test windows as a
    band, both read from ``summary`` (what :func:`pgm_wm.experiments.results.summarize` returns for
    ``results``), in the file's units. Reference rows are drawn dashed and without a band."""
    models = list(results["models"]) if models is None else list(models)
    unknown = [n for n in models if n not in summary]
    if unknown:
        raise ValueError(f"models: not in the results: {unknown}")
    k = np.asarray(results["horizons"], dtype=float)
    curves, bands, styles = {}, {}, {}
    for n in models:
        ivs = summary[n]["rmse"]
        curves[n] = np.array([iv.point for iv in ivs])
        if results["models"][n].get("trained", True):
            bands[n] = (np.array([iv.lo for iv in ivs]), np.array([iv.hi for iv in ivs]))
        else:
            styles[n] = {"ls": "--", "marker": "."}
    units = f" ({results['units']})" if results.get("units") else ""
    plot_curves(ax, k, curves, xlabel="prediction horizon k (steps)", ylabel=f"test RMSE{units}", logy=logy,
                bands=bands, styles=styles)

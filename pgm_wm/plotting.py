"""Plot and table helpers shared by the chapter notebooks.

The helpers here are presentation only: they never compute a model quantity themselves.
Chapters add their own helpers at the end of this file (one function per plot kind).
"""

from __future__ import annotations

from typing import Any, Sequence

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
    rows: Sequence[Sequence[Any]], header: Sequence[str], floatfmt: str = ".4g"
) -> str:
    """Format rows as a Markdown table (display with ``IPython.display.Markdown``).

    Floats are formatted with ``floatfmt``; everything else with ``str``. Every row must have
    as many cells as ``header``.
    """
    def fmt(v: Any) -> str:
        if isinstance(v, (float, np.floating)):
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


# ---------------------------------------------------------------------------------------
# Diagrams of the book's models (drawn by code, matplotlib only). Each returns the figure;
# pass ``ax`` to draw into an existing axis instead. Presentation only: no model quantity
# is computed here except the 1-D Gaussian densities of ``plot_gain_as_weighted_average``.
# ---------------------------------------------------------------------------------------


def _diagram_axes(ax: Any, figsize: tuple[float, float]) -> tuple[Any, Any]:
    """Return ``(fig, ax)``: a new figure of ``figsize`` if ``ax`` is None."""
    if ax is None:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=figsize)
    else:
        fig = ax.figure
    return fig, ax


def _diagram_box(ax: Any, x: float, y: float, text: str, w: float = 1.9, h: float = 0.8,
                 fc: str = "white", fontsize: float = 10) -> None:
    """A rounded box of width ``w`` and height ``h`` centred at ``(x, y)`` holding ``text``."""
    from matplotlib.patches import FancyBboxPatch

    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.02,rounding_size=0.12",
                                fc=fc, ec="k", lw=1.2, zorder=2))
    ax.text(x, y, text, ha="center", va="center", fontsize=fontsize, zorder=3)


def _diagram_arrow(ax: Any, p: tuple[float, float], q: tuple[float, float], text: str = "",
                   rad: float = 0.0, color: str = "k", ls: str = "-", fontsize: float = 9,
                   text_offset: tuple[float, float] = (0.0, 0.18)) -> None:
    """An arrow from ``p`` to ``q`` (optionally curved by ``rad``) with a label at its middle."""
    from matplotlib.patches import FancyArrowPatch

    ax.add_patch(FancyArrowPatch(p, q, arrowstyle="-|>", mutation_scale=13, lw=1.3, color=color,
                                 ls=ls, connectionstyle=f"arc3,rad={rad}", zorder=1))
    if text:
        ax.text((p[0] + q[0]) / 2 + text_offset[0], (p[1] + q[1]) / 2 + text_offset[1], text,
                ha="center", va="bottom", fontsize=fontsize, color=color, zorder=3)


def plot_rkn_cell(ax: Any | None = None) -> Any:
    """Diagram of one step of the Recurrent Kalman Network (chapter 3).

    The encoder turns the raw observation :math:`o_t` into a latent observation
    :math:`w_t` with variance :math:`\\sigma^{obs}_t`; the factorized Kalman update
    (Eq. ``rkn-update``) combines it with the prior belief; the decoder maps the posterior
    to a predicted observation with a variance; the locally linear predict step turns the
    posterior into the prior of the next step, which is the recurrence.

    Args:
        ax: a matplotlib axis to draw into, or None for a new figure.
    Returns:
        The matplotlib figure.
    """
    fig, ax = _diagram_axes(ax, (9.5, 4.2))
    blue, green, grey = "#dbe8f7", "#e2f2dc", "#f2f2f2"
    _diagram_box(ax, 0.0, 0.0, "observation\n$o_t$", w=1.6, fc=grey)
    _diagram_box(ax, 2.6, 0.0, "encoder\n$(w_t, \\sigma^{obs}_t)$", w=2.0, fc=green)
    _diagram_box(ax, 5.5, 0.0, "update\n(condition)", w=1.9, fc=blue)
    _diagram_box(ax, 8.4, 0.0, "decoder\n$(\\hat o_t, \\hat\\sigma_t)$", w=2.0, fc=green)
    _diagram_box(ax, 5.5, 2.3, "predict (marginalize)\n$A_t$ locally linear, $+Q$", w=3.2, fc=blue)
    _diagram_box(ax, 5.5, -2.1, "belief  $\\mu^{+}_t$, $(\\sigma^{u+}_t, \\sigma^{l+}_t, \\sigma^{s+}_t)$",
                 w=4.4, h=0.6, fc="white", fontsize=9)
    _diagram_arrow(ax, (0.8, 0.0), (1.6, 0.0))
    _diagram_arrow(ax, (3.6, 0.0), (4.55, 0.0), "$w_t, \\sigma^{obs}_t$")
    _diagram_arrow(ax, (6.45, 0.0), (7.4, 0.0), "")
    _diagram_arrow(ax, (5.5, -0.4), (5.5, -1.8))
    _diagram_arrow(ax, (6.3, 0.4), (6.3, 1.9), "", color="k")
    ax.text(6.4, 1.15, "posterior $z^{+}_t$", fontsize=9, ha="left", va="center")
    _diagram_arrow(ax, (3.9, 2.3), (4.7, 0.4), "", rad=0.35, color="#b03030", ls="--")
    ax.text(3.35, 1.55, "prior $z^{-}_{t+1}$\n(used at step $t+1$)", fontsize=9, ha="center",
            va="center", color="#b03030")
    ax.text(9.4, 0.75, "loss: NLL of $o_{t}$\nunder $\\mathcal{N}(\\hat o_t, \\hat\\sigma_t)$",
            fontsize=8.5, ha="center", va="bottom", color="0.3")
    ax.text(5.5, 3.05, "the only recurrence: the belief", fontsize=9, ha="center", color="0.3")
    ax.set_xlim(-1.0, 10.6)
    ax.set_ylim(-2.7, 3.4)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("One RKN step: encoder $\\to$ update $\\to$ decoder, and predict to the next step",
                 fontsize=10)
    return fig


def plot_factorized_covariance(m: int = 4, ax: Any | None = None) -> Any:
    """Picture of the factorized covariance of chapter 3 (Eq. ``rkn-cov``).

    Draws the :math:`2m \\times 2m` matrix
    :math:`\\Sigma = [[\\diag(\\sigma^u), \\diag(\\sigma^s)], [\\diag(\\sigma^s), \\diag(\\sigma^l)]]`
    with the entries each of the three vectors occupies coloured and every entry that is
    always zero left blank: only :math:`3m` numbers are stored instead of
    :math:`m(2m+1)`.

    Args:
        m: size of each half of the state (``latent_obs_dim``); at least 1.
        ax: a matplotlib axis to draw into, or None for a new figure.
    Returns:
        The matplotlib figure.
    """
    if not isinstance(m, (int, np.integer)) or m < 1:
        raise ValueError(f"m: must be a positive integer, got {m!r}")
    from matplotlib.patches import Rectangle

    fig, ax = _diagram_axes(ax, (5.2, 5.2))
    colors = {"u": "#4c72b0", "l": "#55a868", "s": "#dd8452"}
    n = 2 * m
    for i in range(n):
        for j in range(n):
            kind = None
            if i == j:
                kind = "u" if i < m else "l"
            elif abs(i - j) == m:
                kind = "s"
            ax.add_patch(Rectangle((j, n - 1 - i), 1, 1, fc=colors[kind] if kind else "white",
                                   ec="0.75", lw=0.8, alpha=0.85 if kind else 1.0))
            if kind and m <= 6:
                ax.text(j + 0.5, n - 0.5 - i, f"$\\sigma^{{{kind}}}_{{{(i % m) + 1}}}$", ha="center",
                        va="center", fontsize=9 if m <= 4 else 7, color="white")
    ax.plot([m, m], [0, n], color="k", lw=1.5)
    ax.plot([0, n], [m, m], color="k", lw=1.5)
    ax.add_patch(Rectangle((0, 0), n, n, fill=False, ec="k", lw=1.5))
    labels = [("$\\operatorname{diag}(\\sigma^u)$", m / 2, n + 0.35), ("$\\operatorname{diag}(\\sigma^s)$", m + m / 2, n + 0.35)]
    for text, x, y in labels:
        ax.text(x, y, text, ha="center", va="bottom", fontsize=10)
    ax.text(-0.3, m + m / 2, "upper $z^u$", rotation=90, ha="right", va="center", fontsize=10)
    ax.text(-0.3, m / 2, "lower $z^l$", rotation=90, ha="right", va="center", fontsize=10)
    ax.text(m / 2, -0.35, "$\\operatorname{diag}(\\sigma^s)$", ha="center", va="top", fontsize=10)
    ax.text(m + m / 2, -0.35, "$\\operatorname{diag}(\\sigma^l)$", ha="center", va="top", fontsize=10)
    ax.set_xlim(-1.2, n + 0.3)
    ax.set_ylim(-1.2, n + 1.0)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(f"$\\Sigma$ of a factorized belief, $m={m}$: {3 * m} stored numbers "
                 f"instead of {m * (2 * m + 1)}", fontsize=10)
    return fig


def plot_mts3_graphical_model(steps: int = 3, ax: Any | None = None) -> Any:
    """Graphical model of the two-level MTS3 (chapter 6) over two windows.

    Top: the slow clock :math:`k`, one task state :math:`l_k` per window of :math:`H` fast
    steps, driven by the abstract action :math:`\\alpha_k` (aggregated from the window's
    actions) and updated by the set of abstract observations :math:`\\beta_{k,1:H}`. Bottom:
    the fast clock :math:`t`, states :math:`z_{k,t}` with observations and actions. The
    dashed arrows are the prior coupling: window :math:`k`'s fast steps are conditioned on
    the *prior* :math:`p(l_k \\mid \\beta_{1:k-1}, \\alpha_{1:k})`, never on a belief that has
    seen window :math:`k`'s own observations.

    Args:
        steps: fast steps drawn per window (the window length :math:`H`), 2 to 5.
        ax: a matplotlib axis to draw into, or None for a new figure.
    Returns:
        The matplotlib figure.
    """
    if not isinstance(steps, (int, np.integer)) or not 2 <= steps <= 5:
        raise ValueError(f"steps: must be an integer from 2 to 5, got {steps!r}")
    from matplotlib.patches import Circle, Rectangle

    fig, ax = _diagram_axes(ax, (11.0, 6.6))
    r = 0.36
    dx = 1.35
    width = steps * dx + 0.9
    nodes: dict[str, tuple[float, float]] = {}

    def node(name: str, x: float, y: float, label: str, kind: str = "latent") -> None:
        nodes[name] = (x, y)
        if kind == "known":
            ax.add_patch(Rectangle((x - 0.8 * r, y - 0.8 * r), 1.6 * r, 1.6 * r, fc="0.82", ec="k",
                                   lw=1.1, zorder=2))
        else:
            ax.add_patch(Circle((x, y), r, fc="0.82" if kind == "observed" else "white", ec="k",
                                lw=1.2, zorder=2))
        ax.text(x, y, label, ha="center", va="center", fontsize=11 if len(label) <= 10 else 8.5, zorder=3)

    def edge(a: str, b: str, color: str = "k", ls: str = "-", rad: float = 0.0) -> None:
        (xa, ya), (xb, yb) = nodes[a], nodes[b]
        d = float(np.hypot(xb - xa, yb - ya))
        pa = (xa + r * (xb - xa) / d, ya + r * (yb - ya) / d)
        pb = (xb - r * (xb - xa) / d, yb - r * (yb - ya) / d)
        _diagram_arrow(ax, pa, pb, color=color, ls=ls, rad=rad)

    y_alpha, y_l, y_beta, y_z, y_o, y_a = 5.2, 3.9, 5.2, 1.6, 0.25, 2.9
    for k, name in enumerate(("k", "k+1")):
        x0 = k * (width + 0.8)
        xl = x0 + width / 2
        node(f"l{k}", xl, y_l, f"$l_{{{name}}}$")
        node(f"alpha{k}", xl - 1.0, y_alpha, f"$\\alpha_{{{name}}}$", "known")
        node(f"beta{k}", xl + 1.2, y_beta, f"$\\beta_{{{name},t}}$", "observed")
        ax.text(xl + 1.2 + 1.3 * r, y_beta, "set of $H$", fontsize=8.5, ha="left", va="center",
                color="0.35")
        edge(f"alpha{k}", f"l{k}")
        edge(f"l{k}", f"beta{k}")
        ax.add_patch(Rectangle((x0, -0.35), width, 3.75, fill=False, ls="--", ec="0.55", lw=1.0))
        ax.text(x0 + 0.08, 3.45, f"window {name}: $H$ fast steps", fontsize=8.5, color="0.35",
                ha="left", va="bottom")
        for t in range(steps):
            xt = x0 + 0.75 + t * dx
            tl = f"{t + 1}" if t < steps - 1 else "H"
            node(f"z{k}{t}", xt, y_z, f"$z_{{{name},{tl}}}$")
            node(f"o{k}{t}", xt, y_o, f"$o_{{{name},{tl}}}$", "observed")
            edge(f"z{k}{t}", f"o{k}{t}")
            edge(f"l{k}", f"z{k}{t}", color="#b03030", ls="--")
            if t > 0:
                node(f"a{k}{t}", xt - dx / 2, y_a, f"$a$", "known")
                edge(f"a{k}{t}", f"z{k}{t}")
                edge(f"z{k}{t - 1}", f"z{k}{t}")
    edge("l0", "l1")
    edge(f"z0{steps - 1}", "z10")
    ax.text((nodes["l0"][0] + nodes["l1"][0]) / 2, y_l + 0.25, "slow clock $k$: $X l_{k} + Y\\alpha_{k+1}$",
            ha="center", va="bottom", fontsize=9)
    ax.text((nodes[f"z0{steps - 1}"][0] + nodes["z10"][0]) / 2, y_z + 0.12, "fast clock $t$",
            ha="center", va="bottom", fontsize=9)
    ax.text(2 * width + 0.8, -0.9,
            "dashed red: the fast steps of window $k$ use the slow prior $p(l_k\\mid\\beta_{1:k-1},\\alpha_{1:k})$;\n"
            "$\\beta_{k,1:H}$ then updates $l_k$ as a set, and the posterior is predicted to $l_{k+1}$",
            ha="right", va="top", fontsize=8.5, color="0.25")
    ax.set_xlim(-0.3, 2 * width + 1.1)
    ax.set_ylim(-1.8, 5.9)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("MTS3: a slow task SSM (top) that reconfigures a fast SSM (bottom), window by window",
                 fontsize=10)
    return fig


def plot_gain_as_weighted_average(prior_mean: float = 0.0, prior_var: float = 1.0,
                                  obs: float = 2.0, obs_var: float = 0.5,
                                  ax: Any | None = None) -> Any:
    """The 1-D Kalman update as a precision-weighted average (chapter 1, Eq. ``kf-update``).

    With :math:`H = 1` the gain is :math:`K = \\sigma^2_- / (\\sigma^2_- + r)`, and the
    posterior mean :math:`\\mu^+ = (1-K)\\mu^- + K y` is the average of the prior mean and the
    observation weighted by their precisions :math:`1/\\sigma^2_-` and :math:`1/r`; the
    posterior precision is their sum. The plot shows the three densities and the weights.

    Args:
        prior_mean, prior_var: the prior :math:`\\mathcal{N}(\\mu^-, \\sigma^2_-)`; ``prior_var > 0``.
        obs, obs_var: the observation :math:`y` and its noise variance :math:`r > 0`.
        ax: a matplotlib axis to draw into, or None for a new figure.
    Returns:
        The matplotlib figure.
    """
    for name, value in (("prior_var", prior_var), ("obs_var", obs_var)):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{name}: must be a positive finite variance, got {value!r}")
    fig, ax = _diagram_axes(ax, (8.0, 4.2))
    gain = prior_var / (prior_var + obs_var)
    post_mean = (1 - gain) * prior_mean + gain * obs
    post_var = 1.0 / (1.0 / prior_var + 1.0 / obs_var)
    spread = 3.5 * np.sqrt(max(prior_var, obs_var))
    x = np.linspace(min(prior_mean, obs) - spread, max(prior_mean, obs) + spread, 600)

    def density(mu: float, var: float) -> np.ndarray:
        return np.exp(-0.5 * (x - mu) ** 2 / var) / np.sqrt(2 * np.pi * var)

    curves = [("prior $\\mathcal{N}(\\mu^-, \\sigma^2_-)$", prior_mean, prior_var, "#4c72b0", "-"),
              ("likelihood of $y$, $\\mathcal{N}(y, r)$", obs, obs_var, "0.35", "--"),
              ("posterior $\\mathcal{N}(\\mu^+, \\sigma^2_+)$", post_mean, post_var, "#c44e52", "-")]
    for label, mu, var, color, ls in curves:
        ax.plot(x, density(mu, var), color=color, ls=ls, lw=2, label=label)
        ax.axvline(mu, color=color, ls=":", lw=1)
    top = density(post_mean, post_var).max()
    y_bar = 1.12 * top
    ax.annotate("", xy=(prior_mean, y_bar), xytext=(obs, y_bar),
                arrowprops=dict(arrowstyle="<->", color="0.3", lw=1))
    ax.plot([post_mean], [y_bar], "v", color="#c44e52", ms=8)
    ax.text(post_mean, y_bar * 1.04,
            f"$\\mu^+ = (1-K)\\,\\mu^- + K\\,y$,  $K = \\frac{{1/r}}{{1/\\sigma^2_- + 1/r}} = {gain:.2f}$",
            ha="center", va="bottom", fontsize=10)
    ax.text(0.01, 0.97, f"precisions add: $1/\\sigma^2_+ = 1/\\sigma^2_- + 1/r$ "
            f"$= {1 / prior_var:.2f} + {1 / obs_var:.2f} = {1 / post_var:.2f}$",
            transform=ax.transAxes, ha="left", va="top", fontsize=9, color="0.25")
    ax.set_ylim(0, y_bar * 1.35)
    ax.set_xlabel("state $z$")
    ax.set_ylabel("density")
    ax.legend(loc="center right", fontsize=8.5, frameon=False)
    ax.set_title("The Kalman update in 1-D: a precision-weighted average of prior and observation",
                 fontsize=10)
    return fig


__all__ += ["plot_rkn_cell", "plot_factorized_covariance", "plot_mts3_graphical_model",
            "plot_gain_as_weighted_average"]

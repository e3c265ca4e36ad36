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

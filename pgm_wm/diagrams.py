r"""Diagrams of the book's models, drawn by code (matplotlib only).

Each function returns the figure; pass ``ax`` to draw into an existing axis instead.
Presentation only: no model quantity is computed here except the 1-D Gaussian densities of
:func:`plot_gain_as_weighted_average`.

* :func:`plot_gain_as_weighted_average` — Chapter 1: the Kalman update in 1-D as a
  precision-weighted average of prior and observation;
* :func:`plot_rkn_cell` — Chapter 3: encoder → update → predict → decoder;
* :func:`plot_factorized_covariance` — Chapter 3: the vᵘ, vˡ, vˢ blocks of Σ;
* :func:`plot_mts3_graphical_model` — Chapter 6: the two clocks, the β and α sets and the
  prior coupling.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["plot_rkn_cell", "plot_factorized_covariance", "plot_mts3_graphical_model",
           "plot_gain_as_weighted_average"]


def _diagram_axes(ax: Any, figsize: tuple[float, float]) -> tuple[Any, Any]:
    """Return ``(fig, ax)``: a new figure of ``figsize`` if ``ax`` is None."""
    if ax is None:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=figsize)
    else:
        fig = ax.figure
    return fig, ax


def _finish_diagram(ax: Any, xlim: tuple[float, float], ylim: tuple[float, float], title: str) -> None:
    """The common frame of the box-and-arrow diagrams: limits, equal aspect, no axes, a title."""
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, fontsize=10)


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
    :math:`w_t` with variance :math:`v^{obs}_t`; the factorized Kalman update
    (Eq. ``rkn-update``) combines it with the prior belief; the decoder maps the posterior
    to a predicted observation with a variance; the locally linear predict step turns the
    posterior into the prior of the next step, which is the recurrence.

    Args:
        ax: a matplotlib axis to draw into, or None for a new figure.
    Returns:
        The matplotlib figure.
    """
    fig, ax = _diagram_axes(ax, (9.5, 4.6))
    blue, green, grey = "#dbe8f7", "#e2f2dc", "#f2f2f2"
    _diagram_box(ax, 0.0, 0.0, "observation\n$o_t$", w=1.6, fc=grey)
    _diagram_box(ax, 2.7, 0.0, "encoder\n$(w_t, v^{obs}_t)$", w=2.0, fc=green)
    _diagram_box(ax, 6.2, 0.0, "update\n(condition)", w=1.9, fc=blue)
    _diagram_box(ax, 9.5, 0.0, "decoder\n$(\\hat o_t, \\hat\\sigma^2_t)$", w=2.0, fc=green)
    _diagram_box(ax, 6.2, 2.5, "predict (marginalize)\n$A_t$ locally linear, $+Q$", w=3.2, fc=blue)
    _diagram_box(ax, 6.2, -2.1, "belief  $\\mu^{+}_t$, $(v^{u+}_t, v^{l+}_t, v^{s+}_t)$",
                 w=4.4, h=0.6, fc="white", fontsize=9)
    _diagram_arrow(ax, (0.8, 0.0), (1.7, 0.0))
    _diagram_arrow(ax, (3.7, 0.0), (5.25, 0.0), "$w_t, v^{obs}_t$", text_offset=(0.0, 0.08))
    _diagram_arrow(ax, (7.15, 0.0), (8.5, 0.0))
    _diagram_arrow(ax, (6.2, -0.4), (6.2, -1.8))
    # the loop: posterior up into the predict step (right), prior of the next step back (left)
    _diagram_arrow(ax, (6.75, 0.4), (6.75, 2.1))
    ax.text(6.9, 1.25, "posterior $z^{+}_t$", fontsize=9, ha="left", va="center")
    _diagram_arrow(ax, (5.65, 2.1), (5.65, 0.4), color="#b03030", ls="--")
    ax.text(5.5, 1.25, "prior $z^{-}_{t+1}$\n(used at step $t+1$)", fontsize=9, ha="right",
            va="center", color="#b03030")
    ax.text(9.5, -0.55, "loss: NLL of $o_{t}$\nunder $\\mathcal{N}(\\hat o_t, \\hat\\sigma^2_t)$",
            fontsize=8.5, ha="center", va="top", color="0.3")
    ax.text(6.2, 3.2, "the only recurrence: the belief", fontsize=9, ha="center", color="0.3")
    _finish_diagram(ax, (-1.0, 10.8), (-2.6, 3.6),
                    "One RKN step: encoder $\\to$ update $\\to$ decoder, and predict to the next step")
    return fig


def plot_factorized_covariance(m: int = 4, ax: Any | None = None) -> Any:
    """Picture of the factorized covariance of chapter 3 (Eq. ``rkn-cov``).

    Draws the :math:`2m \\times 2m` matrix
    :math:`\\Sigma = [[\\diag(v^u), \\diag(v^s)], [\\diag(v^s), \\diag(v^l)]]`
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
                ax.text(j + 0.5, n - 0.5 - i, f"$v^{{{kind}}}_{{{(i % m) + 1}}}$", ha="center",
                        va="center", fontsize=9 if m <= 4 else 7, color="white")
    ax.plot([m, m], [0, n], color="k", lw=1.5)
    ax.plot([0, n], [m, m], color="k", lw=1.5)
    ax.add_patch(Rectangle((0, 0), n, n, fill=False, ec="k", lw=1.5))
    labels = [("$\\operatorname{diag}(v^u)$", m / 2, n + 0.35), ("$\\operatorname{diag}(v^s)$", m + m / 2, n + 0.35)]
    for text, x, y in labels:
        ax.text(x, y, text, ha="center", va="bottom", fontsize=10)
    ax.text(-0.3, m + m / 2, "upper $z^u$", rotation=90, ha="right", va="center", fontsize=10)
    ax.text(-0.3, m / 2, "lower $z^l$", rotation=90, ha="right", va="center", fontsize=10)
    ax.text(m / 2, -0.35, "$\\operatorname{diag}(v^s)$", ha="center", va="top", fontsize=10)
    ax.text(m + m / 2, -0.35, "$\\operatorname{diag}(v^l)$", ha="center", va="top", fontsize=10)
    _finish_diagram(ax, (-1.2, n + 0.3), (-1.2, n + 1.0),
                    f"$\\Sigma$ of a factorized belief, $m={m}$: {3 * m} stored numbers instead of {m * (2 * m + 1)}")
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

    fig, ax = _diagram_axes(ax, (11.0, 6.4))
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

    # rows: abstract action/observation, task, fast states, actions (between the state columns,
    # below the fast chain, so that no edge from the task crosses them), observations
    y_alpha, y_l, y_beta, y_z, y_a, y_o = 5.4, 4.1, 5.4, 1.9, 0.95, 0.0
    box_lo, box_hi = -0.75, 2.75
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
        ax.add_patch(Rectangle((x0, box_lo), width, box_hi - box_lo, fill=False, ls="--", ec="0.55", lw=1.0))
        ax.text(x0 + 0.08, box_lo + 0.06, f"window {name}: $H$ fast steps", fontsize=8.5, color="0.35",
                ha="left", va="bottom")
        for t in range(steps):
            xt = x0 + 0.75 + t * dx
            tl = f"{t + 1}" if t < steps - 1 else "H"
            node(f"z{k}{t}", xt, y_z, f"$z_{{{name},{tl}}}$")
            node(f"o{k}{t}", xt, y_o, f"$o_{{{name},{tl}}}$", "observed")
            edge(f"z{k}{t}", f"o{k}{t}")
            edge(f"l{k}", f"z{k}{t}", color="#b03030", ls="--")
            if t > 0:
                node(f"a{k}{t}", xt - dx / 2, y_a, "$a$", "known")
                edge(f"a{k}{t}", f"z{k}{t}")
                edge(f"z{k}{t - 1}", f"z{k}{t}")
    edge("l0", "l1")
    edge(f"z0{steps - 1}", "z10")
    ax.text((nodes["l0"][0] + nodes["l1"][0]) / 2, y_l + 0.25, "slow clock $k$: $X l_{k} + Y\\alpha_{k+1}$",
            ha="center", va="bottom", fontsize=9)
    ax.text((nodes[f"z0{steps - 1}"][0] + nodes["z10"][0]) / 2, y_z + 0.12, "fast clock $t$",
            ha="center", va="bottom", fontsize=9)
    ax.text(2 * width + 0.8, box_lo - 0.2,
            "dashed red: the fast steps of window $k$ use the slow prior $p(l_k\\mid\\beta_{1:k-1},\\alpha_{1:k})$;\n"
            "$\\beta_{k,1:H}$ then updates $l_k$ as a set, and the posterior is predicted to $l_{k+1}$",
            ha="right", va="top", fontsize=8.5, color="0.25")
    _finish_diagram(ax, (-0.3, 2 * width + 1.1), (-2.1, 6.1),
                    "MTS3: a slow task SSM (top) that reconfigures a fast SSM (bottom), window by window")
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

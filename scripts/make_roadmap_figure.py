#!/usr/bin/env python
"""Draw the book's roadmap figure: the seven chapters' models as small graphical models.

Regenerate it (deterministically; matplotlib only, no data, no training) with::

    cd /work/main && .venv/bin/python scripts/make_roadmap_figure.py

which writes ``book/images/roadmap.png`` (shown in ``book/intro.md``, figure ``fig-roadmap``).
The figure is 8 inches wide, saved at 200 dpi: 1600 px, sharp when the page shows it at
about 800 px.

Each panel is one chapter's model, drawn with the conventions of the chapters' own graphical
models (``pgm_wm.plotting.plot_graphical_model``): white circle = hidden, grey circle =
observed, grey square = known input. What the chapter adds to the model before it is drawn
in colour. ``plot_graphical_model`` draws every node and edge in black, so it cannot mark
the new part; this script uses small helpers of its own that follow the same conventions.
From Chapter 4 on, the encoder and decoder of Chapter 3 are drawn as the single arrow
:math:`z \\to o`.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle, FancyArrowPatch, FancyBboxPatch, Rectangle  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "book" / "images" / "roadmap.png"

NEW = "#d55e00"      # Okabe-Ito vermillion: what this chapter adds
OLD = "black"
GREY = "0.8"         # fill of observed nodes and known inputs, as in plot_graphical_model
R = 0.44             # node radius (data units)
LABEL_SIZE = 9.5     # node labels
NOTE_SIZE = 7.5      # small annotations


class Panel:
    """One chapter's graphical model, drawn into one axis."""

    def __init__(self, ax, title: str, new_text: str):
        self.ax = ax
        self.nodes: dict[str, tuple[float, float, str, float]] = {}
        ax.set_title(title, fontsize=9.5, fontweight="bold", pad=3)
        self.new_text = new_text

    def node(self, name: str, x: float, y: float, label: str, kind: str = "latent", new: bool = False,
             size: float = LABEL_SIZE, box: float = 1.0) -> None:
        """A node: ``kind`` latent (white circle), observed (grey circle) or known (grey square)."""
        color = NEW if new else OLD
        lw = 2.0 if new else 1.1
        if "+1" in label:   # z_{t+1}, l_{k+1}: a smaller label, so that it stays inside the circle
            size = min(size, 8.5)
        if kind == "known":
            s = 0.8 * R * box
            self.ax.add_patch(Rectangle((x - s, y - s), 2 * s, 2 * s, fc=GREY, ec=color, lw=lw, zorder=2))
        else:
            fc = GREY if kind == "observed" else "white"
            self.ax.add_patch(Circle((x, y), R, fc=fc, ec=color, lw=lw, zorder=2))
        self.ax.text(x, y, label, ha="center", va="center", fontsize=size, color=color, zorder=3)
        self.nodes[name] = (x, y, kind, box)

    def _border(self, name: str, toward: tuple[float, float]) -> tuple[float, float]:
        x, y, kind, box = self.nodes[name]
        dx, dy = toward[0] - x, toward[1] - y
        d = float(np.hypot(dx, dy))
        if kind == "known":   # the square's border along the direction (Chebyshev distance)
            s = 0.8 * R * box
            t = s / max(abs(dx), abs(dy))
            return x + t * dx, y + t * dy
        return x + R * dx / d, y + R * dy / d

    def point(self, name: str) -> tuple[float, float]:
        x, y, *_ = self.nodes[name]
        return x, y

    def edge(self, a: str, b: str, new: bool = False, ls: str = "-", rad: float = 0.0) -> None:
        """An arrow from node ``a`` to node ``b``, between their borders."""
        pa, pb = self.point(a), self.point(b)
        self.arrow(self._border(a, pb), self._border(b, pa), new=new, ls=ls, rad=rad)

    def arrow(self, p, q, new: bool = False, ls: str = "-", rad: float = 0.0) -> None:
        color = NEW if new else OLD
        self.ax.add_patch(FancyArrowPatch(p, q, arrowstyle="-|>", mutation_scale=11, lw=1.8 if new else 1.1,
                                          color=color, ls=ls, connectionstyle=f"arc3,rad={rad}", zorder=1))

    def plate(self, x0: float, y0: float, w: float, h: float, label: str, new: bool = False,
              label_pos: str = "bottom") -> None:
        """A dashed box around a set (or a window); the label sits inside, at the bottom or top."""
        color = NEW if new else "0.4"
        self.ax.add_patch(FancyBboxPatch((x0, y0), w, h, boxstyle="round,pad=0,rounding_size=0.12",
                                         fill=False, ls="--", lw=1.2, ec=color, zorder=0))
        y = y0 + 0.06 if label_pos == "bottom" else y0 + h - 0.06
        self.ax.text(x0 + w - 0.08, y, label, ha="right", va="bottom" if label_pos == "bottom" else "top",
                     fontsize=NOTE_SIZE, color=color)

    def note(self, x: float, y: float, text: str, new: bool = True, ha: str = "center", va: str = "center",
             size: float = NOTE_SIZE) -> None:
        self.ax.text(x, y, text, ha=ha, va=va, fontsize=size, color=NEW if new else "0.25", zorder=4)

    def finish(self, xlim: tuple[float, float], ylim: tuple[float, float]) -> None:
        """Fix the limits (equal aspect, no axes) and write the 'new:' line under the model."""
        self.ax.set_xlim(*xlim)
        self.ax.set_ylim(*ylim)
        self.ax.set_aspect("equal")
        self.ax.axis("off")
        self.ax.text(0.5, 0.0, self.new_text, transform=self.ax.transAxes, ha="center", va="top",
                     fontsize=7.5, color=NEW, linespacing=1.15)


# Every panel but MTS3 uses the same frame: two time steps t, t+1 side by side.
XT, XT1 = 0.7, 3.3            # columns of step t and step t+1
XLIM = (0.0, 4.0)
YLIM = (-0.35, 4.35)
Y_Z, Y_A, Y_O = 2.1, 1.05, 0.2  # rows: state, action, observation


def ch1(ax) -> None:
    p = Panel(ax, "1. Linear-Gaussian SSM", "new: a hidden state,\npredicted and updated")
    p.node("z0", XT, Y_Z, "$z_t$", new=True)
    p.node("z1", XT1, Y_Z, "$z_{t+1}$", new=True)
    p.node("y0", XT, Y_O, "$y_t$", "observed", new=True)
    p.node("y1", XT1, Y_O, "$y_{t+1}$", "observed", new=True)
    p.edge("z0", "z1", new=True)
    p.edge("z0", "y0", new=True)
    p.edge("z1", "y1", new=True)
    p.note((XT + XT1) / 2, Y_Z + 0.12, "$A$", va="bottom", size=9)
    p.note(XT + 0.12, (Y_Z + Y_O) / 2, "$H$", ha="left", size=9)
    p.note(XT1 + 0.12, (Y_Z + Y_O) / 2, "$H$", ha="left", size=9)
    p.note(2.0, 3.65, "known linear model,\nGaussian noise", new=False)
    p.finish(XLIM, YLIM)


def ch2(ax) -> None:
    p = Panel(ax, "2. Bayesian aggregation", "new: a set of observations\nof one latent, one update")
    y_l, y_r = 3.55, 1.95
    p.node("l", 2.0, y_l, "$l$")
    xs = (0.7, 1.75, 3.3)
    for x, lab in zip(xs, ("$r_1$", "$r_2$", "$r_N$")):
        p.node(lab, x, y_r, lab, "observed", new=True)
        p.edge("l", lab, new=True)
    p.note(2.52, y_r, "$\\cdots$", size=10)
    p.plate(0.12, y_r - 0.6, 3.76, 1.2, "", new=True)
    p.note(3.88, y_r - 0.68, "set, in any order", ha="right", va="top")
    p.note(2.0, 0.4, "precisions add:\n$1/v_l = 1/v_0 + \\sum_n 1/v_n$")
    p.finish(XLIM, YLIM)


def ch3(ax) -> None:
    p = Panel(ax, "3. RKN", "new: encoder, decoder, factorized\nbelief, locally linear $A_t$")
    y_z, y_w, y_o = 3.2, 1.7, 0.2
    p.node("z0", XT, y_z, "$z_t$")
    p.node("z1", XT1, y_z, "$z_{t+1}$")
    p.node("w0", XT + 0.85, y_w, "$w_t$", "observed")   # beside the column: longer arrows
    p.node("o0", XT, y_o, "$o_t$", "observed", new=True)
    p.node("o1", XT1, y_o, "$o_{t+1}$", "observed", new=True)
    p.edge("z0", "z1", new=True)
    p.note((XT + XT1) / 2, y_z + 0.12, "$A_t$, locally\nlinear", va="bottom")
    p.edge("z0", "w0")
    p.edge("o0", "w0", new=True, ls="--")
    p.note(XT + 0.6, (y_w + y_o) / 2 - 0.15, "encoder", ha="left")
    p.edge("z1", "o1", new=True)
    p.note(XT1 - 0.14, y_w + 0.75, "decoder", ha="right")
    p.finish(XLIM, YLIM)


def ssm_core(p: Panel, observe_next: bool = True) -> None:
    """The skeleton shared by Chapters 4 to 7: z_t -> z_{t+1}, each state emits an observation."""
    p.node("z0", XT, Y_Z, "$z_t$")
    p.node("z1", XT1, Y_Z, "$z_{t+1}$")
    p.edge("z0", "z1")
    p.node("o0", XT, Y_O, "$o_t$", "observed")
    p.edge("z0", "o0")
    if observe_next:
        p.node("o1", XT1, Y_O, "$o_{t+1}$", "observed")
        p.edge("z1", "o1")


def ch4(ax) -> None:
    p = Panel(ax, "4. ac-RKN", "new: the action $a_t$\ndrives the transition")
    ssm_core(p)
    p.node("a0", 2.0, Y_A, "$a_t$", "known", new=True)
    p.edge("a0", "z1", new=True)
    p.note(2.0, Y_A - 0.5, "$+\\,b(a_t)$", va="top", size=8.5)
    p.note(2.0, 3.65, "encoder, decoder\nas in Ch. 3", new=False)
    p.finish(XLIM, YLIM)


def ch5(ax) -> None:
    p = Panel(ax, "5. HiP-RSSM", "new: a task $l$, inferred from\na context set, shifts the dynamics")
    ssm_core(p)
    p.node("a0", 2.0, Y_A, "$a_t$", "known")
    p.edge("a0", "z1")
    y_l = 3.6
    p.node("l", 2.15, y_l, "$l$", new=True)
    p.edge("l", "z1", new=True)
    p.note(2.75, (y_l + Y_Z) / 2 + 0.15, "$+\\,Cl$", ha="left", size=8.5)
    x_r = 0.5
    p.node("r", x_r, y_l, "$r_n$", "observed", new=True)
    p.edge("l", "r", new=True)
    p.plate(x_r - 0.55, y_l - 0.55, 1.1, 1.1, "", new=True)
    p.note(x_r, y_l - 0.62, "context", va="top")
    p.finish(XLIM, YLIM)


def ch6(ax) -> None:
    p = Panel(ax, "6. MTS3", "new: a slow SSM over the task $l_k$ (abstract actions $\\alpha$,\n"
                             "abstract observations $\\beta$) that sets each window's dynamics")
    # slow level (top): l_k -> l_{k+1}, abstract action alpha_{k+1}, abstract observations beta_k
    xk, xk1 = 1.5, 5.1
    y_slow, y_top, y_fast = 2.75, 3.9, 0.8
    p.node("l0", xk, y_slow, "$l_k$", new=True)
    p.node("l1", xk1, y_slow, "$l_{k+1}$", new=True)
    p.edge("l0", "l1", new=True)
    p.node("al", (xk + xk1) / 2, y_top, "$\\alpha_{k+1}$", "known", new=True, size=8.5, box=1.3)
    p.edge("al", "l1", new=True)
    for name, x, lab in (("b0", xk - 0.7, "$\\beta_k$"), ("b1", xk1 + 0.7, "$\\beta_{k+1}$")):
        p.node(name, x, y_top, lab, "observed", new=True, size=8.5)
    p.edge("l0", "b0", new=True)
    p.edge("l1", "b1", new=True)
    p.note((xk + xk1) / 2, y_slow - 0.15, "slow clock $k$", va="top")
    # fast level (bottom): one window of H fast steps per slow step, the SSM of Chapter 5
    for k, x in enumerate((xk, xk1)):
        p.node(f"z{k}a", x - 0.75, y_fast, "$z$")
        p.node(f"z{k}b", x + 0.75, y_fast, "$z$")
        p.edge(f"z{k}a", f"z{k}b")
        p.plate(x - 1.35, y_fast - 0.58, 2.7, 1.16, "", new=False)
        p.arrow((x, y_slow - R), (x, y_fast + 0.58), new=True)
    p.edge("z0b", "z1a")
    p.note(xk, y_fast - 0.65, "window $k$ (Ch. 5's SSM)", new=False, va="top")
    p.note(xk1, y_fast - 0.65, "window $k+1$", new=False, va="top")
    p.note(xk + 0.2, (y_slow + y_fast) / 2 + 0.1, "task of\nthe window", ha="left")
    p.finish((0.0, 6.6), YLIM)


def ch7(ax) -> None:
    p = Panel(ax, "7. Planning", "new: actions are inferred,\ntargets act as observations")
    ssm_core(p, observe_next=False)
    p.node("a0", 2.0, Y_A, "$a_t$", "latent", new=True)
    p.edge("a0", "z1", new=True)
    p.note(2.0 - R - 0.08, Y_A, "to\ninfer", ha="right")
    p.node("r1", XT1, Y_O, "$r_{t+1}$", "observed", new=True)
    p.edge("z1", "r1", new=True)
    p.note(XT1 - R - 0.1, Y_O, "target", ha="right")
    p.note(2.0, 3.65, "a model of\nCh. 1 or Ch. 4", new=False)
    p.finish(XLIM, YLIM)


def make_figure():
    fig = plt.figure(figsize=(8.0, 5.6))
    outer = fig.add_gridspec(2, 1, hspace=0.5, left=0.01, right=0.99, top=0.95, bottom=0.14)
    top = outer[0].subgridspec(1, 4, wspace=0.12)
    bottom = outer[1].subgridspec(1, 3, wspace=0.12, width_ratios=[4.0, 6.6, 4.0])
    for spec, draw in zip(list(top) + list(bottom), (ch1, ch2, ch3, ch4, ch5, ch6, ch7)):
        draw(fig.add_subplot(spec))
    handles = [
        Line2D([], [], ls="", marker="o", ms=10, mfc="white", mec="k", label="hidden"),
        Line2D([], [], ls="", marker="o", ms=10, mfc=GREY, mec="k", label="observed"),
        Line2D([], [], ls="", marker="s", ms=8, mfc=GREY, mec="k", label="known input"),
        Line2D([], [], ls="--", color="k", lw=1.1, label="inference network"),
        Line2D([], [], ls="-", marker="o", ms=10, mfc="white", mec=NEW, mew=2, color=NEW, lw=1.8,
               label="new in this chapter"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.0), handlelength=2.2, columnspacing=1.4)
    return fig


def main() -> None:
    plt.rcParams.update({"mathtext.fontset": "dejavusans", "font.family": "DejaVu Sans"})  # matplotlib's own fonts
    fig = make_figure()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=200, facecolor="white", metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()

"""Smoke tests of the book's diagram functions in pgm_wm.plotting (drawn by code)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pgm_wm import diagrams  # noqa: E402

DIAGRAMS = [
    diagrams.plot_rkn_cell,
    diagrams.plot_factorized_covariance,
    diagrams.plot_mts3_graphical_model,
    diagrams.plot_gain_as_weighted_average,
]


@pytest.mark.parametrize("draw", DIAGRAMS, ids=lambda f: f.__name__)
def test_diagram_returns_a_drawn_figure(draw):
    fig = draw()
    try:
        assert isinstance(fig, matplotlib.figure.Figure)
        ax = fig.axes[0]
        assert len(ax.patches) + len(ax.lines) > 0, "nothing was drawn"
        assert ax.get_title(), "every diagram has a title"
        fig.canvas.draw()  # renders all mathtext labels; a TeX typo raises here
    finally:
        plt.close(fig)


@pytest.mark.parametrize("draw", DIAGRAMS, ids=lambda f: f.__name__)
def test_diagram_draws_into_a_given_axis(draw):
    fig, ax = plt.subplots()
    try:
        assert draw(ax=ax) is fig
        assert len(fig.axes) == 1
    finally:
        plt.close(fig)


@pytest.mark.parametrize("m", [1, 3, 8])
def test_factorized_covariance_colours_exactly_3m_entries(m):
    fig = diagrams.plot_factorized_covariance(m)
    try:
        cells = [p for p in fig.axes[0].patches if p.get_width() == 1 and p.get_height() == 1]
        assert len(cells) == (2 * m) ** 2
        coloured = [p for p in cells if p.get_facecolor()[:3] != (1.0, 1.0, 1.0)]
        # 2m diagonal entries (sigma_u, sigma_l) and 2m side entries (sigma_s, symmetric),
        # i.e. 3m distinct numbers; everything else is structurally zero
        assert len(coloured) == 4 * m
        assert f"{3 * m} stored numbers instead of {m * (2 * m + 1)}" in fig.axes[0].get_title()
    finally:
        plt.close(fig)


def test_gain_picture_shows_the_precision_weighted_average():
    prior_mean, prior_var, y, r = -1.0, 2.0, 3.0, 0.5
    fig = diagrams.plot_gain_as_weighted_average(prior_mean, prior_var, y, r)
    try:
        lines = fig.axes[0].get_lines()
        post = lines[4]  # prior, its marker, likelihood, its marker, posterior
        x, density = post.get_xdata(), post.get_ydata()
        mode = x[np.argmax(density)]
        # independent reference: the product of the two densities, normalized numerically
        product = np.exp(-0.5 * (x - prior_mean) ** 2 / prior_var - 0.5 * (x - y) ** 2 / r)
        ref_mean = np.sum(x * product) / np.sum(product)
        assert mode == pytest.approx(ref_mean, abs=2 * (x[1] - x[0]))
        assert "0.80" in "".join(t.get_text() for t in fig.axes[0].texts)  # K = 2 / 2.5
    finally:
        plt.close(fig)


@pytest.mark.parametrize(
    "call, argument",
    [
        (lambda: diagrams.plot_factorized_covariance(0), "m"),
        (lambda: diagrams.plot_mts3_graphical_model(steps=1), "steps"),
        (lambda: diagrams.plot_gain_as_weighted_average(prior_var=0.0), "prior_var"),
        (lambda: diagrams.plot_gain_as_weighted_average(obs_var=-1.0), "obs_var"),
    ],
)
def test_diagrams_reject_bad_arguments(call, argument):
    with pytest.raises(ValueError, match=f"^{argument}"):
        call()


def test_markdown_table_marks_diverged_values():
    from pgm_wm.plotting import markdown_table

    rows = [["a", 0.5, float("inf")], ["b", 2.05054515609e11, float("nan")], ["c", -3.0, 12.0]]
    table = markdown_table(rows, ["name", "x", "y"], ".3f", diverged_above=1e3)
    lines = table.splitlines()
    assert lines[2] == "| a | 0.500 | diverged |"
    assert lines[3] == "| b | diverged | diverged |"
    assert lines[4] == "| c | -3.000 | 12.000 |"
    # without the threshold the numbers are printed as they are
    assert "inf" in markdown_table(rows[:1], ["name", "x", "y"], ".3f")
    with pytest.raises(ValueError, match="^diverged_above"):
        markdown_table(rows, ["name", "x", "y"], diverged_above=0.0)


# ----------------------------------------------------------------------------- readable diagrams
def _label_boxes(fig):
    """Window extents of every non-empty text of the figure's first axis (title included)."""
    ax = fig.axes[0]
    renderer = fig.canvas.get_renderer()
    texts = [t for t in ax.texts if t.get_text().strip()] + [ax.title]
    return [(t.get_text(), t.get_window_extent(renderer)) for t in texts]


def diagram_overlaps(fig, pad: float = 1.0) -> list[str]:
    """Labels of a box-and-arrow diagram that collide: two texts whose boxes intersect, a text
    that sticks out of (or into) a node it does not belong to, or an arrow that runs through a
    text. A text whose centre lies inside a node is that node's label and must fit inside it."""
    from matplotlib.patches import FancyArrowPatch

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    # each label's box, shrunk by `pad` pixels so that boxes that merely touch do not count
    labels = [(s, type(b).from_extents(b.x0 + pad, b.y0 + pad, b.x1 - pad, b.y1 - pad)) for s, b in _label_boxes(fig)]
    problems = []
    for i, (s1, b1) in enumerate(labels):
        for s2, b2 in labels[i + 1:]:
            if b1.overlaps(b2):
                problems.append(f"texts overlap: {s1!r} / {s2!r}")
    nodes = [p for p in ax.patches if not isinstance(p, FancyArrowPatch) and p.get_fill()]
    for s, b in labels:
        cx, cy = (b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2
        for p in nodes:
            nb = p.get_window_extent(renderer)
            if not nb.overlaps(b):
                continue
            inside = nb.x0 <= cx <= nb.x1 and nb.y0 <= cy <= nb.y1
            if not inside:
                problems.append(f"text {s!r} overlaps a node it does not label")
            elif not (nb.x0 - pad <= b.x0 and b.x1 <= nb.x1 + pad and nb.y0 - pad <= b.y0 and b.y1 <= nb.y1 + pad):
                problems.append(f"text {s!r} does not fit inside its node")
    for p in ax.patches:
        if not isinstance(p, FancyArrowPatch):
            continue
        for poly in p.get_path().to_polygons(p.get_transform(), closed_only=False):
            # sample the arrow's polyline densely and test every point against every label box
            pts = np.concatenate([np.linspace(a, c, 20) for a, c in zip(poly[:-1], poly[1:])]) if len(poly) > 1 else poly
            for s, b in labels:
                if any(b.contains(x, y) for x, y in pts):
                    problems.append(f"an arrow runs through {s!r}")
    return sorted(set(problems))


@pytest.mark.parametrize("draw", [diagrams.plot_rkn_cell, diagrams.plot_factorized_covariance,
                                  *(lambda ax=None, s=s: diagrams.plot_mts3_graphical_model(s, ax=ax)
                                    for s in (2, 3, 5))],
                         ids=["rkn_cell", "factorized_covariance", "mts3_2", "mts3_3", "mts3_5"])
def test_diagram_labels_do_not_collide(draw):
    fig = draw()
    try:
        assert diagram_overlaps(fig) == []
    finally:
        plt.close(fig)


def test_overlap_check_finds_collisions():
    """The check itself: a label on top of another, one half inside a box and an arrow through a
    label are all reported; a clean picture is not."""
    from pgm_wm.diagrams import _diagram_arrow, _diagram_box

    fig, ax = plt.subplots(figsize=(6, 3))
    try:
        ax.set_xlim(0, 10)
        ax.set_ylim(0, 5)
        ax.set_title("t")
        _diagram_box(ax, 2, 2.5, "box")
        _diagram_arrow(ax, (5, 1), (9, 1))
        assert diagram_overlaps(fig) == []
        ax.text(2, 2.5 + 0.3, "sticks out of the box", fontsize=12, ha="left")
        ax.text(7, 1, "on the arrow", ha="center", va="center")
        ax.text(7, 4, "twin", ha="center")
        ax.text(7.1, 4, "twin 2", ha="center")
        found = " | ".join(diagram_overlaps(fig))
        assert "does not fit inside its node" in found or "overlaps a node" in found
        assert "an arrow runs through 'on the arrow'" in found
        assert "texts overlap: 'twin'" in found or "texts overlap: 'twin 2'" in found
    finally:
        plt.close(fig)


# ----------------------------------------------------------------------------- source without docstrings
def _sample(x):
    """Docstring of the sample.

    Two paragraphs.
    """
    # a comment that stays
    def inner(y):
        '''Inner docstring.'''
        return y + 1   # trailing comment

    class Holder:
        """Only a docstring."""

    return inner(x), Holder


def _strip_docstrings(tree):
    """Independent reference: remove docstring nodes from an AST (empty bodies get `...`)."""
    import ast

    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                node.body = node.body[1:] or [ast.Expr(ast.Constant(Ellipsis))]
    return ast.dump(tree)


@pytest.mark.parametrize("name", ["sample", "_linalg.update_cov", "_linalg.update_mean", "factorized.update_unchecked",
                                  "kalman.kf_update", "beliefs.DiagGaussian"])
def test_source_without_docstrings_keeps_the_code_and_drops_the_docstrings(name):
    import ast
    import importlib
    import inspect
    import textwrap

    from pgm_wm.plotting import source_without_docstrings

    if name == "sample":
        obj = _sample
    else:
        module, attr = name.split(".")
        obj = getattr(importlib.import_module(f"pgm_wm.{module}"), attr)
    original = textwrap.dedent(inspect.getsource(obj))
    shown = source_without_docstrings(obj)
    assert ast.dump(ast.parse(shown)) == _strip_docstrings(ast.parse(original))
    # every line shown is a line of the original, in order (comments included)
    it = iter(original.splitlines())
    assert all(any(line == o for o in it) for line in shown.splitlines() if line.strip() != "...")
    if name == "sample":
        assert "# a comment that stays" in shown and "# trailing comment" in shown
        assert "docstring" not in shown.lower()


def test_show_source_is_a_python_block_and_rejects_nothing_to_show():
    from pgm_wm.plotting import show_source

    md = show_source(_sample)
    assert md.data.startswith("```python\n") and md.data.endswith("\n```")
    with pytest.raises(ValueError, match="^objs"):
        show_source()
    with pytest.raises(ValueError, match="^obj"):
        show_source(len)   # a builtin has no Python source


def test_use_book_figures_doubles_the_pixels_of_inline_figures():
    """In an IPython shell the PNG of a figure has twice the pixels of its displayed size (the
    width/height metadata the book and JupyterLab use); outside a shell nothing happens."""
    import base64
    import io

    from IPython.core.interactiveshell import InteractiveShell
    from PIL import Image

    from pgm_wm.plotting import use_book_figures

    if not InteractiveShell.initialized():
        use_book_figures()                  # no shell: a no-op
    shell = InteractiveShell.instance()
    try:
        use_book_figures()
        fig, ax = plt.subplots(figsize=(4, 3), dpi=100)
        ax.plot([0, 1], [0, 1])
        data, meta = shell.display_formatter.format(fig)
        png = data["image/png"]
        width, height = Image.open(io.BytesIO(png if isinstance(png, bytes) else base64.b64decode(png))).size
        shown = meta["image/png"]
        assert abs(width - 2 * shown["width"]) <= 2 and abs(height - 2 * shown["height"]) <= 2
        plt.close(fig)
    finally:
        InteractiveShell.clear_instance()

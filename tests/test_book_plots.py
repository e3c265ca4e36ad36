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

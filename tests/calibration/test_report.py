import numpy as np
import pytest

from services.calibration.report import coverage_map, residual_bars, residual_vectors


def test_residual_bars_draw_one_bar_per_view_and_the_overall_line():
    figure = residual_bars(np.array([0.1, 0.3, 0.2]), ["a.png", "b.png", "c.png"], 0.22)
    axes = figure.axes[0]
    heights = [patch.get_height() for patch in axes.patches]
    np.testing.assert_allclose(heights, [0.1, 0.3, 0.2])
    assert [label.get_text() for label in axes.get_xticklabels()] == ["a.png", "b.png", "c.png"]
    assert "0.220" in axes.get_legend().get_texts()[0].get_text()


def test_residual_bars_refuse_mismatched_labels():
    with pytest.raises(ValueError, match="2 labels for 3 views"):
        residual_bars(np.zeros(3), ["a", "b"], 0.0)


def test_residual_vectors_are_magnified_to_a_visible_length():
    points = [np.array([[10.0, 10.0], [100.0, 50.0]])]
    residuals = [np.array([[0.1, 0.0], [0.0, -0.2]])]
    figure = residual_vectors(points, residuals, (200, 100))
    quiver = figure.axes[0].collections[0]
    np.testing.assert_allclose(quiver.U, [20.0, 0.0])
    np.testing.assert_allclose(quiver.V, [0.0, -40.0])
    assert "x200" in figure.axes[0].get_title() and "0.200 px" in figure.axes[0].get_title()


def test_coverage_map_counts_every_feature_in_its_cell():
    points = [np.array([[5.0, 5.0], [6.0, 6.0]]), np.array([[195.0, 95.0]])]
    figure = coverage_map(points, (200, 100), cells=4)
    counts = figure.axes[0].images[0].get_array()
    assert counts.shape == (2, 4)
    assert counts.sum() == 3 and counts[0, 0] == 2 and counts[1, 3] == 1
    assert "75% of cells empty" in figure.axes[0].get_title()

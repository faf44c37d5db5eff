"""The decision rule: OK and NotOK only when the uncertainty interval lies wholly inside or outside."""

import pytest

from services.inspection.verdict import decide, overall

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("deviation, uncertainty, verdict", [
    (0.0, 0.1, "OK"), (0.19, 0.1, "OK"), (-0.19, 0.1, "OK"),
    (0.25, 0.1, "NotDecidable"), (0.3, 0.1, "NotDecidable"), (-0.35, 0.1, "NotDecidable"),
    (0.45, 0.1, "NotOK"), (-1.0, 0.1, "NotOK"),
    (0.0, float("nan"), "NotDecidable"), (float("nan"), 0.1, "NotDecidable"),
    (0.29, 0.0, "OK"), (0.31, 0.0, "NotOK"),
])
def test_decide(deviation, uncertainty, verdict):
    assert decide(deviation, (-0.3, 0.3), uncertainty) == verdict


def test_overall_and_bad_tolerance():
    assert overall(["OK", "OK"]) == "OK"
    assert overall(["OK", "NotDecidable"]) == "NotDecidable"
    assert overall(["NotDecidable", "NotOK", "OK"]) == "NotOK"
    with pytest.raises(ValueError, match="lies above"):
        decide(0.0, (0.3, -0.3), 0.1)


def _map(patch_cells, patch_depth, points_per_cell=5):
    """A 1 mm cell map of a 40 x 40 mm flat patch at deviation 0 with a square of ``patch_cells`` cells at
    ``patch_depth``."""
    import numpy as np

    from services.inspection.deviation import cell_means

    xs, ys = np.meshgrid(np.arange(40) + 0.5, np.arange(40) + 0.5)
    centres = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.5)])
    points = np.repeat(centres, points_per_cell, axis=0)
    deviation = np.zeros(len(points))
    side = int(round(patch_cells ** 0.5))
    inside = (points[:, 0] < side) & (points[:, 1] < side)
    deviation[inside] = patch_depth
    return cell_means(points, deviation)


@pytest.mark.parametrize("cells, depth, per_cell, verdict", [
    (4, -2.0, 5, "OK"),  # 4 mm^2 of 20 points: too small to decide
    (16, -2.0, 5, "NotOK"),  # 16 mm^2 of 80 points: a defect
    (16, -2.0, 1, "OK"),  # 16 cells but 16 points: too little support
    (16, -1.05, 5, "NotDecidable"),  # the limit within its interval
    (16, -0.5, 5, "OK"),
])
def test_surface_verdict_needs_a_patch_of_stated_size_and_support(cells, depth, per_cell, verdict):
    from services.inspection.deviation import surface_verdict

    assert surface_verdict(_map(cells, depth, per_cell), (-1.0, 1.0), 0.1) == verdict

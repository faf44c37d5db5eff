"""The decision rule: OK and NotOK only when the uncertainty interval lies wholly inside or outside."""

import pytest

from services.inspection.verdict import decide, overall


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

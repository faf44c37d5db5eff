"""The hot-part targets against the simulator's ground truth, with a smaller camera than the experiment's.

experiments/hot_parts.py films the billet and dome before the cool fixture through the simulated station
and scores every point; here the camera is scaled to 0.3 (384 x 240 px) for speed, so the share of the
part within a pixel of its silhouette is larger and the reconstructed shares are a little lower than the
full-size figures in docs/hot-parts.md.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

_SPEC = importlib.util.spec_from_file_location("hot_parts", Path(__file__).parents[2] / "experiments" / "hot_parts.py")
hot_parts = sys.modules.setdefault("hot_parts", importlib.util.module_from_spec(_SPEC))
_SPEC.loader.exec_module(hot_parts)
SCALE = 0.3


@pytest.fixture(scope="module")
def results():
    wanted = ("blue 450/40, 1200 C, auto", "white, 1000 C, auto", "white, 1000 C, auto, drift 5 K",
              "white, 1250 C, auto")
    return {case.name: hot_parts.run_case(case, SCALE) for case in hot_parts.CASES if case.name in wanted}


def test_blue_projector_behind_a_band_pass_filter_measures_the_part_at_1200_c(results):
    result = results["blue 450/40, 1200 C, auto"]
    assert result.part_reconstructed >= 0.90  # 95 % at full size
    assert result.part_mean_error_mm <= 0.05
    assert result.part_off_1mm <= 0.001
    assert result.scan.glow.glow_level < 0.05 and result.scan.glow.hint is None


def test_white_projector_at_1000_c_keeps_most_of_the_part_and_no_wrong_points(results):
    result = results["white, 1000 C, auto"]
    assert result.part_reconstructed >= 0.60
    assert result.part_off_1mm <= 0.005
    assert result.fixture_reconstructed >= 0.95
    assert result.glow_level > 0.5  # the glow fills most of the range the automatic exposure leaves


def test_white_projector_at_1250_c_says_why_the_part_is_missing(results):
    result = results["white, 1250 C, auto"]
    glow = result.scan.glow
    assert result.part_off_1mm <= 0.001
    assert result.part_reconstructed < 0.5
    assert glow.saturated_fraction + glow.lost_fraction > 0.5
    assert "blue projector and a band-pass filter" in glow.hint


def test_hdr_measures_both_the_glowing_part_and_the_cool_fixture_at_1000_c():
    # At half size (640 x 400 px), where the part's silhouette ring is a larger share than at full size.
    case = next(case for case in hot_parts.CASES if case.name == "white, 1000 C, HDR")
    result = hot_parts.run_case(case, 0.5)
    short = result.exposures_us[0]
    assert result.exposures_us == [short] * 4 + [pytest.approx(4 * short, abs=0.05)]
    assert result.part_reconstructed >= 0.95
    assert result.fixture_reconstructed >= 0.95
    assert result.part_off_1mm <= 0.005
    assert result.part_mean_error_mm <= 0.1  # 0.036 mm at full size


def test_a_glow_drifting_5_k_costs_no_accuracy(results):
    constant, drifting = results["white, 1000 C, auto"], results["white, 1000 C, auto, drift 5 K"]
    assert constant.scan.glow.drift == pytest.approx(0.0, abs=0.002)
    assert drifting.scan.glow.drift < -0.02  # 5 K at 1000 C: the glow falls by about 4 %
    assert drifting.part_mean_error_mm <= 1.1 * constant.part_mean_error_mm
    assert drifting.part_reconstructed >= 0.9 * constant.part_reconstructed
    assert drifting.part_off_1mm <= 0.005  # a handful of pixels at this size: compared with the target, not 1.1x

    assert constant.scan.glow.lost_fraction > 0.05  # the glow's shot noise costs the grazing parts of the part

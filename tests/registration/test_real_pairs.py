"""Registration of the 25 real TNO infrared/visible pairs (../shared/data/tno-ir-visible), measured as consistency.

Each infrared image is moved by a known similarity (shift up to 30 px per
axis, rotation up to 4 degrees, scale 0.93..1.07, seeded by the pair number as
in experiments/registration_real.py) and cut to a view inside it; the
registration of the view must equal the registration of the whole image
composed with the move (services.registration.consistency). Over all 25
pairs, issue 11's targets (consistency median at most 0.5 px, at least 90 % of
the pairs under 1 px) are not met yet (docs/registration.md: median 0.54 px,
76 % under 1 px), so they are strict expected failures, which turn into
failures to remove the marks the day the method meets them; what is met today
is guarded against getting worse, with room for the run-to-run scatter of
about 0.1 px (pairs 16 and 20 lie within 0.07 px of 1 px).
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.registration.consistency import move_consistency
from services.registration.register import register

pytestmark = pytest.mark.integration  # 50 full-resolution registrations, about a minute on a quiet core

TNO_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tno-ir-visible"  # shared/ beside the clone
PAIRS = range(1, 26)


def _pair(number: int) -> tuple[np.ndarray, np.ndarray]:
    images = [cv2.imread(str(TNO_DIR / band / f"{number:02d}.png"), cv2.IMREAD_GRAYSCALE) for band in ("vi", "ir")]
    if any(image is None for image in images):
        pytest.fail(f"TNO pair {number:02d} is missing from {TNO_DIR}")
    return images[0], images[1]


def _register(visible: np.ndarray, infrared: np.ndarray) -> np.ndarray:
    return register(visible, infrared, "similarity", metric="ngf", scale=1.0, max_shift=45.0).matrix


@pytest.fixture(scope="module")
def results():
    return {number: move_consistency(_register, *_pair(number), np.random.default_rng([0, number]))
            for number in PAIRS}


def _consistency(results) -> np.ndarray:
    return np.array([result.consistency for result in results.values()])


_TARGET_NOT_MET = "issue 11's target is not met yet (docs/registration.md, Real infrared/visible pairs)"


@pytest.mark.xfail(strict=True, reason=_TARGET_NOT_MET)
def test_real_pairs_are_registered_consistently_to_half_a_pixel_in_the_median(results):
    assert np.median(_consistency(results)) <= 0.5, _consistency(results)


@pytest.mark.xfail(strict=True, reason=_TARGET_NOT_MET)
def test_real_pairs_are_registered_consistently_to_a_pixel_on_nine_pairs_in_ten(results):
    assert np.mean(_consistency(results) < 1.0) >= 0.9, _consistency(results)


def test_real_pair_consistency_is_no_worse_than_documented(results):
    consistency = _consistency(results)  # documented: median 0.542 px, 19 of 25 pairs under 1 px
    assert np.median(consistency) <= 0.65, consistency
    assert np.sum(consistency < 1.0) >= 17, consistency


def test_real_pair_registrations_stay_near_the_hand_alignment(results):
    # the hand alignment is approximate (about a pixel by the README, but 5-10 px at the corners on pairs 11-18,
    # see docs/registration.md), so only a gross disagreement on most pairs would mean a wrong registration
    from_hand = np.array([result.from_hand for result in results.values()])
    assert np.median(from_hand) < 15.0, from_hand

"""Registration of real TNO infrared/visible pairs (../shared/data/tno-ir-visible) with default options.

Measured as consistency: each infrared image is moved by a known similarity
(shift up to 30 px per axis, rotation up to 4 degrees, scale 0.93..1.07,
seeded by the pair number as in experiments/registration_real.py) on its own
canvas, what the move brings in set to 0 and NOT masked, or cut to a view
inside it (the stricter variant); the registration of the moved image must
equal the registration of the whole image composed with the move
(services.registration.consistency). `register` runs with every default:
no mask, no metric, no scale, no search range.

Only the reporting half of the pairs (the even numbers) is used: the
defaults were chosen on the tuning half (the odd numbers), whose figures are
not reported. Issue 35's targets are checked on the moved images (median at
most 0.5 px and at least 90 % under 1 px: both met; the share only since the
gradient-field choice among distinct maxima, designed after pair 06's failure
was seen, docs/registration.md); the documented figures (docs/registration.md)
are guarded against getting worse, with room for the scatter of about 0.1 px
that a change of the optimiser's path brings (another CPU's rounding is one).
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.registration.consistency import move_consistency
from services.registration.register import register

pytestmark = pytest.mark.integration  # 48 full-resolution registrations of real pairs

TNO_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tno-ir-visible"  # shared/ beside the clone
REPORTING = range(2, 26, 2)  # the defaults were chosen on the odd pairs; these report


def _pair(number: int) -> tuple[np.ndarray, np.ndarray]:
    images = [cv2.imread(str(TNO_DIR / band / f"{number:02d}.png"), cv2.IMREAD_GRAYSCALE) for band in ("vi", "ir")]
    if any(image is None for image in images):
        pytest.fail(f"TNO pair {number:02d} is missing from {TNO_DIR}")
    return images[0], images[1]


def _register_with_defaults(visible: np.ndarray, infrared: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    return register(visible, infrared).matrix  # the mask of what the move brought in is not given


def _results(view: bool) -> dict:
    return {number: move_consistency(_register_with_defaults, *_pair(number), np.random.default_rng([0, number]),
                                     view=view)
            for number in REPORTING}


@pytest.fixture(scope="module")
def moved():
    return _results(view=False)


@pytest.fixture(scope="module")
def view():
    return _results(view=True)


def _consistency(by_pair: dict) -> np.ndarray:
    return np.array([result.consistency for result in by_pair.values()])


def test_moved_real_pairs_meet_the_median_target_with_default_options(moved):
    consistency = _consistency(moved)
    assert np.median(consistency) <= 0.5, consistency  # issue 35's target; documented 0.420 px


def test_moved_real_pairs_meet_the_share_target_with_default_options(moved):
    # documented: 11 of 12 (92 %), all but 02 (smoke, similar trunks)
    assert np.mean(_consistency(moved) < 1.0) >= 0.9, _consistency(moved)  # issue 35's target


@pytest.mark.long  # 24 more registrations: the stricter variant's guard, beyond issue 35's targets
def test_cut_views_of_real_pairs_are_no_worse_than_documented(view):
    consistency = _consistency(view)
    assert np.median(consistency) <= 0.9, consistency  # documented 0.787 px
    assert np.sum(consistency < 1.0) >= 7, consistency  # documented 8 of 12


def test_moved_images_bring_in_a_border_that_the_registration_is_not_told_of(moved):
    for result in moved.values():
        assert 0.7 < result.moved_mask.mean() < 1.0  # the move brought in up to 30 % of the canvas
    # as a constant 0, but for the interpolation's blend along its edge
    brought_in = np.concatenate([result.moved_image[~result.moved_mask] for result in moved.values()])
    assert np.mean(brought_in == 0) > 0.9


@pytest.mark.long
def test_a_cut_view_lies_wholly_inside_the_original(view):
    assert all(result.moved_mask is None for result in view.values())


@pytest.mark.parametrize("protocol", ["moved", pytest.param("view", marks=pytest.mark.long)])
def test_real_pair_registrations_stay_near_the_hand_alignment(protocol, request):
    # the hand alignment is approximate (about a pixel by the README, but 5-10 px at the corners on pairs 11-18,
    # see docs/registration.md), so only a gross disagreement on most pairs would mean a wrong registration
    from_hand = np.array([result.from_hand for result in request.getfixturevalue(protocol).values()])
    assert np.median(from_hand) < 15.0, from_hand

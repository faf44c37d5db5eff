"""Registration of real TNO infrared/visible pairs (../shared/data/tno-ir-visible), measured as consistency.

Each infrared image is moved by a known similarity (shift up to 30 px per
axis, rotation up to 4 degrees, scale 0.93..1.07, seeded by the pair number as
in experiments/registration_real.py), on its own canvas with what the move
brings in masked, or cut to a view inside it (the stricter variant); the
registration of the moved image must equal the registration of the whole
image composed with the move (services.registration.consistency). Issue 11's
targets are checked on all 25 moved pairs (median at most 0.5 px, at least 90 %
under 1 px); the stricter cut view, to keep the suite inside its budget, on every
fourth pair (01, 05, ... 25). Both guard the documented figures
(docs/registration.md, beside SimpleITK: the experiment's) against getting worse,
with room for the scatter of about 0.1 px that a change of the optimiser's path
brings (another CPU's rounding is one).
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.registration.consistency import move_consistency
from services.registration.register import register

pytestmark = pytest.mark.integration  # 64 full-resolution registrations

TNO_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tno-ir-visible"  # shared/ beside the clone
PAIRS = {"moved": range(1, 26), "view": range(1, 26, 4)}


def _pair(number: int) -> tuple[np.ndarray, np.ndarray]:
    images = [cv2.imread(str(TNO_DIR / band / f"{number:02d}.png"), cv2.IMREAD_GRAYSCALE) for band in ("vi", "ir")]
    if any(image is None for image in images):
        pytest.fail(f"TNO pair {number:02d} is missing from {TNO_DIR}")
    return images[0], images[1]


def _register(visible: np.ndarray, infrared: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    return register(visible, infrared, "similarity", metric="ngf", scale=1.0, max_shift=45.0,
                    moving_mask=mask).matrix


@pytest.fixture(scope="module", params=["moved", "view"])
def results(request):
    return request.param, {
        number: move_consistency(_register, *_pair(number), np.random.default_rng([0, number]),
                                 view=request.param == "view")
        for number in PAIRS[request.param]}


def test_real_pair_consistency_is_no_worse_than_documented(results):
    protocol, by_pair = results
    consistency = np.array([result.consistency for result in by_pair.values()])
    if protocol == "moved":  # documented: median 0.223 px, 24 of 25 under 1 px (02, mostly smoke, not)
        assert np.median(consistency) <= 0.32, consistency
        assert np.sum(consistency < 1.0) >= 23, consistency  # issue 11: at least 90 %
    else:  # documented: median 0.308 px, 6 of these 7 pairs under 1 px
        assert np.median(consistency) <= 0.40, consistency
        assert np.sum(consistency < 1.0) >= 5, consistency


def test_moved_images_keep_most_of_the_scene_and_mask_the_rest(results):
    protocol, by_pair = results
    for result in by_pair.values():
        if protocol == "moved":
            assert result.moved_image.shape == result.moved_mask.shape
            assert 0.7 < result.moved_mask.mean() < 1.0
        else:
            assert result.moved_mask is None


def test_real_pair_registrations_stay_near_the_hand_alignment(results):
    # the hand alignment is approximate (about a pixel by the README, but 5-10 px at the corners on pairs 11-18,
    # see docs/registration.md), so only a gross disagreement on most pairs would mean a wrong registration
    _, by_pair = results
    from_hand = np.array([result.from_hand for result in by_pair.values()])
    assert np.median(from_hand) < 15.0, from_hand

import cv2
import numpy as np
import pytest

from services.registration.models import apply_homography, corner_error, similarity_about_centres
from services.registration.mutual_information import quantize
from services.registration.search import coarse_search, gradient_field_search


def _blobs(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)


def test_the_best_candidate_is_the_true_shift_rotation_and_scale():
    fixed = _blobs((120, 160), 0)
    truth = similarity_about_centres(np.array([39.5, 31.5]), np.array([79.5, 59.5]), 1.0, np.deg2rad(4.0),
                                     np.array([6.0, -5.0]))
    moving = 1.0 - cv2.warpAffine(fixed, truth[:2], (80, 64), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    candidates = coarse_search(quantize(fixed, 16), quantize(moving, 16), 1.0, np.deg2rad([-4.0, 0.0, 4.0]),
                               np.array([0.95, 1.0, 1.05]), 8, 16, 2.0, count=3)
    assert len(candidates) == 3
    assert corner_error(truth, candidates[0].matrix, 80, 64) < 0.75  # nearest point of the 1 px shift grid
    assert candidates[0].value >= candidates[1].value >= candidates[2].value
    assert corner_error(candidates[0].matrix, candidates[1].matrix, 80, 64) > 1.5


def test_shifts_that_leave_too_little_overlap_are_not_candidates():
    fixed = _blobs((64, 64), 1)
    moving = _blobs((64, 64), 2)
    candidates = coarse_search(quantize(fixed, 8), quantize(moving, 8), 1.0, np.zeros(1), np.ones(1), 40, 8, 2.0,
                               min_overlap=0.9, count=1000)
    centre = np.array([[31.5, 31.5]])
    offsets = [apply_homography(candidate.matrix, centre)[0] - centre[0] for candidate in candidates]
    assert candidates and max(np.abs(offset).max() for offset in offsets) <= 6.4  # 90 % of 64 px rows or columns


def test_negative_search_range_is_refused():
    image = quantize(_blobs((64, 64), 3), 8)
    with pytest.raises(ValueError, match="non-negative"):
        coarse_search(image, image, 1.0, np.zeros(1), np.ones(1), -1, 8, 2.0)


def test_gradient_field_search_finds_the_move_of_a_contrast_inverted_image():
    fixed = _blobs((120, 160), 3)
    truth = similarity_about_centres(np.array([39.5, 31.5]), np.array([79.5, 59.5]), 1.05, np.deg2rad(-4.0),
                                     np.array([-7.0, 4.0]))
    moving = 1.0 - cv2.warpAffine(fixed, truth[:2], (80, 64), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    candidates = gradient_field_search(fixed, moving, 1.0, np.deg2rad([-4.0, 0.0, 4.0]), np.array([0.95, 1.0, 1.05]),
                                       8, count=3)
    assert len(candidates) == 3 and candidates[0].value >= candidates[1].value
    assert corner_error(truth, candidates[0].matrix, 80, 64) < 0.75


def test_the_shifts_scored_by_mi_are_those_the_gradient_fields_rank_best_and_their_hard_binned_mi_is_exact():
    from services.registration.search import _hard_binned_scores

    rng = np.random.default_rng(4)
    canvas = rng.integers(0, 4, size=(12, 14)).astype(np.int16)
    canvas[0, :] = -1  # outside the fixed image
    moving = rng.integers(0, 4, size=(8, 9)).astype(np.int16)
    shifts = np.array([[0, 0], [2, 3], [4, 5]])
    scores = _hard_binned_scores(canvas, moving, shifts, 4, 2.0, False, 10)
    for (dy, dx), value in zip(shifts, scores):
        window = canvas[dy:dy + 8, dx:dx + 9]
        inside = window >= 0
        joint = np.histogram2d(window[inside], moving[inside], bins=4, range=[[-0.5, 3.5], [-0.5, 3.5]])[0]
        p = joint / joint.sum()
        pa, pb = p.sum(axis=1), p.sum(axis=0)
        expected = sum(-(q[q > 0] * np.log2(q[q > 0])).sum() for q in (pa, pb)) + (p[p > 0] * np.log2(p[p > 0])).sum()
        assert value == pytest.approx(expected)
    too_little = _hard_binned_scores(canvas, moving, shifts, 4, 2.0, False, 70)
    assert too_little[0] == -np.inf and np.all(np.isfinite(too_little[1:]))  # 63 of 72 inside at (0, 0), else 72

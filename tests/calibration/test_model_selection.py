"""Lens model selection: the Bayesian information criterion, and calibrate_camera(distortion="auto")."""

import math

import cv2
import numpy as np
import pytest

from services.calibration.camera import AUTO_CANDIDATES, calibrate_camera
from services.calibration.corners import detect_board
from services.calibration.model_selection import ModelFit, bayesian_information_criterion, select_model
from services.formats.board import parse_board
from services.simulation.boards import render_board

pytestmark = pytest.mark.integration

THERMAL_BOARD = parse_board('{"type": "chessboard", "inner_corners": [7, 5], "square_mm": 30.0}')
THERMAL_K = np.array([[400.0, 0.0, 161.3], [0.0, 400.0, 127.6], [0.0, 0.0, 1.0]])
THERMAL_DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])
THERMAL_SIZE = (320, 256)


def _poses(rng, board, K, dist, size, views, near, far):
    """Poses 20..40 degrees tilted, spread over near..far mm and over the image, all corners inside."""
    centre = board.object_points().mean(axis=0)
    poses = []
    while len(poses) < views:
        angle = 2 * np.pi * (len(poses) + rng.uniform()) / views
        tilt = np.radians(rng.uniform(20, 40))
        R = cv2.Rodrigues(np.array([tilt * np.cos(angle), tilt * np.sin(angle), rng.uniform(-0.3, 0.3)]))[0]
        z = near + (far - near) * (len(poses) + rng.uniform()) / views
        reach = 0.25 * z * np.array(size) / K[0, 0]
        t = np.array([rng.uniform(-1, 1) * reach[0], rng.uniform(-1, 1) * reach[1], z]) - R @ centre
        corners = cv2.projectPoints(board.object_points(), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
        if corners.min() >= 8 and np.all(corners.max(axis=0) <= np.array(size) - 8):
            poses.append((R, t))
    return poses


def test_bic_is_n_log_mean_square_plus_k_log_n():
    assert bayesian_information_criterion(50.0, 100, 10) == pytest.approx(100 * math.log(0.5) + 10 * math.log(100))
    with pytest.raises(ValueError, match="more observations"):
        bayesian_information_criterion(1.0, 10, 10)


def test_the_lowest_bic_wins_and_the_reason_names_the_runner_up():
    fits = [ModelFit("radial", 100.0, 1000, 50, bayesian_information_criterion(100.0, 1000, 50), 0.3),
            ModelFit("standard", 99.9, 1000, 53, bayesian_information_criterion(99.9, 1000, 53), 0.3)]
    selection = select_model(fits)
    assert selection.chosen == "radial"
    assert "standard's 3 more parameters" in selection.reason and "0.10 %" in selection.reason
    rich = [fits[0], ModelFit("standard", 60.0, 1000, 53, bayesian_information_criterion(60.0, 1000, 53), 0.2)]
    assert select_model(rich).chosen == "standard"
    assert "support the extra coefficients" in select_model(rich).reason


def test_rich_data_of_a_strongly_distorted_lens_keeps_the_full_model():
    board = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')
    K = np.array([[520.0, 0.0, 322.0], [0.0, 520.0, 238.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.35, 0.15, 0.001, -0.0008, -0.03])
    rng = np.random.default_rng(3)
    points = [cv2.projectPoints(board.object_points(), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
              + rng.normal(0.0, 0.05, (54, 2)) for R, t in _poses(rng, board, K, dist, (640, 480), 40, 250, 600)]
    result = calibrate_camera([board.object_points()] * len(points), points, (640, 480), "auto")
    assert result.distortion_model == "standard"
    assert [fit.model for fit in result.model_selection.fits] == list(AUTO_CANDIDATES)
    assert len(result.dist) == 5 and set(result.std) >= {"k3", "p1", "p2"}
    assert np.abs(result.dist - dist).max() < 0.02


def test_few_blurry_thermal_views_meet_the_targets_with_the_chosen_model():
    """16 hollow-board views at 320x256, 300..600 mm, blur 1 px, noise 2 grey levels; median over 3 seeds."""
    focal, principal = [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        points = []
        for R, t in _poses(rng, THERMAL_BOARD, THERMAL_K, THERMAL_DIST, THERMAL_SIZE, 16, 300, 600):
            image = render_board(THERMAL_BOARD, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE, modality="infrared",
                                 blur_sigma=1.0, noise_sigma=2.0, supersample=1, rng=rng)
            detection = detect_board(image, THERMAL_BOARD)
            if detection is not None:
                points.append(detection.image_points)
        assert len(points) >= 14
        result = calibrate_camera([THERMAL_BOARD.object_points()] * len(points), points, THERMAL_SIZE, "auto")
        assert result.distortion_model in ("radial", "standard")
        assert result.model_selection.reason.startswith(result.distortion_model)
        focal.append(np.abs(np.diag(result.K)[:2] / np.diag(THERMAL_K)[:2] - 1).max())
        principal.append(np.abs(result.K[:2, 2] - THERMAL_K[:2, 2]).max())
    assert np.median(focal) <= 1e-3
    assert np.median(principal) <= 0.5


def test_the_sigma_of_a_simpler_chosen_model_carries_the_choice():
    """A decentred lens (p1, p2 = +-0.001) under noisy corners: the criterion picks k1 k2, whose principal point
    absorbs the tangential terms; the sigma conditional on that choice misses the error, the reported one
    (with the spread to the standard model) covers it."""
    dist = np.array([-0.2, 0.1, 0.001, -0.001, 0.0])
    rng = np.random.default_rng(2)
    points = [cv2.projectPoints(THERMAL_BOARD.object_points(), cv2.Rodrigues(R)[0], t, THERMAL_K, dist)[0].reshape(-1, 2)
              + rng.normal(0.0, 0.1, (35, 2)) for R, t in _poses(rng, THERMAL_BOARD, THERMAL_K, dist, THERMAL_SIZE, 16,
                                                                 300, 600)]
    objects = [THERMAL_BOARD.object_points()] * len(points)
    result = calibrate_camera(objects, points, THERMAL_SIZE, "auto")
    assert result.distortion_model == "radial"
    standard = calibrate_camera(objects, points, THERMAL_SIZE, "standard", jackknife=False)
    assert result.std_model_choice["cx"] == pytest.approx(abs(standard.K[0, 2] - result.K[0, 2]), rel=1e-6)
    # every estimated parameter carries the choice, the distortion coefficients too (the models are nested), theirs
    # without the difference's own noise (Hausman's form), so never more than the difference
    assert set(result.std_model_choice) == {"fx", "fy", "cx", "cy", "k1", "k2"}
    for index, name in enumerate(("k1", "k2")):
        assert result.std_model_choice[name] <= abs(standard.dist[index] - result.dist[index]) + 1e-12
        assert result.std[name] >= result.std_model_choice[name]
    error = abs(result.K[0, 2] - THERMAL_K[0, 2])
    conditional = math.sqrt(result.std["cx"] ** 2 - result.std_model_choice["cx"] ** 2)
    assert error > 1.645 * conditional
    assert error <= 1.645 * result.std["cx"]
    assert standard.std_model_choice is None

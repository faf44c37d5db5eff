"""services.calibration.station: the bundle adjustment of a station's cameras, on exact and noisy corners projected
from a simulated ring station (no rendering; tests/calibration/test_station_cli.py renders)."""

import numpy as np
import pytest

from services.calibration.station import BoardObservation, adjust_station, pose_difference, tied_groups
from services.formats.board import ChessboardSpec
from services.simulation.station_boards import ring_station_rig, station_board_poses

BOARD = ChessboardSpec(type="chessboard", inner_corners=(9, 6), square_mm=30.0)
Z90 = 1.6448536269514722


def projected_views(rig, rng, shared=6, own=4, noise_px=0.0, view_shift_px=0.0, pairs=None):
    """Observations of board poses shared by neighbouring heads and seen by each camera alone: the true corners
    plus independent noise and a shift shared by all corners of one camera's view."""
    cameras = [rig.devices[head.camera] for head in rig.heads]
    poses, seen = station_board_poses(cameras, BOARD, rng, shared, own, pairs)
    observations, X = [], BOARD.object_points()
    for view, ((R, t), which) in enumerate(zip(poses, seen)):
        for index in which:
            pixels = cameras[index].project(X @ R.T + t)
            pixels = pixels + rng.normal(0, noise_px, pixels.shape) + rng.normal(0, view_shift_px, 2)
            observations.append(BoardObservation(index, view, X, pixels))
    return cameras, observations


def relative_truth(cameras):
    """Each camera's true pose in the frame of the first (the adjustment's world by default)."""
    reference = cameras[0]
    return [(c.R @ reference.R.T, c.t - c.R @ reference.R.T @ reference.t) for c in cameras]


def test_exact_corners_give_every_camera_its_true_pose_and_intrinsics():
    rig = ring_station_rig(np.random.default_rng(3), scale=0.5)
    cameras, observations = projected_views(rig, np.random.default_rng(4))
    start = [(c.K * [[1.01], [1.01], [1]], c.dist * 0.9) for c in cameras]  # intrinsics off by 1 % and 10 %
    result = adjust_station(observations, start, refined_intrinsics=[("fx", "fy", "cx", "cy", "k1", "k2")] * 4,
                            jackknife=False)
    for camera, (R, t), index in zip(cameras, relative_truth(cameras), range(4)):
        error = pose_difference(R, t, result.rotations[index], result.translations[index])
        assert np.all(np.abs(error[:3]) < 1e-6) and np.all(np.abs(error[3:]) < 1e-5)
        assert np.allclose(result.K[index], camera.K, atol=1e-5)
    assert result.rms_px < 1e-6 and result.overlap_rms_mm < 1e-6
    assert np.all(result.pose_std[0] == 0)  # the reference fixes the world


def test_the_reference_camera_keeps_the_given_world_pose():
    rig = ring_station_rig(np.random.default_rng(5), scale=0.5)
    cameras, observations = projected_views(rig, np.random.default_rng(6), own=0)
    second = cameras[1]
    result = adjust_station(observations, [(c.K, c.dist) for c in cameras], reference=1,
                            reference_pose=(second.R, second.t), jackknife=False)
    for index, camera in enumerate(cameras):  # the world is the rig's own: every true pose comes back
        error = pose_difference(camera.R, camera.t, result.rotations[index], result.translations[index])
        assert np.all(np.abs(error) < 1e-5)


def test_the_reported_sigma_covers_the_error_when_a_views_corners_share_their_error():
    errors, reported, jacobian = [], [], []
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        rig = ring_station_rig(rng, scale=0.5)
        cameras, observations = projected_views(rig, rng, shared=6, own=3, noise_px=0.05, view_shift_px=0.1)
        result = adjust_station(observations, [(c.K, c.dist) for c in cameras])
        for index, (R, t) in list(enumerate(relative_truth(cameras)))[1:]:
            errors.append(pose_difference(R, t, result.rotations[index], result.translations[index]))
            reported.append(result.pose_std[index])
            jacobian.append(result.pose_std_jacobian[index])
    errors, reported, jacobian = np.abs(errors), np.array(reported), np.array(jacobian)
    covered = np.mean(errors <= Z90 * reported)
    assert covered >= 0.8, covered  # 54 degrees of freedom of 9 heads
    assert np.all(reported >= jacobian)
    # the shared shifts make the Jacobian's sigma claim too much: it covers fewer errors than the reported one
    assert np.mean(errors <= Z90 * jacobian) < covered


def test_cameras_that_share_no_view_are_refused():
    rig = ring_station_rig(np.random.default_rng(7), scale=0.5)
    cameras, observations = projected_views(rig, np.random.default_rng(8), own=2, pairs={(0, 1), (2, 3)})
    assert tied_groups(observations, 4) == [{0, 1}, {2, 3}]
    with pytest.raises(ValueError, match=r"Cameras \[2, 3\] share no chain of board views with camera 0"):
        adjust_station(observations, [(c.K, c.dist) for c in cameras], jackknife=False)


def test_a_pair_tied_by_a_single_view_cannot_give_a_jackknife():
    rig = ring_station_rig(np.random.default_rng(9), scale=0.5)
    cameras, observations = projected_views(rig, np.random.default_rng(10), shared=1, own=3,
                                            pairs={(0, 1), (1, 2), (2, 3)})
    with pytest.raises(ValueError, match="no longer tied"):
        adjust_station(observations, [(c.K, c.dist) for c in cameras])


@pytest.mark.parametrize(("change", "message"), [
    ({"reference": 5}, "reference must index one of the 4 cameras"),
    ({"refined_intrinsics": [("fx", "k6")] * 4}, "cannot refine 'k6'"),
])
def test_bad_arguments_are_refused(change, message):
    rig = ring_station_rig(np.random.default_rng(11), scale=0.5)
    cameras, observations = projected_views(rig, np.random.default_rng(12), shared=2, own=0)
    with pytest.raises(ValueError, match=message):
        adjust_station(observations, [(c.K, c.dist) for c in cameras], jackknife=False, **change)


def test_an_observation_with_too_few_points_is_refused():
    observation = BoardObservation(0, 0, np.zeros((3, 3)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="at least 4 matching"):
        adjust_station([observation], [(np.eye(3), np.zeros(5))] * 2)

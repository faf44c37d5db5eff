import cv2
import numpy as np
import pytest

from services.geometry.camera import camera_center, normalized_coordinates, project_points
from services.geometry.camera_model import CameraModel
from services.structured_light.triangulate import camera_ray_table, triangulate, triangulate_map, triangulation_table


def _rotation(rx, ry, rz):
    return cv2.Rodrigues(np.deg2rad([rx, ry, rz]))[0]


def _rig(projector_dist):
    camera_R = _rotation(1.0, 20.0, 0.5)  # toed in toward the projector
    camera_C = np.array([400.0, 10.0, -5.0])
    camera = dict(K=np.array([[1400.0, 0, 640], [0, 1395.0, 400], [0, 0, 1]]),
                  dist=np.array([-0.12, 0.08, 0.001, -0.0007, -0.02]), R=camera_R, t=-camera_R @ camera_C)
    projector = dict(K=np.array([[1300.0, 0, 515], [0, 1310.0, 760], [0, 0, 1]]), dist=projector_dist,
                     R=_rotation(0.3, 0.2, -0.1), t=np.array([1.0, -2.0, 3.0]))
    return camera, projector


def _points(rng, camera, n=2000):
    """Random points inside the camera's 1280x800 view, where its distortion model is invertible."""
    points = np.column_stack([rng.uniform(-150, 150, n), rng.uniform(-100, 100, n), rng.uniform(430, 570, n)])
    pixels = project_points(points, **camera)
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < 1280) & (pixels[:, 1] >= 0) & (pixels[:, 1] < 800)
    assert inside.mean() > 0.5
    return points[inside]


@pytest.mark.parametrize("projector_dist", [
    np.zeros(0),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02]),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02, 0.01, -0.02, 0.005, 0.001, -0.0005, 0.0008, 0.0002, 0.01, -0.008]),
], ids=["pinhole", "five", "fourteen"])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_recovers_points_through_both_distortions(projector_dist, axis):
    rng = np.random.default_rng(1)
    camera, projector = _rig(projector_dist)
    points = _points(rng, camera)
    camera_pixels = project_points(points, **camera)
    projector_pixels = project_points(points, **projector)
    rays = normalized_coordinates(camera_pixels, camera["K"], camera["dist"])
    coordinate = projector_pixels[:, 0 if axis == "x" else 1]
    result = triangulate(rays, coordinate, axis, camera["R"], camera["t"], projector["K"], projector["dist"],
                         projector["R"], projector["t"])
    assert result.dtype == np.float32
    assert np.abs(result - points).max() < 2e-4  # float32 output at 500 mm


def test_projector_distortion_matters():
    """Ignoring a real projector distortion would move points by far more than the accuracy target."""
    rng = np.random.default_rng(2)
    camera, projector = _rig(np.array([0.05, -0.1, 0.0015, 0.001, 0.02]))
    points = _points(rng, camera)
    rays = normalized_coordinates(project_points(points, **camera), camera["K"], camera["dist"])
    coordinate = project_points(points, **projector)[:, 0]
    ignoring = triangulate(rays, coordinate, "x", camera["R"], camera["t"], projector["K"], np.zeros(5),
                           projector["R"], projector["t"])
    assert np.abs(ignoring - points).max() > 1.0


def test_ray_table_matches_pointwise_undistortion():
    camera, _ = _rig(np.zeros(0))
    table = camera_ray_table(camera["K"], camera["dist"], 64, 48)
    assert table.shape == (48, 64, 2)
    expected = normalized_coordinates(np.array([[10.0, 20.0], [63.0, 47.0]]), camera["K"], camera["dist"])
    np.testing.assert_allclose(table[[20, 47], [10, 63]], expected, atol=1e-7)


def test_unreachable_line_gives_nan():
    camera, projector = _rig(np.zeros(0))
    rays = np.array([[0.0, 0.0]])
    # a column far outside any plausible projector field cannot be met in front of both devices
    result = triangulate(rays, np.array([-1e7]), "x", camera["R"], camera["t"], projector["K"],
                         projector["dist"], projector["R"], projector["t"])
    assert np.isnan(result).all()


def test_rejects_bad_shapes():
    camera, projector = _rig(np.zeros(0))
    with pytest.raises(ValueError, match="camera rays but"):
        triangulate(np.zeros((3, 2)), np.zeros(2), "x", camera["R"], camera["t"], projector["K"],
                    projector["dist"], projector["R"], projector["t"])
    with pytest.raises(ValueError, match="coded axis"):
        triangulate(np.zeros((3, 2)), np.zeros(3), "z", camera["R"], camera["t"], projector["K"],
                    projector["dist"], projector["R"], projector["t"])


def _vertical_rig(projector_dist):
    """The camera above the projector, toed in: the baseline runs along projector y."""
    camera, projector = _rig(projector_dist)
    camera_R = _rotation(-20.0, 1.0, 0.5)
    camera.update(R=camera_R, t=-camera_R @ np.array([10.0, 400.0, -5.0]))
    return camera, projector


def _rear_rig(projector_dist):
    """The camera well behind the projector, looking past it: the projector sees the camera near its axis."""
    camera, projector = _rig(projector_dist)
    camera_R = _rotation(1.0, 8.0, 0.5)
    camera.update(R=camera_R, t=-camera_R @ np.array([-60.0, 10.0, -300.0]))
    return camera, projector


def _table(camera, projector, axis):
    return triangulation_table(CameraModel("camera", 1280, 800, camera["K"], camera["dist"], camera["R"], camera["t"]),
                               CameraModel("projector", 1030, 1520, projector["K"], projector["dist"], projector["R"],
                                           projector["t"]), axis)


def _pixel_points(rng, camera, n=3000):
    """Points on the viewing rays of distinct camera pixel centres, 430..570 mm in front of the projector."""
    pixels = np.unique(rng.integers(0, [1280, 800], size=(n, 2)), axis=0).astype(float)
    rays = normalized_coordinates(pixels, camera["K"], camera["dist"])
    behind_projector = -camera_center(camera["R"], camera["t"])[2]
    depth = rng.uniform(430, 570, len(rays)) + behind_projector
    in_camera = np.column_stack([rays * depth[:, None], depth])
    return pixels.astype(int), (in_camera - camera["t"]) @ camera["R"]


@pytest.mark.parametrize("projector_dist", [
    np.zeros(0),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02]),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02, 0.01, -0.02, 0.005, 0.001, -0.0005, 0.0008, 0.0002, 0.01, -0.008]),
], ids=["pinhole", "five", "fourteen"])
@pytest.mark.parametrize("axis, rig", [("x", _rig), ("y", _vertical_rig)], ids=["beside", "above"])
def test_table_triangulates_every_pixel_as_the_exact_solver(projector_dist, axis, rig):
    rng = np.random.default_rng(3)
    camera, projector = rig(projector_dist)
    table = _table(camera, projector, axis)
    pixels, points = _pixel_points(rng, camera)
    coordinate = project_points(points, **projector)[:, 0 if axis == "x" else 1]
    coordinates = np.full((800, 1280), np.nan, np.float32)
    coordinates[pixels[:, 1], pixels[:, 0]] = coordinate
    points_map = triangulate_map(table, coordinates)
    result = points_map[pixels[:, 1], pixels[:, 0]].astype(np.float64)
    # the coded coordinate of the result is the decoded one: the table is exact to 1e-4 projector pixels,
    # besides the float32 rounding of the coordinate itself
    reprojected = project_points(result, **projector)[:, 0 if axis == "x" else 1]
    assert np.abs(reprojected - coordinates[pixels[:, 1], pixels[:, 0]]).max() < 2e-4
    assert np.abs(result - points).max() < 3e-4
    assert np.isnan(np.delete(points_map.reshape(-1, 3), pixels[:, 1] * 1280 + pixels[:, 0], axis=0)).all()


def test_table_with_the_epipole_in_view_agrees_with_the_exact_solver():
    """With the camera behind the projector, columns near the epipole barely constrain depth; the table
    falls back on the exact solver there and agrees with it wherever it converges."""
    camera, projector = _rear_rig(np.array([0.05, -0.1, 0.0015, 0.001, 0.02]))
    table = _table(camera, projector, "x")
    pixels, points = _pixel_points(np.random.default_rng(4), camera, n=6000)
    projected = project_points(points, **projector)
    lit = (projected >= 0).all(axis=1) & (projected < [1030, 1520]).all(axis=1)  # what the projector shows
    pixels, coordinate = pixels[lit], projected[lit, 0].astype(np.float32)
    coordinates = np.full((800, 1280), np.nan, np.float32)
    coordinates[pixels[:, 1], pixels[:, 0]] = coordinate
    result = triangulate_map(table, coordinates)[pixels[:, 1], pixels[:, 0]]
    rays = camera_ray_table(camera["K"], camera["dist"], 1280, 800)[pixels[:, 1], pixels[:, 0]]
    exact = triangulate(rays, coordinate, "x", camera["R"], camera["t"], projector["K"], projector["dist"],
                        projector["R"], projector["t"])
    np.testing.assert_array_equal(np.isnan(result[:, 0]), np.isnan(exact[:, 0]))
    assert np.isfinite(exact[:, 0]).mean() > 0.95
    origin = projector["R"] @ camera_center(camera["R"], camera["t"]) + projector["t"]
    epipole_column = projector["K"][0, 0] * origin[0] / origin[2] + projector["K"][0, 2]
    assert 0 < epipole_column < 1030
    # within a few columns of the epipole even the exact solver stalls: depth is undetermined there
    converged = np.isfinite(exact[:, 0]) & (np.abs(coordinate - epipole_column) > 10)
    reprojected = project_points(result[converged].astype(np.float64), **projector)[:, 0]
    assert np.abs(reprojected - coordinate[converged]).max() < 1e-3


def test_table_refuses_coordinates_of_another_camera_size():
    camera, projector = _rig(np.zeros(0))
    with pytest.raises(ValueError, match="1280x800 camera"):
        triangulate_map(_table(camera, projector, "x"), np.zeros((10, 10), np.float32))

import numpy as np
import pytest

from services.geometry.camera_model import CameraModel

K = [[800, 0, 320], [0, 800, 240], [0, 0, 1]]


def test_arrays_are_read_only_copies_and_the_centre_is_computed_once():
    R = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    t = np.array([10.0, 20.0, 30.0])
    camera = CameraModel("camera", 640, 480, K, [0.1, 0, 0, 0], R, t)
    t[0] = 99.0
    assert camera.t[0] == 10.0
    with pytest.raises(ValueError):
        camera.K[0, 0] = 1.0
    np.testing.assert_allclose(camera.centre, -R.T @ [10.0, 20.0, 30.0])
    assert camera.centre is camera.centre
    assert camera.size == (640, 480)


def test_replace_equality_and_hash_follow_the_values():
    camera = CameraModel("thermal", 320, 256, K)
    moved = camera.replace(t=[0.0, 0.0, 5.0])
    assert moved != camera and moved.centre[2] == -5.0
    assert moved.replace(t=[0, 0, 0]) == camera and hash(moved.replace(t=[0, 0, 0])) == hash(camera)


def test_projection_through_the_model_matches_the_pinhole():
    camera = CameraModel("camera", 640, 480, K)
    np.testing.assert_allclose(camera.project(np.array([[10.0, -5.0, 100.0]])), [[400.0, 200.0]])


@pytest.mark.parametrize("change, words", [
    ({"K": np.eye(2)}, "K must have shape"), ({"dist": [1.0, 2.0]}, "coefficients"),
    ({"kind": "lidar"}, "kind"), ({"width": 0}, "positive"), ({"t": [1.0, 2.0]}, "t must have shape"),
])
def test_impossible_devices_are_refused(change, words):
    arguments = {"kind": "camera", "width": 640, "height": 480, "K": K} | change
    with pytest.raises(ValueError, match=words):
        CameraModel(**arguments)

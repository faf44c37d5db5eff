"""Small virtual rigs so that rendering tests stay fast."""

import numpy as np
import pytest

from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel


def aimed_device(kind, size, focal, centre, target, dist=()):
    """A device of ``size`` (w, h) and ``focal`` px at ``centre`` whose optical axis passes through ``target``."""
    forward = np.subtract(target, centre, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])
    width, height = size
    K = [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]]
    return CameraModel(kind=kind, width=width, height=height, K=K, dist=list(dist), R=R.tolist(),
                  t=(-R @ np.asarray(centre, float)).tolist())


@pytest.fixture
def small_rig():
    """Projector 160x120 at the origin and camera 200x150 at (150, 0, 0), both aimed at (0, 0, 400), distorted."""
    return Rig(devices={
        "projector": aimed_device("projector", (160, 120), 200.0, (0, 0, 0), (0, 0, 400), (0.08, -0.05, 0.002, 0, 0)),
        "camera": aimed_device("camera", (200, 150), 230.0, (150, 0, 0), (0, 0, 400), (-0.25, 0.1, 0.003, -0.002, 0)),
    })


@pytest.fixture
def aimed():
    """The ``aimed_device`` factory, for tests that build their own devices."""
    return aimed_device

import numpy as np
import pytest

from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView

pytestmark = pytest.mark.integration


def _cloud(hot_scene, with_normals: bool) -> dict:
    cloud = {"x": hot_scene.points[:, 0].astype(np.float32), "y": hot_scene.points[:, 1].astype(np.float32),
             "z": hot_scene.points[:, 2].astype(np.float32), "quality": np.ones(len(hot_scene.points), np.float32),
             "red": np.zeros(len(hot_scene.points), np.uint8)}
    if with_normals:
        cloud.update(nx=hot_scene.normals[:, 0], ny=hot_scene.normals[:, 1], nz=hot_scene.normals[:, 2])
    return cloud


@pytest.mark.parametrize("with_normals", [True, False])
def test_field_adds_temperature_view_angle_and_colours(hot_scene, with_normals):
    viewpoint = -hot_scene.camera.R.T @ hot_scene.camera.t
    field = temperature_field(_cloud(hot_scene, with_normals), [ThermalView(hot_scene.thermal, hot_scene.image)],
                              viewpoint)
    assert set(field) >= {"x", "y", "z", "quality", "temperature", "view_angle", "red", "green", "blue"}
    assert field["temperature"].dtype == np.float32 and field["red"].dtype == np.uint8
    error = np.abs(field["temperature"] - hot_scene.truth)[hot_scene.visible]
    assert np.nanmedian(error) <= 1.0
    assert np.mean(np.isnan(field["temperature"][~hot_scene.visible])) >= 0.99
    assert np.any(field["red"] > 0)  # the old colour was replaced


def test_field_needs_coordinates(hot_scene):
    with pytest.raises(ValueError, match="coordinate"):
        temperature_field({"x": np.zeros(3)}, [ThermalView(hot_scene.thermal, hot_scene.image)], np.zeros(3))

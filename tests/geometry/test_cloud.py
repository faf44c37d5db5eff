import numpy as np
import pytest

from services.geometry.cloud import PointCloud


def test_a_cloud_is_read_only_and_derived_clouds_share_arrays():
    x = np.arange(4, dtype=np.float32)
    cloud = PointCloud({"x": x, "y": x, "z": x})
    with pytest.raises(ValueError):
        cloud["x"][0] = 7.0
    x[0] = 7.0  # the caller's own array stays writable
    field = cloud.with_properties(temperature=np.full(4, 900.0, np.float32))
    assert field.has_temperature and not cloud.has_temperature
    assert np.shares_memory(field["x"], cloud["x"])
    assert set(field.without("temperature")) == {"x", "y", "z"}
    assert field.units["temperature"] == "degC" and field.units["x"] == "mm"
    np.testing.assert_array_equal(field.points[:, 2], x)
    assert len(field) == 4


def test_properties_of_different_lengths_or_dimensions_are_refused():
    with pytest.raises(ValueError, match="same length"):
        PointCloud({"x": np.zeros(2), "y": np.zeros(3)})
    with pytest.raises(ValueError, match="1-D"):
        PointCloud({"x": np.zeros((2, 2))})
    with pytest.raises(ValueError, match="coordinate properties"):
        PointCloud({"x": np.zeros(2)}).points

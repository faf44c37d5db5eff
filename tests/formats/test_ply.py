import numpy as np
import pytest

from services.errors import InputError
from services.formats.ply import cloud_from_ply, cloud_to_ply, read_cloud, write_cloud
from services.geometry.cloud import PointCloud


def test_binary_little_endian_round_trip(tmp_path):
    cloud = {"x": np.arange(5, dtype=np.float32), "y": np.ones(5, np.float32), "z": np.zeros(5, np.float32),
             "red": np.arange(5, dtype=np.uint8)}
    write_cloud(tmp_path / "c.ply", cloud)
    assert (tmp_path / "c.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0")
    again = read_cloud(tmp_path / "c.ply")
    assert list(again) == ["x", "y", "z", "red"]
    for name in cloud:
        np.testing.assert_array_equal(again[name], cloud[name])
        assert again[name].dtype == cloud[name].dtype


def test_bad_files(tmp_path):
    with pytest.raises(ValueError, match="same length"):
        write_cloud(tmp_path / "x.ply", {"x": np.zeros(2), "y": np.zeros(3)})
    with pytest.raises(InputError, match="missing"):
        read_cloud(tmp_path / "none.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(InputError, match="junk.ply"):
        read_cloud(tmp_path / "junk.ply")


def test_bytes_round_trip_keeps_units_and_comments():
    cloud = PointCloud({"x": np.arange(3, dtype=np.float32), "y": np.zeros(3, np.float32),
                        "z": np.full(3, 500, np.float32), "temperature": np.array([900.0, np.nan, 950.0], np.float32)},
                       comments=("made by a test",))
    data = cloud_to_ply(cloud)
    assert b"comment unit temperature degC" in data and b"comment unit x mm" in data
    again = cloud_from_ply(data, "field.ply")
    assert again.units == {"x": "mm", "y": "mm", "z": "mm", "temperature": "degC"}
    assert again.comments == ("made by a test",)
    np.testing.assert_array_equal(again["temperature"], cloud["temperature"])
    assert len(again) == 3


def test_bytes_that_are_not_a_ply_name_their_source():
    with pytest.raises(InputError, match="artifact abc: not a readable PLY"):
        cloud_from_ply(b"junk", "artifact abc")

import numpy as np
import pytest

from services.errors import InputError
from services.formats.ply import read_cloud, write_cloud


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

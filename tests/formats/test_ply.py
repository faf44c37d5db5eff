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


def test_a_binary_cloud_is_read_from_bytes_as_plyfile_reads_it_from_a_file(tmp_path):
    """The in-memory reader of the clouds this project writes (every property scalar) gives what plyfile gives
    for the same file, big-endian too; other PLYs go through plyfile."""
    import numpy as np
    from plyfile import PlyData, PlyElement

    from services.formats.ply import cloud_from_ply, cloud_to_ply
    from services.geometry.cloud import PointCloud

    rng = np.random.default_rng(3)
    cloud = PointCloud({"x": rng.random(1000).astype(np.float32), "y": rng.random(1000), "head": np.arange(1000, dtype=np.int32),
                        "red": rng.integers(0, 255, 1000).astype(np.uint8)}, {"x": "mm"}, ("made here",))
    read = cloud_from_ply(cloud_to_ply(cloud))
    assert dict(read.units) == dict(cloud.units) and read.comments == ("made here",)
    for name, values in cloud.items():
        assert read[name].dtype == values.dtype and np.array_equal(read[name], values)
    vertices = np.array([(1.5, 7), (2.5, 9)], dtype=[("x", ">f8"), ("k", ">i2")])
    path = tmp_path / "big.ply"
    PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order=">").write(str(path))
    big = cloud_from_ply(path.read_bytes())
    assert big["x"].tolist() == [1.5, 2.5] and big["k"].tolist() == [7, 9] and big["x"].dtype.isnative
    faces = PlyElement.describe(np.array([([0, 1, 0],)], dtype=[("vertex_indices", "O")]), "face")
    path = tmp_path / "mesh.ply"
    PlyData([PlyElement.describe(vertices, "vertex"), faces], text=False).write(str(path))
    assert cloud_from_ply(path.read_bytes())["k"].tolist() == [7, 9]

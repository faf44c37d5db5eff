import numpy as np
import pytest

from services.errors import InputError
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.tables import TriangulationTables, table_key

pytestmark = pytest.mark.integration


def test_a_capture_becomes_a_cloud_on_the_plane(small_capture):
    cloud = reconstruct_capture(frames=small_capture.frames, sequence=small_capture.sequence,
                                rig=small_capture.rig, tables=TriangulationTables()).cloud
    assert len(cloud) > 5_000
    assert np.median(np.abs(cloud["z"] - 500.0)) < 0.2
    assert cloud.units["z"] == "mm"


def test_a_manifest_for_another_projector_is_refused_on_every_path(small_capture):
    """The projector-size check is made by the use case, so the worker path makes it too."""
    projector = small_capture.rig.devices["projector"]
    rig = small_capture.rig.with_device("projector", projector.replace(width=projector.width + 8))
    with pytest.raises(InputError, match=r"the scan: the manifest is for a 256x192 projector but the rig's projector "
                                         r"is 264x192"):
        reconstruct_capture(frames=small_capture.frames, sequence=small_capture.sequence, rig=rig,
                            tables=TriangulationTables(), source="the scan")


def test_frames_of_another_size_are_refused(small_capture):
    with pytest.raises(InputError, match="frames are 128x192 but the rig's camera is 256x192"):
        reconstruct_capture(frames=small_capture.frames[:, :, :128], sequence=small_capture.sequence,
                            rig=small_capture.rig, tables=TriangulationTables())


def test_a_black_capture_says_why_no_point_was_reconstructed(small_capture):
    with pytest.raises(InputError, match="no point could be reconstructed"):
        reconstruct_capture(frames=np.zeros_like(small_capture.frames), sequence=small_capture.sequence,
                            rig=small_capture.rig, tables=TriangulationTables())


def test_tables_are_built_once_per_calibration_and_reloaded_from_disk(small_capture, tmp_path):
    camera, projector = small_capture.rig.devices["camera"], small_capture.rig.devices["projector"]
    tables = TriangulationTables(tmp_path)
    first = tables.get(camera, projector, "x")
    assert tables.get(camera, projector, "x") is first and tables.built == 1
    assert (tmp_path / f"{table_key(camera, projector, 'x')}.npz").is_file()
    another_process = TriangulationTables(tmp_path)
    loaded = another_process.get(camera, projector, "x")
    assert another_process.built == 0
    np.testing.assert_array_equal(loaded.line_offsets, first.line_offsets)
    np.testing.assert_array_equal(loaded.pixel_geometry, first.pixel_geometry)
    moved = camera.replace(t=camera.t + [0.5, 0.0, 0.0])
    assert table_key(moved, projector, "x") != table_key(camera, projector, "x")
    another_process.get(moved, projector, "x")
    assert another_process.built == 1


def test_a_damaged_table_file_is_rebuilt(small_capture, tmp_path):
    camera, projector = small_capture.rig.devices["camera"], small_capture.rig.devices["projector"]
    (tmp_path / f"{table_key(camera, projector, 'x')}.npz").write_bytes(b"not an npz")
    tables = TriangulationTables(tmp_path)
    tables.get(camera, projector, "x")
    assert tables.built == 1

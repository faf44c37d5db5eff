"""Scans logged to Rerun are read back from the .rrd (and from the live proxy) exactly as logged."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import rerun.chunk

from services.errors import InputError
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.fusion.colormap import temperature_colors
from services.streaming.proxy import RerunProxy, rerun_executable
from services.streaming.field import field_scene, verdict_markdown
from services.streaming.recording import StationView, scan_recording

# A file a viewer is still saving has no footer yet; reading it is the point of the live tests.
pytestmark = [pytest.mark.integration, pytest.mark.filterwarnings("ignore:RRD file has no footer")]


def _rotation_about_y(degrees: float) -> list[list[float]]:
    angle = np.radians(degrees)
    c, s = np.cos(angle), np.sin(angle)
    return [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]


@pytest.fixture
def rig() -> Rig:
    return Rig(devices={
        "projector": CameraModel(kind="projector", width=1280, height=800, K=[[1500, 0, 640], [0, 1500, 400], [0, 0, 1]]),
        "camera": CameraModel(kind="camera", width=1280, height=800, K=[[1400, 0, 639.5], [0, 1410, 399.5], [0, 0, 1]],
                         R=_rotation_about_y(-20), t=[-330.0, 0.0, 120.0]),
        "thermal": CameraModel(kind="thermal", width=320, height=256, K=[[380, 0, 160], [0, 385, 128], [0, 0, 1]],
                          R=_rotation_about_y(-10), t=[-180.0, 120.0, 30.0]),
    })


@pytest.fixture
def field() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    count = 500
    temperature = rng.uniform(700, 1100, count).astype(np.float32)
    temperature[::7] = np.nan
    return {"x": rng.uniform(-50, 50, count).astype(np.float32), "y": rng.uniform(-40, 40, count).astype(np.float32),
            "z": rng.uniform(580, 620, count).astype(np.float32), "temperature": temperature}


def _read_rrd(path: Path) -> dict[str, dict[str, list]]:
    """Entity path -> component -> values of every row, in log order."""
    columns: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for chunk in rerun.chunk.RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        for name, column in zip(batch.schema.names, batch.columns):
            if pa.types.is_timestamp(column.type):
                column = column.cast(pa.int64())  # nanoseconds; Python datetimes cannot hold them
            columns[chunk.entity_path][name].extend(column.to_pylist())
    return columns


def test_scan_recording_holds_points_temperatures_and_colours(tmp_path, rig, field):
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-42", field_scene(field, rig)))

    assert [entry.recording_id for entry in rerun.chunk.RrdReader(path).recordings()] == ["scan-42"]
    logged = _read_rrd(path)["/world/field"]
    positions = np.array(logged["Points3D:positions"][0])
    np.testing.assert_array_equal(positions, np.column_stack([field["x"], field["y"], field["z"]]))
    temperature = np.array(logged["temperature"][0], dtype=np.float64)
    np.testing.assert_array_equal(temperature, field["temperature"].astype(np.float64))
    colours = np.array(logged["Points3D:colors"][0], dtype=np.uint32)
    expected = temperature_colors(field["temperature"]).astype(np.uint32)
    packed = (expected[:, 0] << 24) | (expected[:, 1] << 16) | (expected[:, 2] << 8) | 0xFF
    np.testing.assert_array_equal(colours, packed)


def test_scan_recordings_leave_no_threads_behind(rig, field):
    """Rerun keeps a dropped stream's threads unless orphans are cleaned up (rerun-io/rerun#2116): a worker
    making one recording per scan must not grow by a thread per scan."""
    scene = field_scene(field, rig)
    scan_recording("scan-0", scene)
    threads = len(os.listdir("/proc/self/task"))
    for index in range(1, 6):
        scan_recording(f"scan-{index}", scene)
    # the leak left two threads per scan (ten here); the suite's other threads (a pool's worker starting
    # or stopping) may change the count by one or two meanwhile
    assert len(os.listdir("/proc/self/task")) <= threads + 2


def test_device_frusta_keep_the_world_to_device_pose(tmp_path, rig, field):
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-1", field_scene(field, rig)))
    logged = _read_rrd(path)
    for name, device in rig.devices.items():
        transform = logged[f"/world/devices/{name}"]
        np.testing.assert_allclose(transform["Transform3D:translation"][0][0], device.t, atol=1e-5)
        # Rerun stores 3x3 matrices column-major.
        matrix = np.array(transform["Transform3D:mat3x3"][0][0]).reshape(3, 3).T
        np.testing.assert_allclose(matrix, device.R, atol=1e-6)
        assert transform["Transform3D:relation"][0] == [2]  # ChildFromParent: x_dev = R x_world + t
        pinhole = logged[f"/world/devices/{name}/image"]
        intrinsics = np.array(pinhole["Pinhole:image_from_camera"][0][0]).reshape(3, 3).T
        np.testing.assert_allclose(intrinsics, device.K)
        assert pinhole["Pinhole:resolution"][0][0] == [device.width, device.height]


def test_thermal_image_shares_the_points_colour_scale(tmp_path, rig, field):
    """The thermal image is mapped on the field's scale; the points keep the field's own colours."""
    low, high = np.nanmin(field["temperature"]), np.nanmax(field["temperature"])
    thermal = np.linspace(600, 1200, 320 * 256, dtype=np.float32).reshape(256, 320)
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-1", field_scene(field, rig, thermal_image=thermal)))
    logged = _read_rrd(path)["/world/devices/thermal/image"]

    image_format = logged["Image:format"][0][0]
    assert (image_format["width"], image_format["height"]) == (320, 256)
    pixels = np.array(logged["Image:buffer"][0][0], dtype=np.uint8).reshape(256, 320, 3)
    np.testing.assert_array_equal(pixels, temperature_colors(thermal, low, high))
    assert (pixels[0, 0] == temperature_colors(np.array([low]))[0]).all()  # 600 C is below the field: clipped


def test_the_fields_own_colours_are_logged_not_recomputed(tmp_path, rig, field):
    field = {**field, "red": np.full(500, 10, np.uint8), "green": np.full(500, 20, np.uint8),
             "blue": np.full(500, 30, np.uint8)}
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-1", field_scene(field, rig)))
    colours = np.array(_read_rrd(path)["/world/field"]["Points3D:colors"][0], dtype=np.uint32)
    assert (colours == (10 << 24 | 20 << 16 | 30 << 8 | 0xFF)).all()


def test_the_deviation_layer_holds_the_parts_points_deviations_and_colours(tmp_path, rig, field):
    """Beside the field, the inspected part's points with their deviation and the deviation colour map."""
    from services.inspection.deviation import deviation_colors

    deviation = np.linspace(-1.5, 1.5, 500).astype(np.float32)
    deviation[:100] = np.nan  # not the part's (the wall)
    rgb = deviation_colors(deviation, (-1.0, 1.0))
    layer = {**field, "deviation": deviation, "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-1", field_scene(field, rig, deviation=layer)))
    logged = _read_rrd(path)["/world/deviation"]
    positions = np.array(logged["Points3D:positions"][0])
    np.testing.assert_array_equal(positions, np.column_stack([field["x"], field["y"], field["z"]])[100:])
    np.testing.assert_array_equal(np.array(logged["deviation"][0], dtype=np.float32), deviation[100:])
    colours = np.array(logged["Points3D:colors"][0], dtype=np.uint32)
    expected = rgb[100:].astype(np.uint32)
    np.testing.assert_array_equal(colours, (expected[:, 0] << 24) | (expected[:, 1] << 16) | (expected[:, 2] << 8) | 0xFF)
    assert tuple(rgb[-1]) != tuple(rgb[100])  # excess and missing material differ in colour
    assert len(_read_rrd(path)["/world/field"]["Points3D:positions"][0]) == 500  # the field stays whole


def test_a_scan_not_inspected_clears_the_deviation_layer(tmp_path, rig, field):
    path = tmp_path / "field.rrd"
    path.write_bytes(scan_recording("scan-1", field_scene(field, rig)))
    logged = _read_rrd(path)["/world/deviation"]
    assert "Points3D:positions" not in logged and logged  # only the clear


def test_the_verdict_is_logged_as_markdown_and_cleared_when_not_inspected(tmp_path, rig, field):
    report = {"part": "shaft-90", "verdict": "NotOK",
              "features": [{"name": "body", "verdict": "NotOK", "deviation": 0.412, "uncertainty": 0.11, "cold": 90.412,
                            "nominal": 90.0},
                           {"name": "face", "verdict": "NotDecidable", "error": "the view does not show it"}],
              "surface": {"verdict": "OK", "cell_min": -0.2, "cell_max": 0.3, "uncertainty": 0.05}}
    text = verdict_markdown(report)
    assert text.startswith("# shaft-90: NotOK") and "| body | NotOK | +0.412 | 0.110 | 90.412 | 90.000 |" in text
    assert "| face | NotDecidable |" in text and "| surface | OK | -0.200..+0.300 |" in text
    inspected, plain = tmp_path / "inspected.rrd", tmp_path / "plain.rrd"
    inspected.write_bytes(scan_recording("scan-1", field_scene(field, rig, verdict=text)))
    plain.write_bytes(scan_recording("scan-2", field_scene(field, rig)))
    logged = _read_rrd(inspected)["/verdict"]
    assert logged["TextDocument:text"][0] in ([text], text)  # one row: the page as logged
    assert "TextDocument:text" not in _read_rrd(plain)["/verdict"] and _read_rrd(plain)["/verdict"]


def test_field_without_temperature_is_refused(rig, field):
    del field["temperature"]
    with pytest.raises(ValueError, match="temperature"):
        scan_recording("scan-1", field_scene(field, rig))


def test_thermal_image_of_the_wrong_size_is_refused(rig, field):
    with pytest.raises(ValueError, match="320x256"):
        scan_recording("scan-1", field_scene(field, rig, thermal_image=np.zeros((10, 10))))


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, as in /proc/net/tcp) listening on ``port``."""
    addresses = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:
                addresses.add(address)
    return addresses


def _wait_for_rows(path: Path, entity: str, rows: int, timeout_s: float = 20.0) -> list[int]:
    """The ``scan`` steps logged to ``entity`` in a file a viewer is saving, once ``rows`` have arrived."""
    deadline = time.monotonic() + timeout_s
    steps: list[int] = []
    while len(steps) < rows and time.monotonic() < deadline:
        time.sleep(0.2)
        if path.exists() and path.stat().st_size:
            try:
                steps = sorted(_read_rrd(path)[entity]["scan"])
            except (OSError, ValueError):
                steps = []  # caught mid-write: read again
    return steps


def test_proxy_listens_on_loopback_only():
    port = _free_port()
    with RerunProxy("127.0.0.1", port) as proxy:
        assert proxy.running
        assert proxy.url == f"rerun+http://127.0.0.1:{port}/proxy"
        assert _listening_addresses(port) == {"0100007F"}  # 127.0.0.1, nothing on 0.0.0.0
    assert not proxy.running
    assert _listening_addresses(port) == set()


def test_proxy_refuses_a_port_in_use():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(InputError, match="already in use"):
            RerunProxy("127.0.0.1", busy.getsockname()[1])


def test_live_view_delivers_each_field_to_a_connected_viewer(tmp_path, rig, field):
    saved = tmp_path / "live.rrd"
    with RerunProxy("127.0.0.1", _free_port()) as proxy:
        view = StationView(proxy.url, "press-3")
        steps = [view.publish(field_scene(field, rig)), view.publish(field_scene(field, rig))]
        view.close()
        # A viewer joining late still gets every field: the proxy buffers them.
        viewer = subprocess.Popen([rerun_executable(), proxy.url, "--save", str(saved)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            assert _wait_for_rows(saved, "/world/field", 2) == [1, 2]
        finally:
            viewer.terminate()
            viewer.wait(timeout=10)
    assert steps == [1, 2]
    logged = _read_rrd(saved)
    np.testing.assert_array_equal(np.array(logged["/world/field"]["Points3D:positions"][-1]),
                                  np.column_stack([field["x"], field["y"], field["z"]]))


def test_live_view_waits_for_a_proxy_that_is_down_without_holding_up_scans(tmp_path, rig, field):
    port = _free_port()
    view = StationView(f"rerun+http://127.0.0.1:{port}/proxy", "press-3")
    assert view.publish(field_scene(field, rig)) is None, "no proxy: the field is not shown, the scan goes on"
    saved = tmp_path / "live.rrd"
    with RerunProxy("127.0.0.1", port) as proxy:
        assert view.publish(field_scene(field, rig)) == 2, "connects as soon as the proxy is up"
        view.close()
        viewer = subprocess.Popen([rerun_executable(), proxy.url, "--save", str(saved)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            assert _wait_for_rows(saved, "/world/field", 1) == [2]
        finally:
            viewer.terminate()
            viewer.wait(timeout=10)


def test_live_view_needs_a_proxy_url():
    with pytest.raises(ValueError, match="rerun\\+http://HOST:PORT/proxy"):
        StationView("localhost", "press-3")

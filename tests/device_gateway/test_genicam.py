"""The GenICam driver against Aravis' in-process fake camera (its ``Fake`` interface, device ``Fake_1``).

This fake camera runs free whatever its trigger (the GigE Vision fake of test_genicam_gigevision.py honours
triggers). Its images are a documented test pattern (Aravis' ``arv_fake_camera_diagonal_ramp``), which
makes them ground truth: pixel (x, y) of frame ``id`` is ``((x + y + id) % 255) * scale`` in Mono8 and
``((256 * (x + y + id)) % 65535) * scale`` in Mono16, clipped to the format's range and truncated, with
``scale = 1 + GainRaw + log10(ExposureTimeAbs / 10000 us)``. So a frame shows the exposure and gain the driver
set, the region it chose and which frame of the camera's count it is.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from device_gateway.devices import DeviceUnavailable
from device_gateway.drivers.genicam import CameraClock, GenicamCamera, GenicamThermal, counts_to_celsius
from gi.repository import Aravis  # noqa: I001  (after the driver, which chooses Aravis' version)


@pytest.fixture(autouse=True)
def _no_network_discovery():
    """Only the Fake (and USB) interfaces are searched here: a GigE Vision search broadcasts on every network."""
    Aravis.disable_interface("GigEVision")
    yield
    Aravis.enable_interface("GigEVision")


@pytest.fixture
def camera():
    camera = GenicamCamera(device_id="Fake_1", pixel_format="Mono8", exposure_us=20000, gain=1,
                           region=(16, 8, 96, 64), trigger="Software")
    camera.open()
    yield camera
    camera.close()


def test_counts_become_celsius_at_the_stated_scale_and_offset():
    counts = np.array([[0, 27315, 65535]], np.uint16)
    np.testing.assert_allclose(counts_to_celsius(counts, 0.01), [[-273.15, 0.0, 382.2]], atol=1e-4)
    np.testing.assert_allclose(counts_to_celsius(counts, 0.1, offset_k=-100.0), [[-373.15, 2358.35, 6180.35]],
                               atol=1e-3)
    assert counts_to_celsius(counts, 0.01).dtype == np.float32
    with pytest.raises(ValueError, match="kelvin per count"):
        counts_to_celsius(counts, 0.0)
    with pytest.raises(ValueError, match="integers"):
        counts_to_celsius(counts.astype(np.float32), 0.01)


def test_the_camera_clock_keeps_the_cameras_intervals_until_it_forgets():
    clock = CameraClock()
    clock.observe(camera_ns=1_000, host_ns=5_000_000_900)
    clock.observe(camera_ns=2_000, host_ns=5_000_001_400)  # a faster transfer does not move it
    assert clock.offset_ns == 4_999_999_900
    assert clock.wall_time(10_000) == pytest.approx(5.0000099, abs=1e-9)
    clock.forget()
    with pytest.raises(ValueError, match="observe a frame first"):
        clock.wall_time(10_000)
    clock.observe(camera_ns=3_000, host_ns=5_000_003_300)
    assert clock.offset_ns == 5_000_000_300


def test_frames_are_the_cameras_with_its_exposure_gain_and_region(camera, aravis_fake_ramp):
    info = camera.info
    assert (info.driver, info.width, info.height, info.model, info.serial) == ("genicam", 96, 64, "Aravis Fake", "1")
    assert camera.exposure_us == 20000 and camera.saturation_level == 255
    frames = [camera.grab(timeout_s=2.0) for _ in range(3)]
    ids = [frame.metadata["frame_id"] for frame in frames]
    assert ids == sorted(set(ids)), "a new frame each grab"
    for frame in frames:
        assert frame.image.dtype == np.uint8 and frame.image.shape == (64, 96)
        expected = aravis_fake_ramp(96, 64, frame.metadata["frame_id"], 20000, 1, 8)
        np.testing.assert_array_equal(frame.image, expected)

    camera.set_exposure(10000)
    frame = camera.grab(timeout_s=2.0)
    assert frame.metadata["exposure_us"] == 10000
    np.testing.assert_array_equal(frame.image, aravis_fake_ramp(96, 64, frame.metadata["frame_id"], 10000, 1, 8))


def test_timestamps_come_from_the_camera(camera):
    before = time.time()
    frames = [camera.grab(timeout_s=2.0) for _ in range(3)]
    after = time.time()
    stamps = np.array([frame.timestamp for frame in frames])
    camera_s = np.array([frame.metadata["camera_timestamp_ns"] for frame in frames]) / 1e9
    assert np.all(np.diff(stamps) > 0)
    np.testing.assert_allclose(np.diff(stamps), np.diff(camera_s), atol=1e-6)  # the camera's intervals exactly
    assert before - 0.1 <= stamps[0] and stamps[-1] <= after  # on the host's wall clock


def test_twelve_and_sixteen_bit_frames_keep_their_depth(aravis_fake_ramp):
    camera = GenicamCamera(device_id="Fake_1", pixel_format="Mono16", exposure_us=10000, region=(0, 0, 80, 60))
    camera.open()
    try:
        frame = camera.grab(timeout_s=2.0)
    finally:
        camera.close()
    assert frame.image.dtype == np.uint16 and camera.saturation_level == 65535
    np.testing.assert_array_equal(frame.image, aravis_fake_ramp(80, 60, frame.metadata["frame_id"], 10000, 0, 16))
    assert GenicamCamera(device_id="x", pixel_format="Mono12").saturation_level == 4095


def test_a_pixel_format_the_camera_lacks_is_refused_naming_what_it_offers():
    camera = GenicamCamera(device_id="Fake_1", pixel_format="Mono12")
    with pytest.raises(DeviceUnavailable, match=r"camera 'camera' \(GenICam Fake_1\) does not offer pixel format "
                                                r"Mono12 \(it offers .*Mono8.*Mono16"):
        camera.open()
    assert not camera.is_open


def test_a_region_outside_the_sensor_is_refused():
    camera = GenicamCamera(device_id="Fake_1", region=(2000, 0, 1280, 800))
    with pytest.raises(DeviceUnavailable, match="does not fit its 2048x2048 sensor"):
        camera.open()


def test_a_missing_camera_is_named_with_those_found():
    camera = GenicamCamera(device_id="Basler-acA1920-40gm-40012345")
    with pytest.raises(DeviceUnavailable, match=r"GenICam Basler-acA1920-40gm-40012345\) is not connected "
                                                r"\(found: .*Fake_1"):
        camera.open()


def test_a_free_running_thermal_camera_gives_celsius_exposed_after_the_grab(aravis_fake_ramp):
    thermal = GenicamThermal(device_id="Fake_1", kelvin_per_count=0.1, offset_k=5.0, region=(0, 0, 64, 48))
    thermal.open()
    try:
        time.sleep(0.2)  # frames queue up meanwhile: none of them is the grab's
        requested = time.time()
        frame = thermal.grab(timeout_s=2.0)
    finally:
        thermal.close()
    assert frame.timestamp >= requested
    counts = aravis_fake_ramp(64, 48, frame.metadata["frame_id"], 10000, 0, 16)
    np.testing.assert_allclose(frame.image, counts * 0.1 + 5.0 - 273.15, atol=1e-3)
    assert frame.image.dtype == np.float32
    assert frame.metadata["units"] == "degC" and frame.metadata["kelvin_per_count"] == 0.1


@pytest.mark.parametrize(("options", "message"), [
    ({"pixel_format": "Mono12p"}, "Mono12p"), ({"trigger": "Hardware"}, "'Software' or an input line"),
    ({"exposure_us": 0}, "positive"), ({"region": (0, 0, 0, 10)}, "positive size"), ({"device_id": ""}, "device id"),
])
def test_bad_options_are_refused_before_opening(options, message):
    with pytest.raises(ValueError, match=message):
        GenicamCamera(**{"device_id": "Fake_1", **options})
    with pytest.raises(ValueError, match="kelvin per count"):
        GenicamThermal(device_id="Fake_1", kelvin_per_count=-0.01)

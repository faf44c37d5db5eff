"""OAK drivers without hardware: fail fast and clearly; frames converted exactly (host-made depthai frames)."""

from __future__ import annotations

import datetime
import time

import depthai as dai
import numpy as np
import pytest

from device_gateway.devices import DeviceLost, DeviceUnavailable
from device_gateway.drivers.oak import (
    OakCamera,
    OakThermal,
    configure_camera,
    configure_thermal,
    find_device,
    frame_metadata,
    host_time_of,
    thermal_image,
)


@pytest.mark.parametrize("driver", [OakCamera, OakThermal])
def test_a_missing_device_fails_fast_naming_it(driver, monkeypatch):
    searches = []
    search = dai.Device.getAllAvailableDevices
    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", lambda: searches.append(1) or search())
    device = driver(device_id="19443010A1B2C3D4E5")
    with pytest.raises(DeviceUnavailable, match="'19443010A1B2C3D4E5' is not connected"):
        device.open()
    assert searches == [1], "one bounded search, not depthai's implicit wait for the device"
    assert not device.is_open


def test_grab_before_open_is_a_lost_device():
    with pytest.raises(DeviceLost, match="not open"):
        OakCamera().grab(timeout_s=0.1)


def test_unknown_board_socket_is_refused():
    with pytest.raises(ValueError, match="CAM_Z"):
        OakCamera(socket="CAM_Z")


def _frame(image: np.ndarray, kind: dai.ImgFrame.Type, age_s: float = 0.0) -> dai.ImgFrame:
    frame = dai.ImgFrame()
    frame.setType(kind)
    frame.setWidth(image.shape[1])
    frame.setHeight(image.shape[0])
    frame.setStride(image.shape[1] * image.itemsize)
    frame.setData(image.view(np.uint8).ravel())
    frame.setTimestamp(dai.Clock.now() - datetime.timedelta(seconds=age_s))
    frame.setSequenceNum(17)
    return frame


def test_thermal_frames_are_float32_celsius():
    temperatures = (np.linspace(20, 1100, 12 * 16).reshape(12, 16)).astype(np.float16)
    image = thermal_image(_frame(temperatures, dai.ImgFrame.Type.GRAYF16))
    assert image.dtype == np.float32
    np.testing.assert_array_equal(image, temperatures.astype(np.float32))


def test_a_thermal_frame_of_another_type_is_refused():
    with pytest.raises(DeviceLost, match="GRAYF16"):
        thermal_image(_frame(np.zeros((4, 4), np.uint8), dai.ImgFrame.Type.GRAY8))


def test_frame_time_and_metadata():
    frame = _frame(np.zeros((4, 4), np.uint8), dai.ImgFrame.Type.GRAY8, age_s=1.5)
    assert host_time_of(frame) == pytest.approx(time.time() - 1.5, abs=0.05)
    assert frame_metadata(frame)["sequence"] == 17
    assert frame_metadata(frame)["lens_position"] == frame.getLensPosition()


def test_a_device_configured_by_ip_is_connected_to_directly_without_a_search(monkeypatch):
    def no_search():
        raise AssertionError("a broadcast search, which a container network does not pass")

    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", no_search)
    info = find_device("192.168.1.44", "thermal")
    assert (info.name, info.protocol) == ("192.168.1.44", dai.XLinkProtocol.X_LINK_TCP_IP)


def test_the_camera_keeps_its_exposure_and_the_focus_it_was_calibrated_at():
    control = dai.CameraControl()
    configure_camera(control, exposure_us=4000, iso=200, lens_position=97)
    assert (control.getLensPosition(), control.getSensitivity()) == (97, 200)
    assert control.getExposureTime() == datetime.timedelta(microseconds=4000)
    with pytest.raises(ValueError, match="0..255"):
        OakCamera(lens_position=300)


@pytest.mark.parametrize(("mode", "expected"), [("low", dai.ThermalGainMode.LOW), ("high", dai.ThermalGainMode.HIGH)])
def test_the_thermal_gain_is_explicit_and_its_own_emissivity_correction_is_off(mode, expected):
    config = dai.ThermalConfig()
    configure_thermal(config, mode)
    assert config.ambientParams.gainMode == expected
    assert config.ambientParams.targetEmissivity == 128  # 128/128: emissivity 1, ours is applied in fusion
    with pytest.raises(ValueError, match="'low' or 'high'"):
        OakThermal(gain_mode="medium")

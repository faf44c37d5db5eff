"""Tests of services.formats.station_capture: the station capture's layout, written and read back."""

import numpy as np
import pytest

from services.errors import InputError
from services.formats.rig import Head, Rig
from services.formats.station_capture import (HeadFrames, is_station_capture, read_head_capture,
                                              read_station_capture, save_station_capture, thermal_path)
from services.formats.thermal import read_thermal_frame
from services.geometry.camera_model import CameraModel
from services.structured_light.patterns import generate_sequence

pytestmark = pytest.mark.unit


def _device(kind, x):
    return CameraModel(kind=kind, width=64, height=48, K=[[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]], dist=[],
                       R=np.eye(3).tolist(), t=[x, 0.0, 0.0])


@pytest.fixture
def rig():
    devices = {"camera-a": _device("camera", 0), "projector-a": _device("projector", 50),
               "camera-b": _device("camera", 100), "projector-b": _device("projector", 150),
               "ir": _device("thermal", 200)}
    return Rig(devices, station_heads=(Head("a", "camera-a", "projector-a"), Head("b", "camera-b", "projector-b")))


def _heads():
    sequence, patterns = generate_sequence(64, 48, closing_black=True)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 200, (len(patterns), 48, 64), dtype=np.uint8) for _ in range(2)]
    for stack in frames:  # white brighter than black, as a real capture
        stack[0] = 250
        stack[1] = 5
    return sequence, (HeadFrames("a", sequence, frames[0]), HeadFrames("b", sequence, frames[1]))


def test_a_station_capture_is_written_and_read_back_head_by_head(tmp_path, rig):
    sequence, heads = _heads()
    thermal = {"ir": np.linspace(20, 1000, 64 * 48, dtype=np.float32).reshape(48, 64)}
    save_station_capture(tmp_path / "capture", heads, thermal)
    assert (tmp_path / "capture" / "a" / "sequence.json").is_file()
    assert (tmp_path / "capture" / "b" / sequence.frames[3].file).is_file()
    assert is_station_capture(tmp_path / "capture", rig)
    assert not is_station_capture(tmp_path / "capture" / "a", rig)  # one head's directory is a capture itself
    read = read_station_capture(tmp_path / "capture", rig)
    assert [h.head for h in read] == ["a", "b"]
    for written, back in zip(heads, read):
        assert back.sequence == written.sequence
        np.testing.assert_array_equal(back.frames, written.frames)
    np.testing.assert_allclose(read_thermal_frame(thermal_path(tmp_path / "capture", "ir")), thermal["ir"])


def test_a_missing_head_is_named_with_the_directories_there_are(tmp_path, rig):
    _, heads = _heads()
    save_station_capture(tmp_path, heads[:1], {})
    with pytest.raises(InputError, match=r"no capture of head 'b' \(the station capture has sub-directories \['a'\]"):
        read_station_capture(tmp_path, rig)
    with pytest.raises(InputError, match="sequence.json"):
        (tmp_path / "c").mkdir()
        read_head_capture(tmp_path, "c")


def test_a_rig_without_heads_reads_no_station_capture(tmp_path):
    rig = Rig({"camera-1": _device("camera", 0), "camera-2": _device("camera", 1), "p": _device("projector", 2)})
    assert not is_station_capture(tmp_path, rig)
    with pytest.raises(InputError, match="names no head"):
        read_station_capture(tmp_path, rig)

"""The capture archive: exact round trip, and anything else refused (never unpickled)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from device_gateway.devices import DeviceInfo
from device_gateway.station import Capture
from device_gateway.transfer import decode_capture, encode_capture


@pytest.fixture
def capture(sequence_and_patterns) -> Capture:
    sequence, patterns = sequence_and_patterns
    rng = np.random.default_rng(3)
    count = len(sequence.frames)
    return Capture(
        sequence=sequence,
        frames=rng.integers(0, 4096, (count, 20, 30), dtype=np.uint16),
        frame_timestamps=1_700_000_000 + np.arange(count) * 0.05,
        frame_metadata=[{"file": frame.file, "exposure_us": 8000} for frame in sequence.frames],
        thermal=rng.uniform(20, 1100, (2, 8, 10)).astype(np.float32),
        thermal_timestamps=np.array([1_700_000_002.0, 1_700_000_002.04]),
        thermal_metadata=[{"units": "degC"}, {"units": "degC"}],
        devices=[DeviceInfo("camera", "camera", "oak", 30, 20, "OAK-D", "14442C10")],
    )


def test_round_trip_is_exact(capture):
    decoded = decode_capture(encode_capture(capture))
    assert decoded.sequence == capture.sequence
    for name in ("frames", "frame_timestamps", "thermal", "thermal_timestamps"):
        np.testing.assert_array_equal(getattr(decoded, name), getattr(capture, name))
        assert getattr(decoded, name).dtype == getattr(capture, name).dtype
    assert decoded.frame_metadata == capture.frame_metadata
    assert decoded.thermal_metadata == capture.thermal_metadata
    assert decoded.devices == capture.devices


def test_bytes_that_are_not_an_archive_are_refused():
    with pytest.raises(ValueError, match="not a capture archive"):
        decode_capture(b"<html>502 Bad Gateway</html>")


def test_an_archive_holding_objects_is_not_unpickled(capture):
    buffer = io.BytesIO()
    np.savez(buffer, frames=np.array([{"payload": 1}], dtype=object))
    with pytest.raises(ValueError, match="not a capture archive"):
        decode_capture(buffer.getvalue())

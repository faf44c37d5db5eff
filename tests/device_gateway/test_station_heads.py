"""The gateway's station of several heads: heads filmed one after another (each head's frames lit by its own
projector only), the thermal cameras once; a head's camera lost mid-capture is that head's error and the other
heads are filmed all the same; the station capture archive keeps which head each frame belongs to."""

import numpy as np
import pytest

from device_gateway.drivers.simulated import simulated_station_heads
from device_gateway.station import ExposureControl, MultiHeadStation
from device_gateway.transfer import decode_station_capture, encode_capture, encode_station_capture
from services.simulation.station import station_sequence


@pytest.fixture(scope="module")
def station():
    heads, thermals, rig = simulated_station_heads(4, 0.1, lose_head="head-2")
    station = MultiHeadStation(heads, thermals, settle_s=0.0)
    sequence, patterns = station_sequence(rig)
    station.open()
    station.prepare(patterns)
    yield station, sequence, patterns, rig
    station.close()


def test_a_lost_head_is_reported_and_the_others_are_filmed(station):
    station, sequence, patterns, rig = station
    first = station.capture(sequence, patterns, exposure=ExposureControl(mode="auto"))
    assert [head.head for head in first.heads] == ["head-1", "head-2", "head-3", "head-4"]
    lost = first.heads[1]
    assert lost.error == "head 'head-2': camera 'camera-2': connection lost (simulated fault)" and len(lost.frames) == 0
    for head in (first.heads[0], *first.heads[2:]):
        camera = rig.devices[rig.head(head.head).camera]
        assert head.error is None and head.frames.shape == (len(sequence.frames), camera.height, camera.width)
        assert [m["head"] for m in head.frame_metadata] == [head.head] * len(sequence.frames)
        assert head.exposure["mode"] == "auto"
        white, black = head.frames[0].astype(float), head.frames[-1].astype(float)
        assert white.mean() > black.mean() + 5  # its own projector lit the part in its frames
    assert sorted(first.thermal) == ["thermal-1", "thermal-2"]
    assert all(frames.shape == (1, 256, 320) and frames.max() > 900 for frames in first.thermal.values())
    second = station.capture(sequence, patterns, exposure=ExposureControl(mode="auto"))
    assert all(head.error is None for head in second.heads)  # the lost camera was re-opened


def test_the_station_capture_archive_keeps_each_frame_s_head(station):
    station, sequence, patterns, _ = station
    captured = station.capture(sequence, patterns)
    decoded = decode_station_capture(encode_station_capture(captured))
    assert decoded.sequence == captured.sequence
    for mine, theirs in zip(captured.heads, decoded.heads):
        assert theirs.head == mine.head and np.array_equal(theirs.frames, mine.frames)
        assert theirs.frame_metadata == mine.frame_metadata and theirs.error == mine.error
    assert all(np.array_equal(decoded.thermal[name], captured.thermal[name]) for name in captured.thermal)
    with pytest.raises(ValueError, match="not a station capture archive"):
        from device_gateway.station import Capture

        single = Capture(sequence, captured.heads[0].frames, captured.heads[0].frame_timestamps, [], 
                         captured.thermal["thermal-1"], np.zeros(1), [{}], [])
        decode_station_capture(encode_capture(single))

"""Station captures with the simulated devices: order, content, timestamps, and recovery from a lost device."""

from __future__ import annotations

import numpy as np
import pytest

from device_gateway.devices import DeviceLost, DeviceUnavailable
from device_gateway.station import Station


def test_capture_films_every_pattern_then_the_thermal_frames(station, simulated, sequence_and_patterns, small_rig):
    sequence, patterns = sequence_and_patterns
    capture = station.capture(sequence, patterns, thermal_frames=3)

    camera, thermal = small_rig.devices["camera"], small_rig.devices["thermal"]
    assert capture.sequence == sequence
    assert capture.frames.shape == (len(patterns), camera.height, camera.width)
    assert capture.frames.dtype == np.uint8
    assert capture.thermal.shape == (3, thermal.height, thermal.width)
    assert capture.thermal.dtype == np.float32
    timestamps = np.concatenate([capture.frame_timestamps, capture.thermal_timestamps])
    assert np.all(np.diff(timestamps) >= 0), "thermal frames are grabbed after the last pattern"
    assert [metadata["file"] for metadata in capture.frame_metadata] == [frame.file for frame in sequence.frames]
    assert len(capture.thermal_metadata) == 3
    assert [info.name for info in capture.devices] == ["camera", "thermal", "projector"]


def test_each_frame_shows_its_own_pattern(station, lit, sequence_and_patterns):
    sequence, patterns = sequence_and_patterns
    capture = station.capture(sequence, patterns)
    white, black = sequence.white_index, sequence.black_index
    assert white is not None and black is not None
    contrast = capture.frames[white].astype(float) - capture.frames[black].astype(float)
    assert np.median(contrast[lit]) > 40, "lit pixels are bright under the white pattern, dark under black"
    assert np.median(np.abs(contrast[~lit])) < 5, "shadowed pixels see only ambient light under both"
    gray = [index for index, frame in enumerate(sequence.frames) if frame.kind == "gray"]
    first, inverse = capture.frames[gray[0]].astype(float), capture.frames[gray[1]].astype(float)
    assert np.mean(np.sign(first - inverse)[lit] != 0) > 0.9, "a Gray plane and its inverse differ where lit"


def test_thermal_frames_carry_the_true_temperatures_with_netd_noise(station, simulated, sequence_and_patterns):
    sequence, patterns = sequence_and_patterns
    capture = station.capture(sequence, patterns, thermal_frames=2)
    truth = simulated.clean_thermal()
    noise = capture.thermal - truth
    netd = simulated.options.thermal_effects.netd
    assert abs(np.std(noise) - netd) < 0.1 * netd
    assert abs(np.mean(noise)) < 0.1 * netd
    assert not np.array_equal(capture.thermal[0], capture.thermal[1]), "each frame has its own noise"
    assert truth.max() > 1000, "the hot billet is in view"


@pytest.mark.parametrize("shape, message", [((3, 10, 10), "uint8 stack"), (None, "manifest lists")])
def test_patterns_that_do_not_fit_are_refused(station, sequence_and_patterns, shape, message):
    sequence, patterns = sequence_and_patterns
    wrong = np.zeros(shape, np.uint8) if shape else patterns[:-1]
    with pytest.raises(ValueError, match=message):
        station.capture(sequence, wrong)


def test_at_least_one_thermal_frame(station, sequence_and_patterns):
    with pytest.raises(ValueError, match="thermal frame"):
        station.capture(*sequence_and_patterns, thermal_frames=0)


def test_a_device_lost_mid_capture_fails_that_capture_and_is_reopened(simulated, unplugged, sequence_and_patterns):
    sequence, patterns = sequence_and_patterns
    camera = unplugged(fail_at=4)
    station = Station(camera, simulated.thermal, simulated.projector)

    with pytest.raises(DeviceLost, match="connection lost"):
        station.capture(sequence, patterns)
    assert camera.opens == 2, "re-opened right after the loss"
    assert all(station.health().values())

    capture = station.capture(sequence, patterns)
    assert capture.frames.shape[0] == len(patterns)
    station.close()


def test_a_device_still_away_after_a_loss_is_retried_on_the_next_capture(simulated, unplugged,
                                                                        sequence_and_patterns):
    sequence, patterns = sequence_and_patterns
    camera = unplugged(fail_at=2, away=2)
    station = Station(camera, simulated.thermal, simulated.projector)

    with pytest.raises(DeviceLost):
        station.capture(sequence, patterns)
    assert station.health()["camera"] is False
    with pytest.raises(DeviceUnavailable, match="not connected"):
        station.capture(sequence, patterns)
    capture = station.capture(sequence, patterns)
    assert capture.frames.shape[0] == len(patterns)
    assert all(station.health().values())
    station.close()


def test_filming_a_sequence_again_gives_the_frames_a_fresh_rendering_would(small_rig, sequence_and_patterns):
    import dataclasses

    from device_gateway.drivers.simulated import REFERENCE_EXPOSURE_US, SimulatedStation, SimulationOptions
    from services.simulation.render import render_frames

    sequence, patterns = sequence_and_patterns
    simulated = SimulatedStation(rig=small_rig, options=SimulationOptions(seed=7))
    station = Station(simulated.camera, simulated.thermal, simulated.projector)
    effects = simulated.options.camera_effects
    effects = dataclasses.replace(effects, exposure=effects.exposure * simulated.camera.exposure_us
                                  / REFERENCE_EXPOSURE_US)
    rng = np.random.default_rng(np.random.SeedSequence(7).spawn(1)[0])  # the camera noise's own generator
    try:
        captures = []
        for _ in range(2):  # the first renders every pattern, the second reuses their noiseless images
            station.open()
            captures.append(station.capture(sequence, patterns).frames)
            expected = render_frames(simulated.view(), patterns, rng, effects, simulated.options.projector_effects)
            np.testing.assert_array_equal(captures[-1], expected)
    finally:
        station.close()
    assert np.any(captures[0] != captures[1])  # fresh noise in every frame
    assert np.abs(captures[0].astype(int) - captures[1]).mean() < 2  # one grey level of noise, the same scene


def test_noise_drawn_ahead_gives_the_frames_noise_drawn_in_line_would(small_rig, sequence_and_patterns):
    from device_gateway.drivers.simulated import SimulatedStation, SimulationOptions

    sequence, patterns = sequence_and_patterns
    captures = []
    for ahead in (False, True):
        simulated = SimulatedStation(rig=small_rig, options=SimulationOptions(seed=3))
        station = Station(simulated.camera, simulated.thermal, simulated.projector)
        try:
            station.open()
            if ahead:
                simulated.camera.prepare(patterns)
                noise = simulated.camera_noise
                with noise._changed:  # the next capture's noise is drawn while the gateway waits
                    assert noise._changed.wait_for(lambda: len(noise._ready) == len(patterns), timeout=30)
            captures.append([station.capture(sequence, patterns).frames for _ in range(2)])
            station.close()  # stops the drawing; the images drawn ahead are the next frames'
            assert simulated.camera_noise._drawer is None
            station.open()  # and draws ahead again, when prepared
            assert (simulated.camera_noise._drawer is not None) == ahead
            captures[-1].append(station.capture(sequence, patterns).frames)
        finally:
            station.close()
    for in_line, drawn_ahead in zip(*captures):
        np.testing.assert_array_equal(drawn_ahead, in_line)
    assert np.any(captures[1][0] != captures[1][1])  # each capture has fresh noise


def test_the_camera_noise_source_refuses_another_shape(small_rig):
    from device_gateway.drivers.simulated import SimulatedStation

    noise = SimulatedStation(rig=small_rig).camera_noise
    with pytest.raises(ValueError, match="float32 of shape"):
        noise.standard_normal((noise.shape[0] + 1, noise.shape[1]), np.float32)

"""Metered exposure and HDR captures of a glowing part with the simulated station."""

from __future__ import annotations

import numpy as np
import pytest

from device_gateway.drivers.simulated import SimulatedStation
from device_gateway.station import ExposureControl, Station
from device_gateway.transfer import decode_capture, encode_capture
from services.simulation.presets import hot_optics, hot_part_scene
from services.structured_light.patterns import generate_sequence


@pytest.fixture(scope="module")
def hot_station(small_rig):
    scene = hot_part_scene(1000.0, hot_optics("white"))
    simulated = SimulatedStation(rig=small_rig, scene=scene, temperatures=scene.temperature)
    station = Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=0.0)
    yield simulated, station
    station.close()


@pytest.fixture(scope="module")
def hot_sequence(small_rig):
    projector = small_rig.devices["projector"]
    return generate_sequence(projector.width, projector.height, closing_black=True)


def test_the_simulated_camera_honours_its_exposure(hot_station):
    simulated, station = hot_station
    station.open()
    simulated.camera.set_exposure(20.0)
    short = simulated.camera.grab(1.0).image.astype(float)
    simulated.camera.set_exposure(80.0)
    long = simulated.camera.grab(1.0).image.astype(float)
    glowing = short > 50
    assert glowing.mean() > 0.05
    assert np.median(long[glowing] / short[glowing]) == pytest.approx(4.0, rel=0.05)


def test_automatic_exposure_keeps_glow_and_pattern_below_saturation(hot_station, hot_sequence):
    simulated, station = hot_station
    simulated.camera.set_exposure(5000.0)  # far too long: the glow alone saturates
    sequence, patterns = hot_sequence
    capture = station.capture(sequence, patterns, exposure=ExposureControl(mode="auto"))
    saturation = capture.exposure["saturation_level"]
    assert saturation == 4095 and capture.frames.dtype == np.uint16
    white = capture.frames[sequence.white_index]
    assert 0.6 * saturation < np.percentile(white, 99.9) < saturation
    glow = capture.frames[sequence.black_index]
    assert capture.exposure["glow_level"] == pytest.approx(np.percentile(glow, 99) / saturation, rel=0.05)
    assert capture.exposure["glow_level"] > 0.4  # unfiltered white light at 1000 C: the glow dominates
    assert [meta["exposure_us"] for meta in capture.frame_metadata] == pytest.approx(
        [capture.exposure["exposures_us"][0]] * len(patterns), abs=0.01)
    assert decode_capture(encode_capture(capture)).exposure == capture.exposure


def test_hdr_merges_a_longer_exposure_where_the_short_one_is_dim(hot_station, hot_sequence):
    simulated, station = hot_station
    sequence, patterns = hot_sequence
    control = ExposureControl(mode="hdr", hdr_exposures=2, hdr_ratio=4.0, hdr_repeats=2)
    capture = station.capture(sequence, patterns, exposure=control)
    short, repeat, long = capture.exposure["exposures_us"]
    assert repeat == short and long == pytest.approx(4 * short, abs=0.05)
    assert capture.exposure["saturation_level"] == 4 * 4095
    white = capture.frames[sequence.white_index].astype(float)
    truth = simulated.view().truth
    fixture, part = (truth.surface == 2) & truth.lit, (truth.surface <= 1) & truth.lit
    # the cool fixture comes from the long exposure (unsaturated there), the glowing part from the short one
    assert np.median(white[fixture]) < 4095 < np.median(white[part])


def test_bad_exposure_controls_are_refused():
    with pytest.raises(ValueError, match="at least 2 exposures"):
        ExposureControl(mode="hdr", hdr_exposures=1)
    with pytest.raises(ValueError, match="at least once"):
        ExposureControl(mode="hdr", hdr_repeats=0)
    with pytest.raises(ValueError, match="fraction of saturation"):
        ExposureControl(target=1.5)

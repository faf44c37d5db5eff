"""Tests of the simulated station: presets.station_rig and services.simulation.station."""

import numpy as np
import pytest

from services.formats.rig import parse_rig, rig_to_json
from services.geometry.camera import project_points
from services.simulation.presets import station_head_meridian, station_rig
from services.simulation.station import station_scene
from services.structured_light.reconstruct import coded_axis

pytestmark = pytest.mark.unit


def _view_angle(device, point, normal):
    towards = device.centre - point
    return np.degrees(np.arccos(np.dot(towards, normal) / np.linalg.norm(towards)))


def test_the_station_rig_is_a_version_2_rig_of_four_heads_and_two_thermal_cameras():
    rig = station_rig()
    assert [h.name for h in rig.heads] == ["head-1", "head-2", "head-3", "head-4"]
    assert sorted(n for n, d in rig.devices.items() if d.kind == "thermal") == ["thermal-1", "thermal-2"]
    assert parse_rig(rig_to_json(rig)) == rig
    assert '"version": 2' in rig_to_json(rig)
    for head in rig.heads:  # each head's baseline crosses the projector's rows: the sequence codes rows
        assert coded_axis(("x", "y"), rig.devices[head.camera], rig.devices[head.projector]) == "y"


def test_every_end_face_is_seen_squarely_enough_by_two_heads_and_the_side_all_round():
    rig = station_rig()
    for end in (-1.0, 1.0):
        seeing = []
        for head in rig.heads:
            angles = [_view_angle(rig.devices[d], np.array([end * 150.0, 0, 0]), np.array([end, 0, 0]))
                      for d in (head.camera, head.projector)]
            if max(angles) < 70.0:
                seeing.append(head.name)
            pixel = project_points(np.array([[end * 150.0, 0.0, 0.0]]), rig.devices[head.camera].K,
                                   rig.devices[head.camera].dist, rig.devices[head.camera].R,
                                   rig.devices[head.camera].t)[0]
            assert 0 <= pixel[0] < 1280 and 0 <= pixel[1] < 800  # every camera sees both ends of the shaft
        assert len(seeing) == 2
    # every meridian of the side faces some head within 70 degrees (camera and projector) at the shaft's middle
    for angle in np.radians(np.arange(0.0, 360.0, 5.0)):
        normal = np.array([0.0, np.sin(angle), np.cos(angle)])
        best = min(max(_view_angle(rig.devices[d], 45.0 * normal, normal) for d in (h.camera, h.projector))
                   for h in rig.heads)
        assert best < 70.0


def test_the_dent_lies_on_the_side_away_from_the_first_head():
    station = station_scene(scale=0.2, dent_depth_mm=0.3)
    dent = station.truth.dent
    assert dent.height_mm == -0.3
    direction = np.asarray(dent.center)[1:] / np.linalg.norm(np.asarray(dent.center)[1:])
    np.testing.assert_allclose(direction, -station_head_meridian(0, 4)[1:], atol=1e-12)
    cold = station.part.cold_vertices()
    deepest = np.argmin(np.linalg.norm(station.part.vertices - np.asarray(dent.center), axis=1))
    assert np.linalg.norm(cold[deepest, 1:]) == pytest.approx(45.0 - 0.3, abs=0.01)
    assert station_scene(scale=0.2).truth.dent is None


def test_impossible_stations_are_refused():
    with pytest.raises(ValueError, match="at least two heads"):
        station_rig(heads=1)
    with pytest.raises(ValueError, match="positive"):
        station_scene(dent_depth_mm=-0.3)

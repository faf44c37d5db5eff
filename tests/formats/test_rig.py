import json

import numpy as np
import pytest

from services.errors import InputError
from services.formats.rig import load_rig, parse_rig, rig_to_json, save_rig


def _device(**overrides):
    device = {"kind": "camera", "width": 1280, "height": 800,
              "K": [[1400, 0, 640], [0, 1400, 400], [0, 0, 1]], "dist": [0.1, -0.05, 0, 0, 0.01],
              "R": np.eye(3).tolist(), "t": [0, 0, 0]}
    device.update(overrides)
    return device


def _rig_text(**overrides):
    return json.dumps({"units": "mm", "devices": {"cam": _device(**overrides),
                                                   "proj": _device(kind="projector", dist=[])}})


def test_round_trip(tmp_path):
    rig = parse_rig(_rig_text())
    save_rig(rig, tmp_path / "rig.json")
    again = load_rig(tmp_path / "rig.json")
    assert again == rig
    assert json.loads(rig_to_json(rig))["devices"]["cam"]["kind"] == "camera"
    np.testing.assert_array_equal(again.devices["cam"].K, rig.devices["cam"].K)


@pytest.mark.parametrize("overrides, field, words", [
    ({"R": [[1, 0, 0], [0, 1, 0], [0, 0.2, 1]]}, "devices.cam.R", "not a rotation"),
    ({"R": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "devices.cam.R", "not a rotation"),
    ({"K": [[-5, 0, 640], [0, 1400, 400], [0, 0, 1]]}, "devices.cam.K", "focal lengths must be positive"),
    ({"K": [[1400, 3, 640], [0, 1400, 400], [0, 0, 1]]}, "devices.cam.K", "skew"),
    ({"kind": "lidar"}, "devices.cam.kind", "camera"),
    ({"dist": [0.1, 0.2, 0.3]}, "devices.cam.dist", "coefficients"),
    ({"width": 0}, "devices.cam.width", "greater than 0"),
    ({"t": [0, 0]}, "devices.cam.t", "at least 3"),
    ({"colour": "red"}, "devices.cam.colour", "Extra inputs"),
])
def test_impossible_rigs_are_refused_naming_device_and_field(overrides, field, words):
    with pytest.raises(InputError) as error:
        parse_rig(_rig_text(**overrides), "rig.json")
    assert f"rig.json: {field}" in str(error.value)
    assert words in str(error.value)


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(InputError, match="cannot read the rig file"):
        load_rig(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="bad.json"):
        load_rig(tmp_path / "bad.json")


def test_device_lookup_by_name_and_kind():
    rig = parse_rig(_rig_text())
    assert rig.device(None, "camera")[0] == "cam"
    assert rig.device("proj", "projector")[0] == "proj"
    with pytest.raises(InputError, match="no device named 'nope'"):
        rig.device("nope", "camera")
    with pytest.raises(InputError, match="is a projector, not a camera"):
        rig.device("proj", "camera")
    with pytest.raises(InputError, match="exactly one thermal"):
        rig.device(None, "thermal")


def _station_text(heads, version=2):
    devices = {"cam-n": _device(), "proj-n": _device(kind="projector", dist=[]),
               "cam-s": _device(), "proj-s": _device(kind="projector", dist=[]),
               "ir": _device(kind="thermal", width=320, height=256, K=[[380, 0, 160], [0, 380, 128], [0, 0, 1]])}
    return json.dumps({"version": version, "units": "mm", "devices": devices, "heads": heads})


def test_a_version_2_rig_lists_its_heads_and_round_trips(tmp_path):
    heads = [{"name": "north", "camera": "cam-n", "projector": "proj-n"},
             {"name": "south", "camera": "cam-s", "projector": "proj-s"}]
    rig = parse_rig(_station_text(heads))
    assert [(h.name, h.camera, h.projector) for h in rig.heads] == [("north", "cam-n", "proj-n"),
                                                                    ("south", "cam-s", "proj-s")]
    assert rig.head("south").camera == "cam-s"
    with pytest.raises(InputError, match="no head named 'east'.*north"):
        rig.head("east")
    save_rig(rig, tmp_path / "rig.json")
    written = json.loads((tmp_path / "rig.json").read_text())
    assert written["version"] == 2 and written["heads"] == heads
    assert load_rig(tmp_path / "rig.json") == rig
    assert rig.without_kind("thermal").heads == rig.heads
    assert rig.without_kind("projector").heads == ()


def test_a_version_1_rig_is_one_head_and_is_written_as_version_1():
    rig = parse_rig(_rig_text())
    assert [(h.name, h.camera, h.projector) for h in rig.heads] == [("head", "cam", "proj")]
    assert set(json.loads(rig_to_json(rig))) == {"units", "devices"}
    two_cameras = parse_rig(json.dumps({"devices": {"a": _device(), "b": _device()}}))
    assert two_cameras.heads == ()


@pytest.mark.parametrize("heads, version, words", [
    ([{"name": "n", "camera": "cam-n", "projector": "proj-n"}], 1, '"heads" needs "version": 2'),
    ([], 2, "at least one head"),
    ([{"name": "n", "camera": "cam-x", "projector": "proj-n"}], 2, "head 'n': no device named 'cam-x'"),
    ([{"name": "n", "camera": "proj-n", "projector": "proj-s"}], 2, "'proj-n' is a projector, not a camera"),
    ([{"name": "n", "camera": "ir", "projector": "proj-n"}], 2, "'ir' is a thermal, not a camera"),
    ([{"name": "n", "camera": "cam-n", "projector": "proj-n"},
      {"name": "n", "camera": "cam-s", "projector": "proj-s"}], 2, "unique"),
    ([{"name": "n", "camera": "cam-n", "projector": "proj-n"},
      {"name": "s", "camera": "cam-s", "projector": "proj-n"}], 2, "already belongs to head 'n'"),
    ([{"name": "../up", "camera": "cam-n", "projector": "proj-n"}], 2, "heads[0].name: a head's name is also its capture directory's"),
])
def test_impossible_heads_are_refused_naming_the_head(heads, version, words):
    with pytest.raises(InputError, match="station.json") as caught:
        parse_rig(_station_text(heads, version), "station.json")
    assert words in str(caught.value)

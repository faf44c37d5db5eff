import numpy as np
import pytest

from services.cli.main import main
from services.formats.ply import read_cloud, write_cloud
from services.formats.rig import save_rig
from services.formats.thermal import write_thermal_frame

pytestmark = pytest.mark.integration


def _score(field, capture):
    """Median |error| over points the thermal camera truly sees, and the NaN fraction of hidden ones."""
    row, column = field["v"].astype(int), field["u"].astype(int)
    on_surface = capture.truth.surface[row, column] >= 0
    seen = capture.seen_by_thermal[row, column] & on_surface
    hidden = on_surface & ~capture.seen_by_thermal[row, column]
    error = np.abs(field["temperature"] - capture.true_temperature[row, column])
    return np.nanmedian(error[seen]), np.mean(np.isfinite(error[seen])), np.mean(np.isnan(field["temperature"][hidden]))


@pytest.fixture(scope="module")
def field_ply(forging_capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("field") / "field.ply"
    code = main(["field", "--rig", str(forging_capture.rig_path), "--captures", str(forging_capture.captures),
                 "--thermal", str(forging_capture.thermal_path), "--out", str(out)])
    assert code == 0
    return out


def test_field_command_meets_the_accuracy_and_occlusion_targets(field_ply, forging_capture):
    field = read_cloud(field_ply)
    median_error, coverage, hidden_nan = _score(field, forging_capture)
    assert median_error <= 1.0
    assert coverage >= 0.8
    assert hidden_nan >= 0.99
    assert np.nanmax(field["temperature"]) > 1000  # the hot part, up to about 1100 C


def test_field_ply_has_the_cloud_properties_temperature_view_angle_and_colours(field_ply):
    field = read_cloud(field_ply)
    for name in ("x", "y", "z", "nx", "ny", "nz", "u", "v", "quality"):
        assert name in field
    assert field["temperature"].dtype == np.float32
    assert field["view_angle"].dtype == np.float32
    assert all(field[c].dtype == np.uint8 for c in ("red", "green", "blue"))
    seen = np.isfinite(field["temperature"])
    assert np.all(field["view_angle"][seen] <= 75.0 + 1e-3)
    hottest, coldest = np.nanargmax(field["temperature"]), np.nanargmin(field["temperature"])
    brightness = field["red"].astype(int) + field["green"] + field["blue"]
    assert brightness[hottest] > brightness[coldest]  # inferno runs from black to bright yellow


def test_fuse_command_matches_field_and_estimates_missing_normals(field_ply, forging_capture, tmp_path):
    field = read_cloud(field_ply)
    cloud = {name: field[name] for name in ("x", "y", "z", "u", "v")}
    write_cloud(tmp_path / "cloud.ply", cloud)
    out = tmp_path / "fused.ply"
    code = main(["fuse", "--rig", str(forging_capture.rig_path), "--cloud", str(tmp_path / "cloud.ply"),
                 "--thermal", str(forging_capture.thermal_path), "--out", str(out)])
    assert code == 0
    fused = read_cloud(out)
    median_error, coverage, hidden_nan = _score(fused, forging_capture)
    assert median_error <= 1.0 and coverage >= 0.8 and hidden_nan >= 0.99
    both = np.isfinite(fused["temperature"]) & np.isfinite(field["temperature"])
    assert np.median(np.abs(fused["temperature"][both] - field["temperature"][both])) < 0.05


def test_fuse_command_fuses_several_frames_and_names_the_device(field_ply, forging_capture, tmp_path):
    second = tmp_path / "second.npy"
    write_thermal_frame(second, np.full((256, 320), 500.0))
    out = tmp_path / "two.ply"
    code = main(["fuse", "--rig", str(forging_capture.rig_path), "--cloud", str(field_ply),
                 "--thermal", str(forging_capture.thermal_path), str(second), "--thermal-device", "thermal",
                 "--out", str(out)])
    assert code == 0
    single, both = read_cloud(field_ply)["temperature"], read_cloud(out)["temperature"]
    seen = np.isfinite(both) & np.isfinite(single)
    np.testing.assert_allclose(both[seen], (single[seen] + 500.0) / 2, atol=1e-3)
    # the same points are seen, but for readings only the unseen space's skirts take: whether their neighbours
    # vouch for them allows an absolute 20 K, which halving the contrast changes for a few
    assert np.mean(np.isfinite(both) == np.isfinite(single)) > 0.99


def test_emissivity_raises_the_temperature_of_apparent_frames(field_ply, forging_capture, tmp_path):
    out = tmp_path / "emissive.ply"
    assert main(["fuse", "--rig", str(forging_capture.rig_path), "--cloud", str(field_ply),
                 "--thermal", str(forging_capture.thermal_path), "--emissivity", "0.8", "--out", str(out)]) == 0
    corrected, apparent = read_cloud(out)["temperature"], read_cloud(field_ply)["temperature"]
    hot = apparent > 500
    assert np.all(corrected[hot] > apparent[hot] + 20)


@pytest.mark.parametrize(("change", "message"), [
    ({"thermal": "small"}, "thermal frame is 100x80 but the thermal camera is 320x256"),
    ({"cloud": "missing.ply"}, "missing.ply: point cloud file is missing"),
    ({"device": ["nope"]}, "no device named 'nope'"),
    ({"device": ["camera"]}, "is a camera, not a thermal"),
    ({"device": ["thermal", "thermal"]}, "one name or one per frame"),
    ({"emissivity": "1.5"}, "--emissivity must be in (0, 1]"),
    ({"rig": "no-thermal"}, "exactly one thermal device"),
])
def test_bad_input_exits_2_with_a_message_naming_it(change, message, field_ply, forging_capture, tmp_path, capsys):
    rig_path, thermal = forging_capture.rig_path, forging_capture.thermal_path
    if change.get("thermal") == "small":
        thermal = tmp_path / "small.tif"
        write_thermal_frame(thermal, np.full((80, 100), 900.0))
    if change.get("rig") == "no-thermal":
        rig = forging_capture.rig
        rig_path = tmp_path / "rig.json"
        save_rig(rig.without_kind("thermal"), rig_path)
    cloud = tmp_path / change["cloud"] if "cloud" in change else field_ply
    argv = ["fuse", "--rig", str(rig_path), "--cloud", str(cloud), "--thermal", str(thermal),
            "--out", str(tmp_path / "out.ply")]
    if "device" in change:
        argv += ["--thermal-device", *change["device"]]
    if "emissivity" in change:
        argv += ["--emissivity", change["emissivity"]]
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert message in error
    assert "Traceback" not in error
    assert not (tmp_path / "out.ply").exists()

"""``thermofield calibrate station`` and the calibrate_station use case on rendered views of a small simulated
station (services.simulation.station_boards, a quarter of the cameras' resolution)."""

import json
import shutil

import numpy as np
import pytest

from services.calibration.station import pose_difference
from services.cli.main import main
from services.formats.board import ChessboardSpec
from services.formats.calibration import load_station_calibration
from services.formats.images import write_png
from services.formats.rig import Head, Rig, load_rig, save_rig
from services.simulation.station_boards import ring_station_rig, station_board_views

pytestmark = pytest.mark.integration
BOARD = ChessboardSpec(type="chessboard", inner_corners=(9, 6), square_mm=30.0)


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    """The true station, its heads' own rigs (as calibrate projector writes them) and the board views on disk."""
    rng = np.random.default_rng(20)
    truth = ring_station_rig(rng, scale=0.25)
    views = station_board_views(truth, BOARD, rng, shared=4, own=4, supersample=1)
    directory = tmp_path_factory.mktemp("station")
    (directory / "board.json").write_text(BOARD.model_dump_json())
    heads = []
    for head in truth.heads:
        camera, projector = truth.devices[head.camera], truth.devices[head.projector]
        relative = projector.R @ camera.R.T
        own = Rig({"camera": camera.replace(R=np.eye(3), t=np.zeros(3)),
                   "projector": projector.replace(R=relative, t=projector.t - relative @ camera.t)})
        save_rig(own, directory / f"{head.name}.json")
        heads += ["--head", f"{head.name}={directory / f'{head.name}.json'}"]
        (directory / "views" / head.name).mkdir(parents=True)
        for view, image in views.images[head.camera].items():
            write_png(directory / "views" / head.name / f"view{view:03d}.png", image)
    return truth, directory, heads


def test_calibrate_station_places_every_head_in_the_first_heads_frame(station, capsys):
    truth, directory, heads = station
    out = directory / "station.json"
    assert main(["calibrate", "station", "--board", str(directory / "board.json"), "--views",
                 str(directory / "views"), *heads, "--out", str(out)]) == 0
    rig = load_rig(out)
    assert json.loads(out.read_text())["version"] == 2
    assert rig.heads == tuple(Head(h.name, f"camera-{h.name}", f"projector-{h.name}") for h in truth.heads)
    report = load_station_calibration(directory / "station_station.json")
    sigmas = {record.device: np.array(list(record.pose_std.values())) for record in report.devices}
    first = truth.devices[truth.heads[0].camera]
    for head in truth.heads:  # the truth in the first head's camera frame, the world of the calibration
        for name in (head.camera, head.projector):
            device, true = rig.devices[name], truth.devices[name]
            R, t = true.R @ first.R.T, true.t - true.R @ first.R.T @ first.t
            error = pose_difference(R, t, device.R, device.t)
            # 320x200 cameras and four views per pair: the reported sigmas are about 0.05 degree and 0.6 mm
            assert np.linalg.norm(error[:3]) < 0.25 and np.linalg.norm(error[3:]) < 3.0, (name, error)
            if name == head.camera:
                assert np.all(np.abs(error) <= 3 * sigmas[name] + 1e-9), (name, error, sigmas[name])
    assert report.version == 1 and report.world == "camera-north" and report.intrinsics == "refined"
    assert [record.device for record in report.devices] == [h.camera for h in truth.heads]
    assert {tuple(o.devices) for o in report.overlaps} == {("camera-north", "camera-east"),
                                                           ("camera-north", "camera-west"),
                                                           ("camera-east", "camera-south"),
                                                           ("camera-south", "camera-west")}
    assert report.overlap_rms_px < 0.2 and report.overlap_rms_mm < 0.2
    assert all(record.pose_std["x"] > 0 for record in report.devices[1:])
    output = capsys.readouterr().out
    assert "overlaps RMS" in output and "camera-south:" in output


def test_a_station_rig_keeps_its_world_frame_when_calibrated_again(station):
    truth, directory, _ = station
    save_rig(truth, directory / "nominal.json")
    out = directory / "again.json"
    assert main(["calibrate", "station", "--board", str(directory / "board.json"), "--views",
                 str(directory / "views"), "--rig", str(directory / "nominal.json"), "--world", "east",
                 "--intrinsics", "fixed", "--out", str(out)]) == 0
    rig = load_rig(out)
    assert np.allclose(rig.devices["camera-east"].R, truth.devices["camera-east"].R)
    west, true_west = rig.devices["camera-west"], truth.devices["camera-west"]
    assert np.linalg.norm(pose_difference(true_west.R, true_west.t, west.R, west.t)[3:]) < 0.5
    assert np.array_equal(rig.devices["camera-west"].K, truth.devices["camera-west"].K)  # fixed intrinsics


def test_a_head_without_views_is_named(station, tmp_path, capsys):
    _, directory, heads = station
    shutil.copytree(directory / "views", tmp_path / "views")
    shutil.rmtree(tmp_path / "views" / "south")
    assert main(["calibrate", "station", "--board", str(directory / "board.json"), "--views", str(tmp_path / "views"),
                 *heads, "--out", str(tmp_path / "out.json")]) == 2
    assert "no images of head 'south'" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()


def test_heads_that_share_no_view_are_named(station, tmp_path, capsys):
    _, directory, heads = station
    shutil.copytree(directory / "views", tmp_path / "views")
    north = {p.name for p in (tmp_path / "views" / "north").iterdir()}
    for neighbour in ("east", "west"):  # north keeps only the views it sees alone
        for path in (tmp_path / "views" / neighbour).iterdir():
            if path.name in north:
                (tmp_path / "views" / "north" / path.name).unlink()
    assert main(["calibrate", "station", "--board", str(directory / "board.json"), "--views", str(tmp_path / "views"),
                 *heads, "--out", str(tmp_path / "out.json")]) == 2
    assert "groups that share no board view (north; east, south, west)" in capsys.readouterr().err


def test_an_unknown_sub_directory_is_named(station, tmp_path, capsys):
    _, directory, heads = station
    shutil.copytree(directory / "views", tmp_path / "views")
    (tmp_path / "views" / "upper").mkdir()
    shutil.copy(next((tmp_path / "views" / "north").iterdir()), tmp_path / "views" / "upper")
    assert main(["calibrate", "station", "--board", str(directory / "board.json"), "--views", str(tmp_path / "views"),
                 *heads, "--out", str(tmp_path / "out.json")]) == 2
    assert "'upper' is neither a head of the station" in capsys.readouterr().err

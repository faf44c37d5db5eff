"""End to end on the simulated four-head station at reduced resolution: simulate (the command), reconstruct each
head, merge, fuse, and the commands on the station capture; checked against the simulator's truth."""

from types import SimpleNamespace

import numpy as np
import pytest

from services.cli.main import main
from services.errors import InputError
from services.formats.ply import read_cloud
from services.formats.rig import load_rig
from services.formats.station_capture import read_station_capture, thermal_path
from services.formats.thermal import read_thermal_frame
from services.open3d_loader import open3d
from services.pipeline.field import fuse_field
from services.pipeline.station import merge_heads, reconstruct_head, reconstruct_station
from services.pipeline.tables import TriangulationTables
from services.simulation.station import lateral_coverage, station_scene

pytestmark = pytest.mark.integration

SCALE = 0.3
# At 0.3 of the resolution the camera's pixel spans about 1.7 mm on the shaft, 5 mm along it where the view is
# oblique: coverage is counted in 6 mm cells (docs/station.md counts 2 mm cells at full resolution).
CELL_MM = 6.0


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    out = tmp_path_factory.mktemp("station") / "capture"
    assert main(["simulate", "--scene", "station", "--scale", str(SCALE), "--out", str(out)]) == 0
    rig = load_rig(out / "rig.json")
    heads = read_station_capture(out, rig)
    merged = reconstruct_station(heads=heads, rig=rig, tables=TriangulationTables())
    return SimpleNamespace(directory=out, rig=rig, heads=heads, merged=merged, truth=station_scene(scale=SCALE))


def _surface_distance(points, truth):
    scene = open3d().t.geometry.RaycastingScene()
    scene.add_triangles(open3d().core.Tensor(truth.part.hot_vertices_part().astype(np.float32)),
                        open3d().core.Tensor(truth.part.triangles.astype(np.uint32)))
    return scene.compute_distance(open3d().core.Tensor(points.astype(np.float32))).numpy()


def test_the_merged_cloud_covers_the_shaft_all_round_and_lies_on_it(station):
    cloud = station.merged.cloud
    assert cloud["head"].dtype == np.int32
    assert set(np.unique(cloud["head"])) == {0, 1, 2, 3}
    assert lateral_coverage(cloud.points, station.truth, cell_mm=CELL_MM) >= 0.95
    distance = _surface_distance(cloud.points, station.truth)
    assert np.median(distance) < 0.1
    assert np.percentile(distance, 95) < 0.3
    # both end faces are measured (the length between them needs them)
    for end in (-1, 1):
        face = np.abs(cloud["x"] - end * 150.0 * (1 + 0.0136)) < 1.0  # the hot shaft is about 1.4 % longer
        assert np.count_nonzero(face & (np.hypot(cloud["y"], cloud["z"]) < 40.0)) > 200


def test_the_merge_reports_small_residuals_thin_overlaps_and_bounded_corrections(station):
    report = station.merged.report
    assert report.heads == ("head-1", "head-2", "head-3", "head-4")
    assert len(report.residuals) >= 4  # neighbours on the side, opposite heads on their end face
    # the rig is exact: what is left in the overlaps is the reconstruction's view-angle bias (at 0.3 of the
    # resolution -0.06 to +0.05 mm where one head sees the surface obliquely, docs/station.md), which the
    # refinement cannot remove and must not make worse
    before = {(r.first, r.second): r.patch_rms_mm for r in report.residuals_before}
    assert all(r.patch_rms_mm <= before[r.first, r.second] + 0.005 for r in report.residuals)
    assert max(r.patch_rms_mm for r in report.residuals) <= 0.08
    for c in report.corrections:
        assert (c.applied and c.translation_mm <= 0.15 and c.rotation_deg <= 0.03) or \
            "beyond 3 sigma of the calibration" in c.reason
    # the refined merge lies on the true shaft as closely as the unrefined one (the calibration is exact)
    heads = {h.name: reconstruct_head(frames=c.frames, sequence=c.sequence, rig=station.rig, head=h.name,
                                      tables=TriangulationTables()).cloud
             for h, c in zip(station.rig.heads, station.heads)}
    unrefined = merge_heads(clouds=heads, rig=station.rig, refine=False).cloud.points
    refined = station.merged.cloud.points
    assert np.median(np.abs(_surface_distance(refined, station.truth))) <= \
        1.1 * np.median(np.abs(_surface_distance(unrefined, station.truth)))
    assert sum(report.kept_points) == len(station.merged.cloud)
    assert sum(report.kept_points) < 0.95 * sum(report.measured_points)  # the overlaps were thinned


def test_a_head_is_reconstructed_alone_and_the_merge_needs_every_head(station):
    first = station.heads[0]
    cloud = reconstruct_head(frames=first.frames, sequence=first.sequence, rig=station.rig, head="head-1",
                             tables=TriangulationTables()).cloud
    assert len(cloud) == station.merged.report.measured_points[0]
    with pytest.raises(InputError, match="no head named 'head-9'"):
        reconstruct_head(frames=first.frames, sequence=first.sequence, rig=station.rig, head="head-9",
                         tables=TriangulationTables())
    with pytest.raises(InputError, match=r"missing \['head-2', 'head-3', 'head-4'\]"):
        merge_heads(clouds={"head-1": cloud}, rig=station.rig)


def test_every_thermal_camera_gives_the_merged_cloud_its_temperature(station):
    thermal = [(name, read_thermal_frame(thermal_path(station.directory, name))) for name in ("thermal-1", "thermal-2")]
    field = fuse_field(cloud=station.merged.cloud, rig=station.rig, thermal=thermal)
    temperature = field["temperature"]
    seen = np.isfinite(temperature)
    assert seen.mean() > 0.3
    error = np.abs(temperature[seen] - station.truth.part.surface_temperature(field.points[seen]))
    assert np.median(error) < 1.0
    # both cameras contribute: points of the heads on either side have temperatures
    assert all(seen[field["head"] == index].mean() > 0.1 for index in range(4))


def test_the_field_command_merges_the_heads_and_takes_one_frame_per_thermal_camera(station, tmp_path):
    out = tmp_path / "field.ply"
    arguments = ["field", "--rig", str(station.directory / "rig.json"), "--captures", str(station.directory)]
    for name in ("thermal-1", "thermal-2"):
        arguments += ["--thermal", f"{name}={thermal_path(station.directory, name)}"]
    assert main(arguments + ["--out", str(out)]) == 0
    field = read_cloud(out)
    assert set(np.unique(field["head"])) == {0, 1, 2, 3}
    assert np.isfinite(field["temperature"]).mean() > 0.3


def test_the_station_capture_refuses_single_head_options(station, tmp_path, capsys):
    code = main(["reconstruct", "--rig", str(station.directory / "rig.json"), "--captures", str(station.directory),
                 "--camera", "camera-1", "--out", str(tmp_path / "cloud.ply")])
    assert code == 2
    assert "--camera does not apply" in capsys.readouterr().err
    code = main(["field", "--rig", str(station.directory / "rig.json"), "--captures", str(station.directory),
                 "--thermal", f"thermal-1={thermal_path(station.directory, 'thermal-1')}",
                 str(thermal_path(station.directory, "thermal-2")), "--out", str(tmp_path / "field.ply")])
    assert code == 2
    assert "name the thermal device of every frame or of none" in capsys.readouterr().err

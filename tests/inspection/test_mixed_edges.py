"""Good parts before a cool wall, fused as the station fuses them: mixed edge pixels decide no verdict.

The tuning scenes of issue 34 (docs/inspection.md, "Tuning scenes"): capped carbon-steel billets at 950 to
1100 degC in tolerance and an open 90/70 mm tube at 1000 degC, each 160 mm before a 60 degC wall, on the
forging rig at 35 % resolution. The thermal frame is rendered from the hot mesh with the camera's area
integration and blur (``simulated_thermal_frame``), so the part's silhouette pixels mix it with the wall;
the field is fused from it by ``temperature_field`` and inspected. Ground truth: the simulator's part.
"""

import numpy as np
import pytest

from services.formats.part import load_part
from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.inspection.inspect import inspect_field, prepare_part
from services.simulation.hot_part import (Backdrop, Bump, HotPart, billet_pose, cylinder_mesh, on_part,
                                          simulated_field, simulated_thermal_frame, tube_mesh, write_billet_part,
                                          write_tube_part)
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature

pytestmark = pytest.mark.integration

SEGMENTS = 180
WALL = Backdrop(centre=(0.0, 20.0, 760.0), temperature_c=60.0)
TOLERANCE = (-0.5, 0.5)


@pytest.fixture(scope="module")
def rig():
    return forging_rig(0.35)


@pytest.fixture(scope="module")
def billet(tmp_path_factory):
    return prepare_part(load_part(write_billet_part(tmp_path_factory.mktemp("billet"), segments=SEGMENTS,
                                                    surface_tolerance=TOLERANCE)))


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    return prepare_part(load_part(write_tube_part(tmp_path_factory.mktemp("tube"), segments=SEGMENTS,
                                                  surface_tolerance=TOLERANCE)))


def fused_scan(rig, hot, seed):
    """The field as ``thermofield field`` makes it from the simulated cloud and thermal frame, and which
    of its points lie on the part."""
    devices = rig.devices
    rng = np.random.default_rng(seed)
    field, truth = simulated_field(hot, devices["camera"], devices["projector"], devices["thermal"], rng,
                                   backdrop=WALL)
    frame = simulated_thermal_frame(hot, devices["thermal"], rng, backdrop=WALL)
    fused = temperature_field({name: field[name] for name in "xyz"}, [ThermalView(devices["thermal"], frame)],
                              devices["camera"].centre)
    return {name: fused[name] for name in ("x", "y", "z", "temperature")}, on_part(hot, truth)


def billet_part(prepared, temperature, bumps=()):
    vertices, triangles = cylinder_mesh(45.0, 200.0, SEGMENTS)
    return HotPart(vertices, triangles, prepared.part.material, SurfaceTemperature(base=temperature),
                   pose=billet_pose(), bumps=tuple(bumps))


def tube_part(prepared, bumps=()):
    vertices, triangles = tube_mesh(45.0, 35.0, 200.0, SEGMENTS)
    return HotPart(vertices, triangles, prepared.part.material, SurfaceTemperature(base=1000.0),
                   pose=billet_pose(tilt_deg=45.0), bumps=tuple(bumps))


@pytest.mark.parametrize("temperature", [950.0, 1025.0, 1100.0])
def test_billets_in_tolerance_before_a_wall_are_ok(rig, billet, temperature):
    field, part_points = fused_scan(rig, billet_part(billet, temperature), seed=int(temperature))
    measured = field["temperature"][part_points]
    # no part point reads a mix of the part and the wall (the silhouette pixels read 550..1000 degC unguarded)
    assert np.nanmax(np.abs(measured - temperature)) <= 5.0
    report = inspect_field(field=field, part=billet).report
    diameter = report["features"][0]
    assert abs(diameter["cold"] - 90.0) <= 0.05
    assert report["surface"]["defects"] == []
    assert report["surface"]["verdict"] == "OK"
    assert report["verdict"] == "OK"


def test_an_open_tube_in_tolerance_has_no_rim_defects(rig, tube):
    field, part_points = fused_scan(rig, tube_part(tube), seed=7)
    assert np.nanmax(np.abs(field["temperature"][part_points] - 1000.0)) <= 5.0
    report = inspect_field(field=field, part=tube).report
    assert abs(report["features"][0]["cold"] - 90.0) <= 0.05
    assert report["surface"]["defects"] == []
    assert report["verdict"] == "OK"


def test_a_real_dent_beyond_the_tolerance_is_still_not_ok(rig, billet):
    """The other direction: the support rule does not suppress a defect of a few square millimetres."""
    dent = Bump((40.0, 0.0, -45.0), 5.0, -1.5)
    report = inspect_field(field=fused_scan(rig, billet_part(billet, 1000.0, [dent]), seed=3)[0],
                           part=billet).report
    assert report["surface"]["verdict"] == "NotOK"
    deepest = report["surface"]["defects"][0]
    assert deepest["depth"] == pytest.approx(-1.5, abs=0.15)
    # the billet is symmetric about its axis and end to end: the dent's place is its |x| and its radius
    x, y, z = deepest["center"]
    assert abs(abs(x) - 40.0) < 3.0 and abs(np.hypot(y, z) - 43.5) < 2.0
    assert report["verdict"] == "NotOK"


def test_a_small_dent_is_found_on_the_fused_field(rig, billet):
    dent = Bump((40.0, 0.0, -45.0), 4.0, -0.3)
    report = inspect_field(field=fused_scan(rig, billet_part(billet, 1000.0, [dent]), seed=4)[0],
                           part=billet).report
    dents = [defect for defect in report["surface"]["defects"] if defect["depth"] < 0]
    assert len(dents) == 1
    assert dents[0]["depth"] == pytest.approx(-0.3, abs=0.06)
    assert report["surface"]["verdict"] == "OK"  # 0.3 mm lies within +-0.5 mm less U


def test_a_handful_of_stray_points_decides_nothing(rig, billet):
    """12 points 2 mm off (as a bad code or a mixed pixel makes them) are no defect; 200 of them in one
    patch are."""
    field, part_points = fused_scan(rig, billet_part(billet, 1000.0), seed=5)
    report = inspect_field(field=field, part=billet).report
    assert report["verdict"] == "OK"
    xyz = np.column_stack([field[name] for name in "xyz"]).astype(np.float64)
    centre = np.array([0.0, 20.0, 600.0])
    for count, expected in ((12, "OK"), (400, "NotOK")):
        # the points of the part nearest a spot on its flank, pushed 2 mm toward the axis's side (outward)
        target = centre + np.array([0.0, -45.0, 0.0])
        index = np.flatnonzero(part_points)[np.argsort(np.linalg.norm(xyz[part_points] - target, axis=1))[:count]]
        moved = {name: values.copy() for name, values in field.items()}
        outward = xyz[index] - centre
        outward[:, 0] = 0.0
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        for axis, name in enumerate("xyz"):
            moved[name][index] += (2.0 * outward[:, axis]).astype(np.float32)
        report = inspect_field(field=moved, part=billet).report
        assert report["surface"]["verdict"] == expected, count
        assert report["surface"]["max"] > 1.0  # the points are there, beyond the tolerance

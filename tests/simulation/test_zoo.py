"""The scene zoo: deterministic per seed, ground truth consistent with the scene, every part kind drawn;
and (integration) the short zoo through the real use cases, within bounds that today's code meets."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.formats.part import load_part
from services.inspection.inspect import prepare_part
from services.simulation.hot_part import box_mesh, revolved_loop_mesh
from services.simulation.raycast import cast_rays
from services.simulation.zoo import PART_KINDS, REPORTING_SEEDS, TUNING_SEEDS, zoo_scene

ROOT = Path(__file__).resolve().parents[2]


def _volume(vertices, triangles):
    corners = vertices[triangles]
    return np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6


def _watertight(triangles):
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    return (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()


def test_box_and_ring_meshes_are_closed_outward_and_of_their_volume():
    vertices, triangles = box_mesh((40.0, 30.0, 20.0), 5.0)
    assert _watertight(triangles)
    assert _volume(vertices, triangles) == pytest.approx(24000.0, rel=1e-12)
    vertices, triangles = revolved_loop_mesh([(-10.0, 20.0), (10.0, 20.0), (10.0, 30.0), (-10.0, 30.0)], 360, 2.0)
    assert _watertight(triangles)
    polygon = 0.5 * 360 * np.sin(2 * np.pi / 360) * (30.0**2 - 20.0**2)  # the annulus of 360-gons
    assert _volume(vertices, triangles) == pytest.approx(polygon * 20.0, rel=1e-9)
    with pytest.raises(ValueError, match="every r > 0"):
        revolved_loop_mesh([(0.0, 0.0), (1.0, 1.0), (0.0, 1.0)])


def test_the_seed_ranges_are_disjoint_and_large_enough():
    assert not set(TUNING_SEEDS) & set(REPORTING_SEEDS)
    assert len(REPORTING_SEEDS) >= 200


def test_a_seed_gives_the_same_scene_and_another_seed_another():
    first, again, other = zoo_scene(1003), zoo_scene(1003), zoo_scene(1004)
    assert first.scene == again.scene and first.rig == again.rig and first.part_file == again.part_file
    assert first.truth == again.truth
    np.testing.assert_array_equal(first.nominal_vertices, again.nominal_vertices)
    assert other.rig != first.rig


def test_every_part_kind_and_both_truths_appear_over_seeds():
    scenes = [zoo_scene(seed) for seed in range(1000, 1007)]
    assert {scene.kind for scene in scenes} == set(PART_KINDS)
    assert {scene.truth.in_tolerance for scene in scenes} == {True, False}


@pytest.mark.parametrize("seed", [1000, 1001, 1002, 1003, 1004, 1005, 1006])
def test_ground_truth_is_consistent_with_the_scene(seed, tmp_path):
    zoo = zoo_scene(seed)
    rig = zoo.rig
    camera, projector, thermal = (rig.devices[name] for name in ("camera", "projector", "thermal"))
    # surface 0 is the hot part: its mesh is the HotPart's hot vertices in the (random) world frame
    np.testing.assert_allclose(np.asarray(zoo.scene.surfaces[0].vertices),
                               zoo.part.to_world(zoo.part.hot_vertices_part()), atol=1e-9)
    # the camera's optical axis meets the part or passes within a part's size of it
    hot = zoo.part.to_world(zoo.part.hot_vertices_part())
    centre = hot.mean(axis=0)
    axis = camera.R[2]
    offset = centre - camera.centre
    assert np.linalg.norm(offset - (offset @ axis) * axis) < 120.0
    # the part is in front of all three devices and inside their images
    for device in (camera, projector, thermal):
        assert (hot @ device.R[2] + device.t[2] > 100.0).all()
        pixel = device.K @ ((device.R @ centre + device.t) / (device.R @ centre + device.t)[2])
        assert 0 <= pixel[0] < device.width and 0 <= pixel[1] < device.height
    # the camera sees the part: its ray toward the part's centre meets surface 0 or a fixture first
    hits = cast_rays(zoo.scene, camera.centre, (centre - camera.centre)[None])
    assert hits.surface[0] >= 0
    # the part is hot, its surroundings cool; the temperature field is the part's own field, moved to the world
    temperature = zoo.temperatures.surfaces[0].evaluate(hot)
    assert temperature.min() > 700.0
    assert all(field.base < 300.0 for field in zoo.temperatures.surfaces[1:])
    cold = zoo.part.to_world(zoo.part.cold_vertices())
    np.testing.assert_allclose(zoo.temperatures.surfaces[0].evaluate(cold),
                               zoo.part.temperature.evaluate(zoo.part.cold_vertices()), atol=1e-6)
    # the part file loads, its features fit the nominal, and the truth names only its features
    part = load_part(zoo.write_part(tmp_path))
    assert json.loads((tmp_path / "part.json").read_text())["name"] == f"zoo-{seed}-{zoo.kind}"
    prepared = prepare_part(part)
    names = {feature.name for feature in part.definition.features}
    assert set(zoo.truth.features) <= names
    assert prepared.part.name == part.name
    # an in-tolerance part's true sizes are within their tolerances, an out-of-tolerance part has a reason
    for feature in part.definition.features:
        if feature.name in zoo.truth.features:
            deviation = zoo.truth.features[feature.name] - feature.nominal
            inside = feature.tolerance[0] <= deviation <= feature.tolerance[1]
            assert inside or not zoo.truth.in_tolerance
    if not zoo.truth.in_tolerance:
        assert "dent" in zoo.truth.deviation or "bulge" in zoo.truth.deviation or any(
            not (f.tolerance[0] <= zoo.truth.features.get(f.name, f.nominal) - f.nominal <= f.tolerance[1])
            for f in part.definition.features if f.nominal is not None)


def test_a_negative_seed_is_refused():
    with pytest.raises(ValueError, match="non-negative"):
        zoo_scene(-1)


SHORT_ZOO = range(1000, 1010)


@pytest.mark.integration
@pytest.mark.timeout(1800)  # about a minute of two cores idle; the shared machine can be ten times slower
def test_short_zoo_through_the_real_commands(tmp_path):
    """Ten reporting scenes through reconstruct, field, inspect and register. The bounds are what today's
    code meets on them (docs/zoo.md), looser than the issue's targets: the fixes will tighten them."""
    output = tmp_path / "zoo.json"
    command = [sys.executable, str(ROOT / "experiments" / "zoo.py"), "--seeds", f"{SHORT_ZOO.start}-{SHORT_ZOO.stop - 1}",
               "--json", str(output), "--cache", str(tmp_path / "cache")]
    # the command as it is run, in a process of its own (its worker processes start with no OpenMP of the suite's)
    done = subprocess.run([*command, "--jobs", "2"], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(output.read_text())
    assert [r["seed"] for r in results] == list(SHORT_ZOO)
    assert not [r["seed"] for r in results if "crash" in r]
    scored = [r for r in results if "refused" not in r]
    assert len(scored) >= 9
    wrong = np.array([r["wrong_rate"] for r in scored])
    coverage = np.array([r["coverage"] for r in scored])
    assert np.median(wrong) < 0.004  # today about 0.0013; target 0.0002
    assert np.percentile(wrong, 95) < 0.02  # today about 0.006; target 0.001
    assert np.median(coverage) > 0.95  # today about 0.99; target 0.95
    assert np.median([r["error"]["median"] for r in scored]) < 0.2
    # fixture and wall points read at a part's temperature (F1): 145 on these ten with the unseen space, 5,379
    # with the cloud's z-buffer alone
    assert sum(r.get("hot_readings_off_part") or 0 for r in scored) < 1000
    # verdicts: today no out-of-tolerance part of these ten is passed, and one in-tolerance part is rejected
    # (seed 1006, a flange: docs/zoo.md); the target is none of either
    false_ok = [r["seed"] for r in results if not r["in_tolerance"] and r.get("verdict") == "OK"]
    false_not_ok = [r["seed"] for r in results if r["in_tolerance"] and r.get("verdict") == "NotOK"]
    assert not false_ok
    assert len(false_not_ok) <= 2
    # a rerun reads the cache
    assert subprocess.run(command, capture_output=True, cwd=ROOT).returncode == 0
    assert json.loads(output.read_text()) == results


def test_the_zoo_command_refuses_bad_seeds_and_reporting_tuning_seeds(tmp_path, capsys):
    sys.path.insert(0, str(ROOT))
    from experiments.zoo import main, parse_seeds

    assert parse_seeds("1000-1002,1005,1001") == [1000, 1001, 1002, 1005]
    for argv in (["--seeds", "12x"], ["--seeds", "9-3"], ["--seeds", "5-6", "--markdown", str(tmp_path / "z.md")]):
        with pytest.raises(SystemExit) as exit_:
            main([*argv, "--json", str(tmp_path / "z.json")])
        assert exit_.value.code == 2
    assert "never reported" in capsys.readouterr().err
    assert not (tmp_path / "z.md").exists()


def test_a_not_decidable_verdict_is_classed_by_the_truth_of_its_undecided_feature():
    sys.path.insert(0, str(ROOT))
    from experiments.zoo import undecided_reason

    seed = next(s for s in TUNING_SEEDS if zoo_scene(s).truth.features)
    zoo = zoo_scene(seed)
    feature = next(f for f in zoo.part_file["features"] if f["name"] in zoo.truth.features)
    true = zoo.truth.features[feature["name"]]
    margin = min(abs(true - (feature["nominal"] + limit)) for limit in feature["tolerance"])
    assert margin > 0.05  # the zoo draws in-tolerance sizes within 0.4 of their tolerance, out ones beyond 1.5

    def result(cold: float, uncertainty: float) -> dict:
        return {"seed": seed, "verdict": "NotDecidable", "surface": {"verdict": "OK"},
                "features": {feature["name"]: {"verdict": "NotDecidable", "cold": cold, "uncertainty": uncertainty}}}

    assert undecided_reason(result(true, margin + 0.01)) == "limit"
    assert undecided_reason(result(true + 0.5 * (margin - 0.01), margin - 0.01)) == "covered"
    assert undecided_reason(result(true + 2 * (margin - 0.01), margin - 0.01)) == "error"
    decided = result(true, margin)
    decided["features"][feature["name"]]["verdict"] = "OK"
    assert undecided_reason(decided) == "unknown"

"""align_nominal against constructed one-sided views with ground-truth poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.inspection.alignment import _axis_of_revolution, align_nominal
from services.inspection.nominal import NominalSurface
from services.simulation.hot_part import cylinder_mesh, revolved_mesh, tube_mesh
from services.simulation.raycast import cast_rays
from services.simulation.scene import Mesh, Scene


def _seen_from(nominal: NominalSurface, viewer: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nominal's samples (part frame) that a viewer at ``viewer`` sees, facing it and first on its ray, and
    their outward normals (which face the viewer, as a reconstruction's normals face its camera)."""
    samples, normals = nominal.samples, nominal.sample_normals
    toward = samples - viewer
    distance = np.linalg.norm(toward, axis=1)
    facing = np.einsum("ij,ij->i", normals, toward) < -0.2 * distance
    scene = Scene(surfaces=[Mesh(vertices=nominal.vertices.tolist(), faces=nominal.triangles.tolist())])
    hits = cast_rays(scene, viewer, toward[facing])
    first = np.zeros(len(samples), dtype=bool)
    first[np.flatnonzero(facing)] = hits.distance > distance[facing] - 1e-3
    return samples[first], normals[first]


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = rng.uniform(-300.0, 300.0, 3) + [0.0, 0.0, 800.0]
    return pose


def _pose_error(nominal: NominalSurface, found: np.ndarray, truth: np.ndarray) -> float:
    """Worst distance of the nominal's samples placed by ``found`` from the nominal placed by ``truth`` (mm):
    zero for any pose the part's symmetries cannot tell from the truth."""
    world = nominal.samples @ found[:3, :3].T + found[:3, 3]
    back = (world - truth[:3, 3]) @ truth[:3, :3]
    return float(np.abs(nominal.signed_distance(back)).max())


@pytest.mark.parametrize("viewer", [(0.0, 30.0, -570.0), (-40.0, 0.0, -570.0)])
def test_a_tube_as_long_as_it_is_wide_seen_from_one_side_is_found_where_it_lies(viewer):
    # an open tube of 51 mm by 50 mm with a 4.3 mm wall seen from its side (zoo tuning seed 1's tube): the
    # view's centroid lies a quarter of the diameter off the tube's, and started from it the ICP settled with
    # the seen outer wall on the inner wall of a tube moved by the wall's thickness (rms 0.87 mm, 4.8 mm off)
    nominal = NominalSurface(*tube_mesh(25.5, 21.2, 50.4, segments=180, max_edge_mm=3.0))
    seen, _ = _seen_from(nominal, np.array(viewer))
    truth = _pose(1)
    points = seen @ truth[:3, :3].T + truth[:3, 3]
    coarse = align_nominal(points, nominal, max_distance_mm=5.0, polish=False)
    alignment = align_nominal(points, nominal, max_distance_mm=5.0, start=coarse.matrix)
    assert alignment.inlier_fraction == 1.0
    assert alignment.rms_mm < 0.05
    assert _pose_error(nominal, alignment.matrix, truth) < 0.5


def _flanged_shaft() -> NominalSurface:
    """A flanged shaft about as long as it is wide (as zoo flanges are): body radius 28.4 mm, 75 mm long, a
    flange of radius 43.9 mm and 19.1 mm thick 5 mm from one end."""
    half, radius, flange_radius, start, thickness = 37.5, 28.4, 43.9, -32.5, 19.1
    profile = [(half, 0.0), (half, radius), (start + thickness, radius), (start + thickness, flange_radius),
               (start, flange_radius), (start, radius), (-half, radius), (-half, 0.0)]
    return NominalSurface(*revolved_mesh(profile, 180, 3.0))


def _aligned_view(nominal: NominalSurface, viewer, seed: int = 1):
    """The view from ``viewer`` placed by pose ``seed``, aligned with its normals; the alignment and the truth."""
    seen, normals = _seen_from(nominal, np.array(viewer, dtype=float))
    truth = _pose(seed)
    points, normals = seen @ truth[:3, :3].T + truth[:3, 3], normals @ truth[:3, :3].T
    coarse = align_nominal(points, nominal, max_distance_mm=5.0, polish=False, normals=normals)
    return align_nominal(points, nominal, max_distance_mm=5.0, start=coarse.matrix, normals=normals), truth


def test_a_flanged_shaft_whose_view_has_no_telling_principal_axes_is_found_where_it_lies():
    # seen from here, the view's principal axes lie at an angle to the shaft's: every axis-to-axis start
    # settled 27 mm off (a pose error; rms 2.5 mm with 78 % inliers), as zoo flanges did (docs/zoo.md, I1)
    nominal = _flanged_shaft()
    alignment, truth = _aligned_view(nominal, (-432.0, -321.0, -187.0))
    assert alignment.inlier_fraction == 1.0
    assert alignment.rms_mm < 0.05
    assert _pose_error(nominal, alignment.matrix, truth) < 0.5


def test_a_tube_seen_from_its_side_is_not_put_with_its_outer_wall_on_the_inner_one():
    # without the normals this view settled 4.9 mm off, the seen outer wall on the nominal's inner wall, whose
    # outward normal faces away from the camera: every point within 5 mm, so the inlier count could not tell
    nominal = NominalSurface(*tube_mesh(25.5, 21.2, 50.4, segments=180, max_edge_mm=3.0))
    alignment, truth = _aligned_view(nominal, (108.0, -113.0, 548.0))
    assert alignment.inlier_fraction == 1.0
    assert alignment.rms_mm < 0.05
    assert _pose_error(nominal, alignment.matrix, truth) < 0.5


def test_the_axis_of_revolution_of_a_one_sided_view_is_found_from_its_normals():
    nominal = _flanged_shaft()
    seen, normals = _seen_from(nominal, np.array([-432.0, -321.0, -187.0]))
    truth = _pose(3)
    points, normals = seen @ truth[:3, :3].T + truth[:3, 3], normals @ truth[:3, :3].T
    direction, point = _axis_of_revolution(points, normals)
    true_direction = truth[:3, 0]  # the shaft's axis is the part frame's x
    assert abs(direction @ true_direction) > np.cos(np.radians(0.5))
    offset = point - truth[:3, 3]
    assert np.linalg.norm(offset - (offset @ true_direction) * true_direction) < 0.2


def test_normals_that_are_not_one_per_point_are_refused():
    nominal = NominalSurface(*cylinder_mesh(20.0, 50.0, 60))
    with pytest.raises(ValueError, match="one normal per point"):
        align_nominal(nominal.samples[:100], nominal, normals=nominal.sample_normals[:99])

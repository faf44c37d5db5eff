import numpy as np
import pytest

from services.simulation.raycast import cast_rays
from services.simulation.scene import Cylinder, Mesh, Plane, Scene, Sphere


def _random_directions(count, spread, seed=0):
    rng = np.random.default_rng(seed)
    directions = np.column_stack([rng.uniform(-spread, spread, (count, 2)), np.ones(count)])
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _uv_sphere(centre, radius, segments=96, rings=48):
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = np.asarray(centre) + radius * np.stack(
        [np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    faces = []
    for i in range(rings):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [[a, b, d], [a, d, c]]
    return vertices, np.array(faces)


def test_plane_hits_match_the_closed_form():
    plane = Plane(center=[10, -5, 500], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[300, 200])
    directions = _random_directions(20000, 0.5)
    hits = cast_rays(Scene(surfaces=[plane]), np.zeros(3), directions)
    expected_distance = 500 / directions[:, 2]
    expected_points = directions * expected_distance[:, None]
    inside = (np.abs(expected_points[:, 0] - 10) <= 150) & (np.abs(expected_points[:, 1] + 5) <= 100)
    assert 0.2 < inside.mean() < 0.9
    np.testing.assert_array_equal(hits.surface, np.where(inside, 0, -1))
    np.testing.assert_allclose(hits.distance[inside], expected_distance[inside], rtol=1e-12)
    np.testing.assert_allclose(hits.points[inside], expected_points[inside], atol=1e-9)
    assert np.all(np.isinf(hits.distance[~inside])) and np.all(np.isnan(hits.points[~inside]))
    np.testing.assert_allclose(hits.normals[inside], np.tile([0, 0, -1.0], (inside.sum(), 1)))


def test_plane_normal_faces_the_ray_from_either_side():
    plane = Plane(center=[0, 0, 100], normal=[0, 0, 1], u_axis=[0, 1, 0], size=[10, 10])
    hits = cast_rays(Scene(surfaces=[plane]), np.array([[0, 0, 0], [0, 0, 200.0]]), np.array([[0, 0, 1], [0, 0, -1.0]]))
    np.testing.assert_allclose(hits.normals, [[0, 0, -1], [0, 0, 1]])
    np.testing.assert_allclose(hits.distance, [100, 100])


def test_sphere_hits_lie_on_the_sphere_and_are_the_nearest_root():
    centre, radius = np.array([20.0, -10.0, 480.0]), 100.0
    directions = _random_directions(20000, 0.35, seed=1)
    hits = cast_rays(Scene(surfaces=[Sphere(center=centre.tolist(), radius=radius)]), np.zeros(3), directions)
    along = directions @ centre
    miss_distance = np.sqrt(np.maximum(centre @ centre - along**2, 0))
    expected_hit = miss_distance < radius
    assert 0.2 < expected_hit.mean() < 0.9
    np.testing.assert_array_equal(hits.surface >= 0, expected_hit)
    np.testing.assert_allclose(hits.distance[expected_hit],
                               along[expected_hit] - np.sqrt(radius**2 - miss_distance[expected_hit] ** 2), rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(hits.points[expected_hit] - centre, axis=1), radius, rtol=1e-12)
    np.testing.assert_allclose(hits.normals[expected_hit], (hits.points[expected_hit] - centre) / radius, atol=1e-12)


def test_ray_from_inside_a_sphere_hits_the_far_side():
    hits = cast_rays(Scene(surfaces=[Sphere(center=[0, 0, 0], radius=50)]), np.zeros(3), np.array([[1.0, 0, 0]]))
    assert hits.distance[0] == pytest.approx(50)
    np.testing.assert_allclose(hits.normals[0], [-1, 0, 0])


def test_cylinder_side_and_cap_hits_are_exact():
    cylinder = Cylinder(center=[0, 0, 600], axis=[1, 0, 0], radius=60, length=200)
    scene = Scene(surfaces=[cylinder])
    origins = np.array([[0, 0, 0], [30, 25, 0], [500, 10, 600], [500, 10, 600], [0, 80, 0]], dtype=float)
    directions = np.array([[0, 0, 1], [0, 0, 1], [-1, 0, 0], [-1, 0.0, 1e-9], [0, 0, 1]], dtype=float)
    hits = cast_rays(scene, origins, directions)
    np.testing.assert_allclose(hits.distance[:4], [540, 600 - np.sqrt(60**2 - 25**2), 400, 400], rtol=1e-12)
    np.testing.assert_allclose(hits.normals[1], [0, 25 / 60, -np.sqrt(60**2 - 25**2) / 60], atol=1e-12)
    np.testing.assert_allclose(hits.normals[2], [1, 0, 0])
    assert hits.surface[4] == -1


def test_cylinder_random_hits_lie_on_its_surface():
    cylinder = Cylinder(center=[5, 15, 500], axis=[1, 0.3, 0.2], radius=40, length=150)
    axis = np.array(cylinder.axis) / np.linalg.norm(cylinder.axis)
    directions = _random_directions(20000, 0.3, seed=2)
    hits = cast_rays(Scene(surfaces=[cylinder]), np.zeros(3), directions)
    hit = hits.surface == 0
    assert hit.mean() > 0.1
    offset = hits.points[hit] - cylinder.center
    height = offset @ axis
    radial = np.linalg.norm(offset - height[:, None] * axis, axis=1)
    on_side = np.isclose(radial, 40, rtol=1e-9) & (np.abs(height) <= 75 + 1e-9)
    on_cap = np.isclose(np.abs(height), 75, rtol=1e-9) & (radial <= 40 + 1e-9)
    assert np.all(on_side | on_cap) and on_cap.any() and on_side.any()
    assert np.all(np.einsum("ij,ij->i", hits.normals[hit], directions[hit]) < 0)


def test_open_cylinder_shows_its_inside():
    tube = Cylinder(center=[0, 0, 300], axis=[0, 0, 1], radius=20, length=100, capped=False)
    hits = cast_rays(Scene(surfaces=[tube]), np.zeros(3), np.array([[0, 0, 1.0], [0.07, 0, 1]]))
    assert hits.surface[0] == -1
    assert hits.surface[1] == 0 and 250 < hits.points[1, 2] < 350
    np.testing.assert_allclose(np.hypot(*hits.points[1, :2]), 20)


def test_two_triangle_mesh_equals_the_plane():
    plane = Plane(center=[0, 0, 400], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[200, 100])
    mesh = Mesh(vertices=[[-100, -50, 400], [100, -50, 400], [100, 50, 400], [-100, 50, 400]],
                faces=[[0, 1, 2], [0, 2, 3]])
    directions = _random_directions(20000, 0.4, seed=3)
    from_plane = cast_rays(Scene(surfaces=[plane]), np.zeros(3), directions)
    from_mesh = cast_rays(Scene(surfaces=[mesh]), np.zeros(3), directions)
    np.testing.assert_array_equal(from_mesh.surface, from_plane.surface)
    np.testing.assert_allclose(from_mesh.distance, from_plane.distance, rtol=1e-12)
    np.testing.assert_allclose(from_mesh.normals, from_plane.normals, atol=1e-12)


def test_tessellated_sphere_agrees_with_the_analytic_sphere_within_its_chord_error():
    centre, radius, segments, rings = [0.0, 0.0, 480.0], 100.0, 96, 48
    vertices, faces = _uv_sphere(centre, radius, segments, rings)
    mesh = Mesh(vertices=vertices.tolist(), faces=faces.tolist())
    directions = _random_directions(50000, 0.25, seed=4)
    exact = cast_rays(Scene(surfaces=[Sphere(center=centre, radius=radius)]), np.zeros(3), directions)
    tessellated = cast_rays(Scene(surfaces=[mesh]), np.zeros(3), directions)
    both = (exact.surface == 0) & (tessellated.surface == 0)
    assert both.sum() > 0.95 * (exact.surface == 0).sum()
    sagitta = radius * (1 - np.cos(np.pi / rings))
    radial = np.linalg.norm(tessellated.points[both] - centre, axis=1)
    assert np.all((radial >= radius - 2 * sagitta) & (radial <= radius + 1e-9))
    depth_error = tessellated.distance[both] - exact.distance[both]
    assert np.all(depth_error >= -1e-9)  # the inscribed mesh lies inside the sphere
    facing = -np.einsum("ij,ij->i", exact.normals[both], directions[both]) > 0.5
    assert depth_error[facing].max() <= 2 * sagitta / 0.5


def test_nearest_surface_wins_and_t_min_skips_the_start():
    scene = Scene(surfaces=[Plane(center=[0, 0, 500], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[100, 100]),
                            Sphere(center=[0, 0, 300], radius=50)])
    hits = cast_rays(scene, np.zeros(3), np.array([[0, 0, 1.0]]))
    assert hits.surface[0] == 1 and hits.distance[0] == pytest.approx(250)
    leaving = cast_rays(scene, np.array([[0, 0, 250.0]]), np.array([[0, 0, 1.0]]), t_min=1e-3)
    assert leaving.surface[0] == 1 and leaving.distance[0] == pytest.approx(100)


def test_bad_rays_are_refused():
    scene = Scene(surfaces=[Sphere(center=[0, 0, 10], radius=1)])
    with pytest.raises(ValueError, match="shape"):
        cast_rays(scene, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="non-zero"):
        cast_rays(scene, np.zeros(3), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="origins"):
        cast_rays(scene, np.zeros((3, 3)), np.ones((2, 3)))

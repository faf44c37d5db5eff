import numpy as np
import pytest

from services.geometry.camera import project_points
from services.simulation.presets import forging_rig, forging_scene, paper_plane, paper_rig, paper_sphere
from services.simulation.raycast import cast_rays
from services.simulation.render import render_view

PAPER_DEPTHS = range(430, 571, 20)


def _project(device, points):
    return project_points(points, device.K, device.dist, device.R, device.t)


def _margin(device, pixels):
    """Smallest distance in pixels from any point to the image border (negative if outside)."""
    return min(pixels.min(), (device.width - 1 - pixels[:, 0]).min(), (device.height - 1 - pixels[:, 1]).min())


def test_paper_rig_matches_the_paper():
    rig = paper_rig()
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    np.testing.assert_allclose(camera.R, [[0.94, 0, 0.342], [0, 1, 0], [-0.342, 0, 0.94]], atol=1e-3)
    np.testing.assert_allclose(camera.centre, [400, 0, 0], atol=1e-12)
    np.testing.assert_allclose(projector.R, np.eye(3))
    np.testing.assert_allclose(projector.t, 0)
    assert camera.size == projector.size == (1024, 768) and camera.dist.size == projector.dist.size == 0
    np.testing.assert_allclose(camera.R[2], [-np.sin(np.radians(20)), 0, np.cos(np.radians(20))])


@pytest.mark.parametrize("depth", PAPER_DEPTHS)
def test_paper_plane_is_fully_visible_and_lit_with_a_margin(depth):
    rig = paper_rig()
    edge = np.linspace(-1, 1, 21)
    outline = np.concatenate([np.column_stack([150 * edge, np.full(21, side * 100.0)]) for side in (-1, 1)]
                             + [np.column_stack([np.full(21, side * 150.0), 100 * edge]) for side in (-1, 1)])
    points = np.column_stack([outline, np.full(len(outline), float(depth))])
    assert _margin(rig.devices["camera"], _project(rig.devices["camera"], points)) > 10
    assert _margin(rig.devices["projector"], _project(rig.devices["projector"], points)) > 10


@pytest.mark.parametrize("depth", [430, 570])
def test_every_camera_pixel_on_the_paper_plane_is_lit(depth):
    rig = paper_rig()
    truth = render_view(paper_plane(depth), rig.devices["camera"], rig.devices["projector"], supersample=1).truth
    on_plane = truth.surface == 0
    assert on_plane.sum() > 50_000
    assert np.all(truth.lit[on_plane])
    np.testing.assert_allclose(truth.points[on_plane][:, 2], depth)


def test_paper_spheres_are_fully_in_view():
    rig = paper_rig()
    for radius in (80, 130):
        sphere = paper_sphere(radius).surfaces[0]
        assert sphere.center == [0.0, 0.0, 480.0] and sphere.radius == radius
        angles = np.linspace(0, 2 * np.pi, 72)
        rim = np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.full(72, 480.0)])
        for name in ("camera", "projector"):
            assert _margin(rig.devices[name], _project(rig.devices[name], rim)) > 10


def _quarter_size(device):
    """The same view at a quarter of the resolution."""
    K = device.K.copy()
    K[:2] /= 4
    K[:2, 2] = (K[:2, 2] * 4 + 0.5) / 4 - 0.5
    return device.replace(**{"width": device.width // 4, "height": device.height // 4, "K": K.tolist()})


def test_forging_rig_devices():
    rig = forging_rig()
    assert {name: (d.kind, d.width, d.height) for name, d in rig.devices.items()} == {
        "projector": ("projector", 1280, 800), "camera": ("camera", 1280, 800), "thermal": ("thermal", 320, 256)}
    for name, centre in (("projector", [0, 0, 0]), ("camera", [350, 0, 0]), ("thermal", [180, -120, 0])):
        device = rig.devices[name]
        np.testing.assert_allclose(device.centre, centre, atol=1e-9)
        assert any(device.dist)
        centre_pixel = _project(device, np.array([[0.0, 0.0, 600.0]]))[0]
        np.testing.assert_allclose(centre_pixel, [(device.width - 1) / 2, (device.height - 1) / 2], atol=1e-6)


def test_forging_scene_has_points_the_camera_sees_lit_but_the_thermal_camera_cannot():
    rig = forging_rig()
    camera, projector, thermal = (rig.devices[name] for name in ("camera", "projector", "thermal"))
    scene = forging_scene()
    truth = render_view(scene, _quarter_size(camera), projector, supersample=1).truth
    lit_points = truth.points[truth.lit]
    assert set(np.unique(truth.surface[truth.lit])) == {0, 1, 2}
    thermal_centre = thermal.centre
    towards = lit_points - thermal_centre
    distance = np.linalg.norm(towards, axis=1)
    hidden = cast_rays(scene, thermal_centre, towards).distance < distance - 1e-3
    in_thermal_view = np.all((_project(thermal, lit_points) >= 0) & (_project(thermal, lit_points)
                                                                   <= [thermal.width - 1, thermal.height - 1]), axis=1)
    assert in_thermal_view.mean() > 0.9
    assert 0.01 < (hidden & in_thermal_view).mean() < 0.5

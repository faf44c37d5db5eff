import numpy as np
import pytest

from services.geometry.camera import pixel_grid, pixel_rays, project_points
from services.geometry.camera_model import CameraModel
from services.simulation.raycast import cast_rays
from services.simulation.render import CameraEffects, ProjectorEffects, expose, render_frames, render_view
from services.simulation.scene import Albedo, Mesh, Plane, Scene, Sphere

pytestmark = pytest.mark.integration

NOISELESS_16 = CameraEffects(bit_depth=16)


def _plane(depth, size=(600, 600), normal=(0, 0, -1), u_axis=(1, 0, 0), albedo=Albedo(), centre_x=0.0):
    return Plane(center=[centre_x, 0, depth], normal=list(normal), u_axis=list(u_axis), size=list(size), albedo=albedo)


def _uniform(projector, value, count=1):
    return np.full((count, projector.height, projector.width), value, dtype=np.uint8)


def _project(device, points):
    return project_points(points, device.K, device.dist, device.R, device.t)


def test_ground_truth_points_project_back_to_their_pixel_centres(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    scene = Scene(surfaces=[_plane(400, normal=(0.2, 0, -1), u_axis=(1, 0, 0.2))])
    truth = render_view(scene, camera, projector).truth
    seen = np.isfinite(truth.depth)
    assert seen.mean() > 0.5 and truth.lit.mean() > 0.3
    centres = pixel_grid(camera.width, camera.height).reshape(camera.height, camera.width, 2)
    np.testing.assert_allclose(_project(camera, truth.points[seen]), centres[seen], atol=1e-6)
    camera_frame = truth.points[seen] @ camera.R.T + camera.t
    np.testing.assert_allclose(truth.depth[seen], camera_frame[:, 2])
    lit_centre = np.isfinite(truth.projector_pixels[..., 0])
    np.testing.assert_allclose(truth.projector_pixels[lit_centre], _project(projector, truth.points[lit_centre]))
    assert np.all(lit_centre[truth.lit]) and np.all(truth.surface[seen] == 0) and np.all(truth.surface[~seen] == -1)


def _spot_centroid(frame, around, radius=6):
    u0, v0 = np.round(around).astype(int)
    window = frame[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1].astype(float)
    v, u = np.mgrid[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    return np.array([(u * window).sum(), (v * window).sum()]) / window.sum()


def _undistorted(device):
    return device.replace(**{"dist": []})


def test_a_projected_spot_lands_where_both_distorted_lens_models_say(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    scene = Scene(ambient=0.0, surfaces=[_plane(420)])
    spot = np.array([[128.0, 28.0]])  # near a projector corner, where distortion is strong

    def expected_camera_pixel(cam, proj):
        origin, direction = pixel_rays(spot, proj.K, proj.dist, proj.R, proj.t)
        return _project(cam, cast_rays(scene, origin, direction).points)[0]

    pattern = _uniform(projector, 0)
    pattern[0, 27:30, 127:130] = 255
    frame = render_frames(render_view(scene, camera, projector), pattern, np.random.default_rng(0), NOISELESS_16)[0]
    expected = expected_camera_pixel(camera, projector)
    assert np.linalg.norm(_spot_centroid(frame, expected) - expected) < 0.2
    assert np.linalg.norm(expected_camera_pixel(_undistorted(camera), _undistorted(projector)) - expected) > 2


def test_a_sphere_casts_its_projector_shadow_where_predicted(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    centre, radius = np.array([0.0, 0.0, 330.0]), 30.0
    scene = Scene(ambient=0.1, surfaces=[_plane(500), Sphere(center=centre.tolist(), radius=radius)])
    view = render_view(scene, camera, projector, supersample=1)
    truth = view.truth
    on_plane = truth.surface == 0
    points = truth.points[on_plane]
    rays = points / np.linalg.norm(points, axis=1, keepdims=True)  # the projector sits at the origin
    distance_to_centre_line = np.linalg.norm(centre - (rays @ centre)[:, None] * rays, axis=1)
    pixels = _project(projector, points)
    in_image = np.all((pixels >= -0.5) & (pixels <= [projector.width - 0.5, projector.height - 0.5]), axis=1)
    expected_lit = (distance_to_centre_line > radius) & in_image
    assert (~expected_lit & in_image).sum() > 100  # a visible shadow
    np.testing.assert_array_equal(truth.lit[on_plane], expected_lit)
    white = render_frames(view, _uniform(projector, 255), np.random.default_rng(0), NOISELESS_16)[0]
    shadow = on_plane.copy()
    shadow[on_plane] = ~expected_lit & in_image
    ambient_only = 65535 * 0.8 * 0.8 * 0.1
    np.testing.assert_allclose(white[shadow], ambient_only, atol=1)
    assert white[truth.lit & on_plane].min() > 3 * ambient_only


def test_lambertian_shading_albedo_and_ambient_light(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    tilt = np.radians(35)
    scene = Scene(ambient=0.1, surfaces=[_plane(400, normal=(np.sin(tilt), 0, -np.cos(tilt)),
                                                u_axis=(np.cos(tilt), 0, np.sin(tilt)), albedo=Albedo(base=0.6))])
    view = render_view(scene, camera, projector, supersample=1)
    white, black = render_frames(view, np.concatenate([_uniform(projector, 255), _uniform(projector, 0)]),
                                 np.random.default_rng(0), NOISELESS_16)
    truth = view.truth
    interior = truth.lit & np.all((truth.projector_pixels >= 1)
                                  & (truth.projector_pixels <= [projector.width - 2, projector.height - 2]), axis=-1)
    assert interior.sum() > 1000
    to_projector = projector.centre - truth.points[interior]
    cosine = to_projector @ np.array([np.sin(tilt), 0, -np.cos(tilt)]) / np.linalg.norm(to_projector, axis=1)
    assert np.ptp(cosine) > 0.1
    np.testing.assert_allclose(white[interior], 65535 * 0.8 * 0.6 * (0.1 + cosine), atol=1.0)
    seen = truth.surface == 0
    np.testing.assert_allclose(black[seen], 65535 * 0.8 * 0.6 * 0.1, atol=1.0)
    assert np.all(black[~seen] == 0)


def _facing_rig(width=41, focal=100.0):
    """Camera and projector sharing the origin, looking along +z, no distortion."""
    K = [[focal, 0, (width - 1) / 2], [0, focal, (width - 1) / 2], [0, 0, 1]]
    camera = CameraModel(kind="camera", width=width, height=width, K=K)
    projector = CameraModel(kind="projector", width=4 * width, height=4 * width,
                       K=[[4 * focal, 0, (4 * width - 1) / 2], [0, 4 * focal, (4 * width - 1) / 2], [0, 0, 1]])
    return camera, projector


def test_supersampling_integrates_the_pixel_area_at_edges():
    camera, projector = _facing_rig()
    edge_x = (30 + 0.5 / 3 - 20) / 100 * 400  # between the centre and right sub-samples of column 30
    scene = Scene(ambient=0.0, surfaces=[_plane(400, size=(2 * edge_x + 400, 300), centre_x=-200)])
    frames = {}
    for supersample in (1, 3):
        view = render_view(scene, camera, projector, supersample)
        frames[supersample] = render_frames(view, _uniform(projector, 255), np.random.default_rng(0), NOISELESS_16)[0]
    row = 20
    assert frames[1][row, 30] == pytest.approx(frames[1][row, 29], rel=1e-3)
    assert frames[3][row, 30] == pytest.approx(2 / 3 * frames[3][row, 29], rel=1e-3)
    assert frames[3][row, 31] == 0


def test_sensor_noise_has_the_requested_statistics():
    irradiance = np.full((300, 300), 0.5)
    grey = 0.8 * 0.5 * 255
    frame = expose(irradiance, CameraEffects(noise_sigma=2.0), np.random.default_rng(1)).astype(float)
    assert frame.mean() == pytest.approx(grey, abs=0.05)
    assert frame.std() == pytest.approx(np.sqrt(2.0**2 + 1 / 12), rel=0.03)
    shot = expose(irradiance, CameraEffects(noise_sigma=2.0, shot_noise_gain=0.5, bit_depth=16),
                  np.random.default_rng(2)).astype(float)
    assert shot.std() == pytest.approx(np.sqrt(4 + 0.5 * 0.8 * 0.5 * 65535), rel=0.03)


def test_quantisation_rounds_and_saturation_clips():
    for bits, dtype in ((8, np.uint8), (16, np.uint16)):
        full = (1 << bits) - 1
        levels = np.arange(0, 2 * full, max(1, full // 500))
        irradiance = ((levels + 0.3) / full).reshape(1, -1)  # 0.3 above each level: no rounding ties
        frame = expose(irradiance, CameraEffects(exposure=1.0, bit_depth=bits), np.random.default_rng(0))
        assert frame.dtype == dtype
        np.testing.assert_array_equal(frame[0], np.minimum(levels, full))
        assert np.mean(frame == full) > 0.45


def test_camera_and_projector_gamma():
    irradiance = np.array([[0.25]])
    assert expose(irradiance, CameraEffects(exposure=1.0, gamma=2.0, bit_depth=16),
                  np.random.default_rng(0))[0, 0] == round(65535 * 0.5)
    camera, projector = _facing_rig()
    view = render_view(Scene(ambient=0.0, surfaces=[_plane(400)]), camera, projector)
    effects = ProjectorEffects(gamma=2.2)
    half, full = render_frames(view, np.concatenate([_uniform(projector, 128), _uniform(projector, 255)]),
                               np.random.default_rng(0), NOISELESS_16, effects)
    np.testing.assert_allclose(half[20, 20] / full[20, 20], (128 / 255) ** 2.2, rtol=1e-3)
    black = render_frames(view, _uniform(projector, 0), np.random.default_rng(0), NOISELESS_16,
                          ProjectorEffects(black_level=0.05))[0]
    np.testing.assert_allclose(black[20, 20] / full[20, 20], 0.05, rtol=1e-3)


def _second_moment(profile):
    x = np.arange(len(profile))
    weights = profile / profile.sum()
    mean = (x * weights).sum()
    return ((x - mean) ** 2 * weights).sum()


def test_defocus_blur_spreads_light_and_keeps_its_energy():
    delta = np.zeros((41, 41))
    delta[20, 20] = 0.5
    blurred = expose(delta, CameraEffects(exposure=1.0, blur_sigma=2.0, bit_depth=16), np.random.default_rng(0))
    assert blurred.sum() == pytest.approx(0.5 * 65535, rel=1e-3)
    assert _second_moment(blurred.sum(axis=0).astype(float)) == pytest.approx(4.0, rel=0.02)

    camera, projector = _facing_rig()
    view = render_view(Scene(ambient=0.0, surfaces=[_plane(400)]), camera, projector)
    stripe = _uniform(projector, 0)
    stripe[0, :, 80:84] = 255
    sharp, soft = (render_frames(view, stripe, np.random.default_rng(0), NOISELESS_16,
                                 ProjectorEffects(blur_sigma=sigma))[0][20].astype(float) for sigma in (0.0, 8.0))
    assert _second_moment(soft) > 3 * _second_moment(sharp)
    assert soft.sum() == pytest.approx(sharp.sum(), rel=0.01)


def test_frames_are_deterministic_by_seed(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    view = render_view(Scene(surfaces=[_plane(400, albedo=Albedo(texture_amplitude=0.2, seed=3))]), camera, projector)
    patterns = np.random.default_rng(5).integers(0, 256, (2, projector.height, projector.width), dtype=np.uint8)
    effects = CameraEffects(noise_sigma=1.5, blur_sigma=0.7)
    first = render_frames(view, patterns, np.random.default_rng(11), effects)
    np.testing.assert_array_equal(first, render_frames(view, patterns, np.random.default_rng(11), effects))
    assert np.any(first != render_frames(view, patterns, np.random.default_rng(12), effects))


def test_bad_arguments_are_refused(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    scene = Scene(surfaces=[_plane(400)])
    with pytest.raises(ValueError, match="odd"):
        render_view(scene, camera, projector, supersample=2)
    view = render_view(scene, camera, projector, supersample=1)
    with pytest.raises(ValueError, match=r"patterns must have shape \(F, 120, 160\)"):
        render_frames(view, np.zeros((1, 10, 10), np.uint8), np.random.default_rng(0))
    with pytest.raises(ValueError, match="bit depth"):
        CameraEffects(bit_depth=12)
    with pytest.raises(ValueError, match="black level"):
        ProjectorEffects(black_level=1.0)


def test_aimed_devices_helper_matches_its_target(aimed):
    device = aimed("camera", (100, 80), 120.0, (200, -50, 0), (0, 0, 500))
    np.testing.assert_allclose(_project(device, np.array([[0.0, 0.0, 500.0]]))[0], [49.5, 39.5])


def test_a_two_triangle_mesh_renders_like_the_same_plane(small_rig):
    camera, projector = small_rig.devices["camera"], small_rig.devices["projector"]
    mesh = Mesh(vertices=[[-150, -100, 400], [150, -100, 400], [150, 100, 400], [-150, 100, 400]],
                faces=[[0, 1, 2], [0, 2, 3]], albedo=Albedo(texture_amplitude=0.2, seed=1))
    plane = _plane(400, size=(300, 200), albedo=Albedo(texture_amplitude=0.2, seed=1))
    patterns = np.random.default_rng(2).integers(0, 256, (2, projector.height, projector.width), dtype=np.uint8)
    views = [render_view(Scene(surfaces=[surface]), camera, projector) for surface in (plane, mesh)]
    frames = [render_frames(view, patterns, np.random.default_rng(0), NOISELESS_16) for view in views]
    np.testing.assert_allclose(views[1].truth.depth, views[0].truth.depth, rtol=1e-12)
    np.testing.assert_array_equal(views[1].truth.lit, views[0].truth.lit)
    assert np.abs(frames[1].astype(int) - frames[0]).max() <= 1
    assert views[0].truth.lit.mean() > 0.2


@pytest.mark.parametrize("effects", [ProjectorEffects(), ProjectorEffects(gamma=2.2, black_level=0.03, blur_sigma=0.7)])
def test_8_bit_patterns_get_the_light_the_formula_gives_their_values(effects):
    from services.simulation.render import projector_light

    pattern = np.random.default_rng(0).integers(0, 256, (40, 60)).astype(np.uint8)
    as_float = projector_light(pattern.astype(np.float64) / 255.0, effects)  # the formula, without the table
    np.testing.assert_allclose(projector_light(pattern, effects), as_float, rtol=1e-6, atol=1e-7)
    assert projector_light(pattern, effects).dtype == np.float32

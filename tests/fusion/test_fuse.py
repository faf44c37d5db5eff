import numpy as np
import pytest

from services.fusion.fuse import ThermalView, fuse_temperature, view_angles
from services.geometry.camera import project_points

pytestmark = pytest.mark.integration


def test_seen_points_get_their_true_temperature(hot_scene):
    field = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, hot_scene.image)])
    error = np.abs(field.temperature - hot_scene.truth)[hot_scene.visible]
    # all but the guard band on the plate beside the bar's outline and the bar's mixed pixels along it (88 %)
    assert np.mean(np.isfinite(error)) > 0.85
    assert np.nanmedian(error) <= 1.0
    assert np.nanpercentile(error, 90) <= 2.0
    assert np.nanmax(error) <= 5.0  # no pixel that mixes the bar with the plate, or the plate with what lies beyond


def test_mixed_edge_pixels_get_no_temperature_without_the_footprint_test(hot_scene):
    """Both directions: the same scene without the footprint test (no blur assumed, a bilinear stencil
    alone) lets mixed pixels through; with the camera's blur they are NaN, and the points well inside
    the bar keep theirs."""
    view = ThermalView(hot_scene.thermal, hot_scene.image)
    with_test = fuse_temperature(hot_scene.points, hot_scene.normals, [view])
    error = np.abs(with_test.temperature - hot_scene.truth)[hot_scene.visible]
    assert np.nanmax(error) <= 5.0
    # a blur of 0 still covers the pixel's own area and the stencil: fewer points dropped, some of them mixed
    narrow = fuse_temperature(hot_scene.points, hot_scene.normals, [view], thermal_blur_px=0.0)
    narrow_error = np.abs(narrow.temperature - hot_scene.truth)[hot_scene.visible]
    assert np.mean(np.isfinite(narrow_error)) > np.mean(np.isfinite(error))
    assert np.nanmax(narrow_error) > 5.0  # the image's blur (0.6 px) reaches beyond a footprint without it


def test_occluded_points_are_nan_not_the_occluder_temperature(hot_scene):
    field = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, hot_scene.image)])
    occluded = ~hot_scene.visible
    assert occluded.sum() > 1000  # the bar hides part of the plate from the thermal camera
    assert np.mean(np.isnan(field.temperature[occluded])) >= 0.99


def test_occluded_points_would_read_the_occluder_without_the_z_buffer(hot_scene):
    """The scene tests occlusion for real: where hidden plate points project, the image shows the bar."""
    hidden_plate = ~hot_scene.visible & (hot_scene.points[:, 2] > 649)
    assert hidden_plate.sum() > 1000
    pixels = project_points(hot_scene.points[hidden_plate], hot_scene.thermal.K, hot_scene.thermal.dist,
                            hot_scene.thermal.R, hot_scene.thermal.t)
    column, row = np.rint(pixels).astype(int).T
    shown = hot_scene.image[row, column]
    assert np.median(np.abs(shown - hot_scene.truth[hidden_plate])) > 50


def test_view_angle_limit_leaves_grazing_points_nan(hot_scene):
    field = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, hot_scene.image)],
                             max_view_angle_deg=30.0)
    angle = np.rad2deg(view_angles(hot_scene.points, hot_scene.normals,
                                   hot_scene.thermal.centre))
    beyond = hot_scene.visible & (angle > 31)
    assert beyond.sum() > 1000
    assert np.all(np.isnan(field.temperature[beyond]))
    within = np.isfinite(field.temperature)
    assert np.all(field.view_angle[within] <= 30.0 + 1e-3)
    np.testing.assert_allclose(field.view_angle[within], angle[within], atol=1e-3)


def test_several_frames_average_the_noise(hot_scene):
    from tests.fusion.conftest import noiseless_image

    plate = hot_scene.visible & (hot_scene.points[:, 2] > 649)
    frames = noiseless_image(hot_scene) + np.random.default_rng(5).normal(0.0, 0.05, (4,) + hot_scene.image.shape)
    single = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, frames[0])])
    averaged = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, frames)])
    residual_single = single.temperature[plate] - hot_scene.truth[plate]
    residual_averaged = averaged.temperature[plate] - hot_scene.truth[plate]
    # 50 mK noise dominates the typical residual; four frames halve it (edge pixels blurred with the
    # background dominate the tails, so compare medians)
    assert np.nanmedian(np.abs(residual_averaged)) < 0.7 * np.nanmedian(np.abs(residual_single))


def test_views_are_weighted_by_cosine_of_view_angle_and_inverse_square_distance(hot_scene):
    from tests.fusion.conftest import look_at

    head_on = look_at("thermal", [0, 0, 0], [0, 0, 650], 380, 320, 256)
    oblique = look_at("thermal", [500, 0, 150], [0, 0, 650], 380, 320, 256)
    plate = hot_scene.points[:, 2] > 649
    points, normals = hot_scene.points[plate], hot_scene.normals[plate]
    uniform = [ThermalView(head_on, np.full((256, 320), 100.0)), ThermalView(oblique, np.full((256, 320), 200.0))]
    field = fuse_temperature(points, normals, uniform)
    # both cameras have f = 380 px: the weight is cos(angle) / distance^2 (the pixel's footprint's inverse)
    w_head_on = np.cos(view_angles(points, normals, head_on.centre)) / np.sum((points - head_on.centre) ** 2, axis=1)
    w_oblique = np.cos(view_angles(points, normals, oblique.centre)) / np.sum((points - oblique.centre) ** 2, axis=1)
    expected = (100 * w_head_on + 200 * w_oblique) / (w_head_on + w_oblique)
    both = np.isfinite(field.temperature) & (np.abs(field.temperature - 100) > 1) & (np.abs(field.temperature - 200) > 1)
    assert both.sum() > 1000
    np.testing.assert_allclose(field.temperature[both], expected[both], atol=1e-3)


def test_nan_pixels_of_a_frame_are_not_sampled(hot_scene):
    image = hot_scene.image.copy()
    image[:, : image.shape[1] // 2] = np.nan
    field = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, image)])
    assert np.isfinite(field.temperature).sum() > 1000
    pixels = project_points(hot_scene.points, hot_scene.thermal.K, hot_scene.thermal.dist,
                            hot_scene.thermal.R, hot_scene.thermal.t)
    in_nan_half = pixels[:, 0] < image.shape[1] // 2 - 1
    assert in_nan_half.sum() > 1000
    assert np.all(np.isnan(field.temperature[in_nan_half]))
    error = np.abs(field.temperature - hot_scene.truth)[hot_scene.visible]
    assert np.nanmedian(error) <= 1.0


def test_bad_arguments_are_refused(hot_scene):
    view = ThermalView(hot_scene.thermal, hot_scene.image)
    with pytest.raises(ValueError, match="normals"):
        fuse_temperature(hot_scene.points, hot_scene.normals[:10], [view])
    with pytest.raises(ValueError, match="thermal view"):
        fuse_temperature(hot_scene.points, hot_scene.normals, [])
    with pytest.raises(ValueError, match="limit"):
        fuse_temperature(hot_scene.points, hot_scene.normals, [view], max_view_angle_deg=95)
    with pytest.raises(ValueError, match="for this device"):
        ThermalView(hot_scene.thermal, hot_scene.image[:100])


def test_points_beside_a_saturated_pixel_get_no_temperature(hot_scene):
    image = hot_scene.image.copy()
    column = image.shape[1] // 2
    image[:, column] = np.nan  # one saturated column: beyond the camera's measuring range
    field = fuse_temperature(hot_scene.points, hot_scene.normals, [ThermalView(hot_scene.thermal, image)])
    pixels = project_points(hot_scene.points, hot_scene.thermal.K, hot_scene.thermal.dist,
                            hot_scene.thermal.R, hot_scene.thermal.t)
    beside = (np.abs(pixels[:, 0] - column) < 0.99) & hot_scene.visible
    assert beside.sum() > 20
    assert np.all(np.isnan(field.temperature[beside]))  # never the lower temperature of the other neighbours

import numpy as np
import pytest

from services.fusion.carving import (
    UnseenSpace, Witness, depth_map, occluder_samples, restore_consistent, skirt_segments,
    smooth_surfaces, unseen_space,
)
from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.geometry.camera_model import CameraModel

from tests.fusion.conftest import look_at


def _camera(width: int = 120, height: int = 100, focal: float = 200.0) -> CameraModel:
    return CameraModel(kind="camera", width=width, height=height,
                       K=[[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])


def _block_on_plane(camera: CameraModel, near: float = 500.0, far: float = 800.0) -> np.ndarray:
    depth = np.full((camera.height, camera.width), far)
    depth[30:70, 40:80] = near
    return depth


def test_skirts_stand_at_depth_jumps_between_the_two_depths():
    camera = _camera()
    depth = _block_on_plane(camera)
    segments = skirt_segments(depth, camera)
    assert len(segments) > 100  # the block's outline: 2 * (40 + 40) pixel pairs
    z = segments[..., 2]  # the camera is at the origin looking along +z: world z is depth
    assert z.min() > 500.0 and z.max() < 800.0
    assert np.all(z[:, 0] < z[:, 1])  # from just behind the near surface back to the far one
    # on the image, every skirt lies on the block's outline (the ray between a block pixel and a plane pixel)
    u = segments[:, 0, 0] / segments[:, 0, 2] * 200.0 + 59.5
    v = segments[:, 0, 1] / segments[:, 0, 2] * 200.0 + 49.5
    on_outline = (np.isclose(u, 39.5) | np.isclose(u, 79.5)) & (v > 29) & (v < 70)
    on_outline |= (np.isclose(v, 29.5) | np.isclose(v, 69.5)) & (u > 39) & (u < 80)
    assert on_outline.all()


def test_a_steep_smooth_surface_has_no_skirt():
    camera = _camera()
    columns = np.arange(camera.width, dtype=float)
    # a plane at 70 degrees to the image: depth grows 2.75 footprints a pixel, within the 4 the threshold allows
    depth = np.tile(600.0 * np.exp(columns * 2.75 / 200.0), (camera.height, 1))
    assert len(skirt_segments(depth, camera)) == 0
    # the same depths a pixel apart by 8 footprints are a jump
    steep = np.tile(600.0 * np.exp(columns * 8.0 / 200.0), (camera.height, 1))
    assert len(skirt_segments(steep, camera)) > 0


def test_a_hole_beside_a_near_surface_gets_a_skirt_back_to_the_far_depth():
    camera = _camera()
    depth = _block_on_plane(camera)
    depth[30:70, 80:86] = np.inf  # the block's dark flank beside it: no point
    segments = skirt_segments(depth, camera)
    u = segments[:, 0, 0] / segments[:, 0, 2] * 200.0 + 59.5
    beside = np.isclose(u, 79.5)
    assert beside.sum() >= 40
    assert np.all(segments[beside, 1, 2] > 780.0)  # back to the plane beyond the hole
    # and the plane's pixels across the hole get skirts forward from the block's depth
    across = np.isclose(u, 85.5)
    assert across.sum() >= 40 and np.all(segments[across, 0, 2] < 510.0)
    # a hole inside one surface bounds nothing
    inside = np.full((camera.height, camera.width), 700.0)
    inside[40:45, 50:55] = np.inf
    assert len(skirt_segments(inside, camera)) == 0


def test_smooth_surfaces_split_at_jumps():
    camera = _camera()
    labels, count = smooth_surfaces(_block_on_plane(camera), camera)
    assert count == 2
    assert len(np.unique(labels[30:70, 40:80])) == 1 and labels[50, 60] != labels[5, 5]


def test_another_witness_carves_the_space_it_saw_through():
    camera = _camera()
    other = look_at("camera", [300, 0, 0], [0, 0, 700], 200.0, 120, 100)
    segment = np.array([[[0.0, 0.0, 600.0], [0.0, 0.0, 700.0]]])
    view = look_at("thermal", [-200, 0, 0], [0, 0, 650], 200.0, 120, 100)
    # the other camera measured a surface behind the whole segment: it saw through it
    seen_through = UnseenSpace(segment, np.array([0]), ((camera, np.full((100, 120), np.inf)),
                                                        (other, np.full((100, 120), 2000.0))), np.empty(0, int),
                               np.empty((0, 3), int))
    assert len(occluder_samples(seen_through, view, 2.0)) == 0
    # where it measured nothing the space is unknown to it, and the skirt stays; its owner never carves it
    unknown = UnseenSpace(segment, np.array([0]), ((camera, np.full((100, 120), 1.0)),
                                                   (other, np.full((100, 120), np.inf))), np.empty(0, int),
                          np.empty((0, 3), int))
    samples = occluder_samples(unknown, view, 2.0)
    assert len(samples) >= 2
    assert samples[:, 2].min() == pytest.approx(600.0) and samples[:, 2].max() == pytest.approx(700.0)


def test_readings_only_the_skirts_took_come_back_where_their_neighbours_vouch():
    """One witness image, 20 x 40 pixels: a hot part on the left (1000 C, rising 5 K a column), a cool wall on
    the right (30 C). The skirts took a band across the part, whose readings are its own, and a block of the wall,
    which reads the part's temperature (the hot flank in front of it)."""
    camera = _camera(40, 20)
    rows, columns = np.mgrid[0:20, 0:40]
    rows, columns = rows.ravel(), columns.ravel()
    surfaces = np.where(columns < 20, 1, 2)
    truth = np.where(columns < 20, 1000.0 + 5.0 * columns, 30.0)
    plain = truth + np.random.default_rng(3).normal(0.0, 1.0, len(truth))
    carved = plain.copy()
    band = (columns >= 6) & (columns <= 14)  # wider than the vouching window: it grows inward ring by ring
    block = (columns >= 26) & (columns <= 31) & (rows >= 5) & (rows <= 14)
    plain[block] = 1000.0
    carved[band | block] = np.nan
    lone = 0  # a point on a surface of its own: nothing vouches for it
    surfaces[lone] = 3
    carved[lone] = np.nan
    space = UnseenSpace(np.empty((0, 2, 3)), np.empty(0, int), ((camera, np.zeros((20, 40))),), surfaces,
                        np.column_stack([np.zeros(len(rows), int), rows, columns]))
    restored = restore_consistent(plain, carved, space)
    assert np.array_equal(restored[band], plain[band])
    assert np.isnan(restored[block]).all()
    assert np.isnan(restored[lone])
    assert np.array_equal(restored[~(band | block) & (np.arange(len(rows)) != lone)],
                          carved[~(band | block) & (np.arange(len(rows)) != lone)])
    # a few hot readings the skirts missed on the wall do not vouch for the block: the median does not move
    carved[(columns == 25) & (rows < 10)] = 1000.0
    assert np.isnan(restore_consistent(plain, carved, space)[block]).all()


@pytest.mark.integration
def test_a_flank_the_cloud_lacks_no_longer_lends_its_temperature_to_the_plate_behind(hot_scene):
    """The hot scene's bar with the half facing the thermal camera's side cut from the cloud (a flank the
    projector left dark): the plate points the thermal camera sees only through that flank read the bar's
    temperature without the witnesses, and none does with them; the seen points keep their readings."""
    bar = np.abs(hot_scene.points[:, 2] - 650.0) > 1.0
    keep = ~(bar & (hot_scene.points[:, 1] < -15.0))
    cloud = {"x": hot_scene.points[keep, 0], "y": hot_scene.points[keep, 1], "z": hot_scene.points[keep, 2],
             "nx": hot_scene.normals[keep, 0], "ny": hot_scene.normals[keep, 1], "nz": hot_scene.normals[keep, 2]}
    truth, visible = hot_scene.truth[keep], hot_scene.visible[keep]
    views = [ThermalView(hot_scene.thermal, hot_scene.image)]
    plain = np.asarray(temperature_field(cloud, views, hot_scene.camera.centre)["temperature"], dtype=float)
    carved = np.asarray(temperature_field(cloud, views, hot_scene.camera.centre,
                                          witnesses=[Witness(hot_scene.camera)])["temperature"], dtype=float)
    hidden = ~visible
    assert np.sum(np.abs(plain[hidden] - truth[hidden]) > 20.0) > 50
    assert np.sum(np.abs(carved[hidden] - truth[hidden]) > 20.0) <= 0.02 * np.sum(np.isfinite(plain[hidden]))
    seen_plain, seen_carved = np.isfinite(plain[visible]), np.isfinite(carved[visible])
    assert seen_carved.mean() >= seen_plain.mean() - 0.02
    assert np.nanmax(np.abs(carved[visible] - truth[visible])) <= np.nanmax(np.abs(plain[visible] - truth[visible]))


def test_the_camera_depth_map_is_the_nearest_point_per_pixel():
    camera = _camera()
    points = np.array([[0.0, 0.0, 500.0], [0.0, 0.0, 400.0], [1.0, 0.0, 900.0]])
    depth = depth_map(points, camera)
    assert np.isfinite(depth).sum() == 1 and depth.min() == 400.0  # the third point falls on the same pixel
    space = unseen_space(points, [Witness(camera)])
    assert space.surfaces.shape == (3,) and np.array_equal(space.pixels[:, 1:], [[50, 60]] * 3)

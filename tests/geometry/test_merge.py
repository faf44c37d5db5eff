"""Tests of services.geometry.merge on clouds of a known surface whose heads carry known pose errors."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.formats.stored_scan import overlap_sample_bytes, overlap_sample_from_bytes
from services.geometry.merge import (PoseCorrection, PoseUncertainty, overlap_residuals, overlap_sample,
                                     refine_head_poses, thin_overlaps)

RADIUS, HALF = 45.0, 150.0
SPACING = 1.5


def _cylinder_patch(angles: tuple[float, float], rng, noise: float = 0.005, ends: tuple[int, ...] = ()):
    """Points and outward normals of a capped cylinder (axis x, radius 45, 300 long): the side between two angles
    (degrees, round the axis) and the named end faces (+1, -1), about SPACING apart."""
    around = np.radians(np.arange(angles[0], angles[1], np.degrees(SPACING / RADIUS)))
    along = np.arange(-HALF, HALF, SPACING)
    a, x = np.meshgrid(around, along)
    normals = np.column_stack([np.zeros(a.size), np.cos(a.ravel()), np.sin(a.ravel())])
    points = np.column_stack([x.ravel(), RADIUS * normals[:, 1], RADIUS * normals[:, 2]])
    pieces_p, pieces_n = [points], [normals]
    for end in ends:
        grid = np.arange(-RADIUS, RADIUS, SPACING)
        y, z = np.meshgrid(grid, grid)
        inside = y**2 + z**2 < RADIUS**2
        face = np.column_stack([np.full(inside.sum(), end * HALF), y[inside], z[inside]])
        pieces_p.append(face)
        pieces_n.append(np.tile([float(end), 0.0, 0.0], (len(face), 1)))
    points, normals = np.concatenate(pieces_p), np.concatenate(pieces_n)
    return points + rng.normal(0, noise, points.shape) * normals, normals


def _station(rng, noise=0.005):
    """Four heads round the shaft, each seeing 150 degrees of the side; opposite heads share an end face."""
    return [_cylinder_patch((start, start + 150.0), rng, noise, ends=(1,) if k % 2 == 0 else (-1,))
            for k, start in enumerate((-165.0, -75.0, 15.0, 105.0))]


def _moved(cloud, rotvec_deg, translation, centre):
    rotation = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    points, normals = cloud
    return (points - centre) @ rotation.T + centre + translation, normals @ rotation.T


def _true_surface_distance(points):
    """Distance of points from the capped cylinder's surface (side or end face, the nearer)."""
    side = np.abs(np.hypot(points[:, 1], points[:, 2]) - RADIUS)
    end = np.abs(np.abs(points[:, 0]) - HALF)
    return np.where(np.abs(points[:, 0]) < HALF - 1.0, side, np.minimum(side, end))


def test_known_pose_errors_are_undone_within_the_prior():
    rng = np.random.default_rng(1)
    heads = _station(rng)
    errors = [((0, 0, 0), (0, 0, 0)), ((0.01, -0.008, 0.005), (0.06, -0.04, 0.05)),
              ((-0.006, 0.01, 0.0), (-0.05, 0.03, 0.06)), ((0.0, 0.007, -0.01), (0.04, 0.07, -0.03))]
    disturbed = [_moved(cloud, rotvec, translation, cloud[0].mean(axis=0))
                 for cloud, (rotvec, translation) in zip(heads, errors)]
    uncertainty = [PoseUncertainty(0.05, 0.01)] * 4
    before = overlap_residuals(*zip(*disturbed))
    corrections = refine_head_poses(*zip(*disturbed), uncertainty)
    assert all(c.applied for c in corrections)
    assert corrections[0].translation_mm == 0 and corrections[0].rotation_deg == 0
    merged = [c.apply(*cloud)[0] for c, cloud in zip(corrections, disturbed)]
    after = overlap_residuals(merged, [c.apply(*cloud)[1] for c, cloud in zip(corrections, disturbed)])
    worst_before = max(r.patch_rms_mm for r in before)
    worst_after = max(r.patch_rms_mm for r in after)
    assert worst_before > 0.04
    assert worst_after < 0.01
    # the sides are back on the true surface (the reference head was not disturbed)
    side = [np.abs(points[:, 0]) < HALF - 1.0 for points in merged]
    for points, on_side in zip(merged, side):
        assert np.sqrt(np.mean(_true_surface_distance(points[on_side]) ** 2)) < 0.012
    # along the axis only the end faces constrain the heads: head 2 shares the reference's face and is back on it;
    # heads 1 and 3 share the other face with each other, so they agree with each other, and their common shift
    # along the axis, which no overlap observes, stays where the calibration put it (within its prior)
    end_offset = [np.mean(np.abs(points[~on_side, 0]) - HALF) for points, on_side in zip(merged, side)]
    assert abs(end_offset[2] - end_offset[0]) < 0.012
    assert abs(end_offset[1] - end_offset[3]) < 0.012
    assert abs(end_offset[1]) < 3 * 0.05


def test_each_heads_overlap_sample_made_apart_and_stored_gives_the_merge_what_its_cloud_does():
    rng = np.random.default_rng(6)
    first, second = (_cylinder_patch(angles, rng, ends=(1,)) for angles in ((-90.0, 30.0), (-30.0, 90.0)))
    disturbed = [first, _moved(second, (0.01, 0.0, -0.008), (0.05, -0.04, 0.03), second[0].mean(axis=0))]
    samples = [overlap_sample_from_bytes(overlap_sample_bytes(overlap_sample(*cloud))) for cloud in disturbed]
    uncertainty = [PoseUncertainty(0.05, 0.01)] * 2
    direct = refine_head_poses(*zip(*disturbed), uncertainty)
    sampled = refine_head_poses([s.refine_points for s in samples], [s.refine_normals for s in samples], uncertainty,
                                sampled=True)
    assert direct[1].translation_mm > 0.02
    for a, b in zip(direct, sampled):
        np.testing.assert_allclose(b.translation, a.translation, atol=1e-12)
        np.testing.assert_allclose(b.rotation, a.rotation, atol=1e-12)
    moved = [c.apply(*cloud) for c, cloud in zip(direct, disturbed)]
    moved_samples = [s.moved(c) for s, c in zip(samples, direct)]
    for a, b in zip(overlap_residuals(*zip(*moved)), overlap_residuals(
            [s.residual_points for s in moved_samples], [s.residual_normals for s in moved_samples], sampled=True),
            strict=True):
        assert (b.first, b.second, b.points) == (a.first, a.second, a.points)
        assert (b.rms_mm, b.patch_rms_mm) == pytest.approx((a.rms_mm, a.patch_rms_mm), rel=1e-9)
    assert samples[0].spacing_mm == pytest.approx(SPACING, rel=0.1)


def test_a_correction_beyond_the_calibrations_uncertainty_is_refused_not_applied():
    rng = np.random.default_rng(2)
    heads = _station(rng)
    disturbed = list(heads)
    disturbed[2] = _moved(heads[2], (0.0, 0.0, 0.0), (0.0, 0.8, 0.0), heads[2][0].mean(axis=0))  # 0.8 mm off
    corrections = refine_head_poses(*zip(*disturbed), [PoseUncertainty(0.05, 0.01)] * 4)
    refused = corrections[2]
    assert not refused.applied
    assert "beyond 3 sigma of the calibration" in refused.reason
    points, _ = refused.apply(*disturbed[2])
    np.testing.assert_array_equal(points, disturbed[2][0])


def test_a_head_without_overlap_is_kept_and_says_so():
    rng = np.random.default_rng(3)
    a = _cylinder_patch((0.0, 60.0), rng)
    b = _cylinder_patch((180.0, 240.0), rng)
    corrections = refine_head_poses([a[0], b[0]], [a[1], b[1]], [PoseUncertainty(0.05, 0.01)] * 2)
    assert not corrections[1].applied
    assert "too little overlap" in corrections[1].reason
    assert overlap_residuals([a[0], b[0]], [a[1], b[1]]) == []


def test_the_overlap_residual_measures_a_known_offset_along_the_normal():
    rng = np.random.default_rng(4)
    first = _cylinder_patch((0.0, 90.0), rng, noise=0.02)
    second = _cylinder_patch((45.0, 135.0), rng, noise=0.02)
    # push the second head's surface 0.05 mm outward (along its own normals): a known misregistration
    shifted = (second[0] + 0.05 * second[1], second[1])
    (residual,) = overlap_residuals([first[0], shifted[0]], [first[1], shifted[1]])
    assert residual.first == 0 and residual.second == 1
    assert residual.patch_rms_mm == pytest.approx(0.05, abs=0.006)
    assert residual.rms_mm > residual.patch_rms_mm  # the point noise is in it
    (aligned,) = overlap_residuals([first[0], second[0]], [first[1], second[1]])
    # aligned, what is left is the noise floor: 0.02 mm noise over the ~7 points of a head in a 4 mm patch
    assert aligned.patch_rms_mm < 0.015
    assert aligned.patch_rms_mm < 0.3 * residual.patch_rms_mm


def test_thinning_keeps_one_head_per_voxel_the_one_seeing_it_most_squarely():
    rng = np.random.default_rng(5)
    points = rng.uniform(0, 10, (30000, 3))  # 30 points a voxel: every voxel holds every head's
    head = rng.integers(0, 3, len(points))
    angle = np.array([50.0, 20.0, 70.0])[head]
    angle[(head == 0) & (points[:, 0] < 2)] = 5.0  # head 0 sees this slab best
    keep = thin_overlaps(points, head, angle, voxel_mm=1.0)
    voxels = np.floor(points / 1.0).astype(int)
    kept_heads: dict[tuple, set] = {}
    for v, h in zip(map(tuple, voxels[keep]), head[keep]):
        kept_heads.setdefault(v, set()).add(int(h))
    assert all(len(h) == 1 for h in kept_heads.values())
    assert set(head[keep & (points[:, 0] < 2)]) == {0}
    assert set(head[keep & (points[:, 0] >= 2)]) == {1}
    # every voxel that had a point keeps one
    assert len(kept_heads) == len(np.unique(voxels, axis=0))


def test_bad_input_is_refused_with_a_sentence():
    with pytest.raises(ValueError, match="one entry per head"):
        refine_head_poses([np.zeros((3, 3))], [np.zeros((3, 3)), np.zeros((3, 3))], [PoseUncertainty(1, 1)])
    with pytest.raises(ValueError, match="positive"):
        PoseUncertainty(0.0, 0.01)
    with pytest.raises(ValueError, match="voxel"):
        thin_overlaps(np.zeros((2, 3)), np.zeros(2, int), np.zeros(2), 0.0)


def test_an_unapplied_correction_leaves_points_and_normals_alone():
    correction = PoseCorrection(Rotation.from_rotvec([0, 0, 0.1]).as_matrix(), np.ones(3), np.zeros(3), False, 0)
    points, normals = np.ones((2, 3)), np.eye(3)[:2]
    assert correction.apply(points, normals)[0] is points
    assert correction.rotation_deg == pytest.approx(np.degrees(0.1))

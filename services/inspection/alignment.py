"""Alignment of the nominal part to measured points: principal-axis starts, then robust point-to-plane ICP whose
correspondences must face the camera that measured each point."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations, product

import numpy as np

from services.geometry.rigid import rigid_transform
from services.inspection.nominal import NominalSurface
from services.inspection.point_rows import finite_rows
from services.inspection.robust import even_subset

_COARSE_POINTS = 300
_CANDIDATE_POINTS = 1000
_FINE_POINTS = 10000
_COARSE_KEEP = 3
_PRUNED_STARTS = 6
_RANK_TOLERANCE = 1e-9
_FACING_CANDIDATES = 8
"""Nearest samples searched for one that faces a point's camera (beside an edge the nearest may lie on the
other face, about 90 degrees off)."""


@dataclass(frozen=True)
class Alignment:
    """Where the nominal part lies among the measured points.

    Attributes
    ----------
    matrix : (4, 4) array
        Homogeneous transform from the part frame to the world (measured) frame.
    rms_mm : float
        Root mean square distance from the nominal surface of the measured points within
        ``max_distance_mm`` of it (at most 10 000 of them, evenly drawn).
    inlier_fraction : float
        Fraction of those points within ``max_distance_mm`` of the nominal surface.
    """

    matrix: np.ndarray
    rms_mm: float
    inlier_fraction: float

    def to_part(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the part frame."""
        rotation, translation = self.matrix[:3, :3], self.matrix[:3, 3]
        return rigid_transform(points, rotation.T, -rotation.T @ translation)

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Part-frame points (N, 3) in the world frame."""
        return rigid_transform(points, self.matrix[:3, :3], self.matrix[:3, 3])


def _principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - centre).T))
    return centre, vectors[:, ::-1]


def _axis_of_revolution(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The line (a unit direction and its point nearest the points' centroid) that the normal lines of
    ``points`` (N, 3) with unit ``normals`` (N, 3) meet best in the least-squares sense: the axis of a surface of
    revolution (a cylinder's, cone's, torus's; a plane across it or a sphere centred on it does not move it).
    None with fewer than 6 finite normals.

    Notes
    -----
    A normal line through p along n meets the axis of direction a and moment a' (Pluecker coordinates)
    when their reciprocal product vanishes, (p x n) . a + n . a' = 0 [1]_. With M the sum of l l^T over
    l = (p x n, n), the minimum of c^T M c over c = (a, a') with |a| = 1 is the smallest eigenvector of
    the reduced 3 x 3 matrix A - B C^+ B^T (M = [[A, B], [B^T, C]]), and a' = -C^+ B^T a. Points are
    centred on their centroid first; the axis's point nearest it is a x a'.

    References
    ----------
    .. [1] H. Pottmann and T. Randrup, "Rotational and helical surface approximation for reverse
       engineering", Computing 60(4), 1998.
    """
    finite = np.isfinite(normals).all(axis=1)
    if np.count_nonzero(finite) < 6:
        return None
    centre = points[finite].mean(axis=0)
    p, n = points[finite] - centre, normals[finite]
    lines = np.concatenate([np.cross(p, n), n], axis=1)
    m = lines.T @ lines
    a_block, b_block, c_inverse = m[:3, :3], m[:3, 3:], np.linalg.pinv(m[3:, 3:])
    _, vectors = np.linalg.eigh(a_block - b_block @ c_inverse @ b_block.T)
    direction = vectors[:, 0]
    moment = -c_inverse @ b_block.T @ direction
    return direction, centre + np.cross(direction, moment)


def _turning(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``source`` to unit vector ``target``."""
    axis = np.cross(source, target)
    sine, cosine = np.linalg.norm(axis), float(source @ target)
    if sine < 1e-12:
        if cosine > 0:
            return np.eye(3)
        other = np.eye(3)[np.argmin(np.abs(source))]
        axis = np.cross(source, other)
        return _rotations((np.pi * axis / np.linalg.norm(axis))[None])[0]
    return _rotations((np.arctan2(sine, cosine) * axis / sine)[None])[0]


def _start_rotations() -> list[np.ndarray]:
    """The 24 proper rotations mapping coordinate axes to signed coordinate axes."""
    rotations = []
    for order in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), order] = signs
            if np.linalg.det(matrix) > 0:
                rotations.append(matrix)
    return rotations


def _rotations(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (S, 3, 3) of rotation vectors (S, 3) (Rodrigues)."""
    angle = np.linalg.norm(omega, axis=1)
    k = omega / np.where(angle < 1e-15, 1.0, angle)[:, None]
    cross = np.zeros((len(omega), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    cross -= cross.transpose(0, 2, 1)
    return (np.eye(3) + np.sin(angle)[:, None, None] * cross
            + (1 - np.cos(angle))[:, None, None] * cross @ cross)


def _least_squares_steps(system: np.ndarray, right: np.ndarray, size: float) -> np.ndarray:
    """Minimum-norm solutions (S, 6) of S normal systems (S, 6, 6) in (rotation vector, translation), with the
    rotations scaled by the part's ``size`` (mm) so that both halves are lengths: singular values below
    ``_RANK_TOLERANCE`` of the largest count as zero. A symmetry (a cylinder's spin about its axis) or a
    direction that no seen face pins then stays where it is, instead of taking a step from the rounding of the
    distance grid's gradients (unscaled, a spin's singular value of about 1e-14 of the largest passed machine
    precision and the polish walked a part off its true pose)."""
    scale = np.array([1 / size] * 3 + [1.0] * 3)
    u, singular, vt = np.linalg.svd(system * scale[:, None] * scale[None, :])
    kept = singular > _RANK_TOLERANCE * singular[:, :1]
    inverse = np.divide(1.0, singular, out=np.zeros_like(singular), where=kept)
    return scale * np.einsum("sji,sj->si", vt, inverse * np.einsum("sji,sj->si", u, right * scale))


def _moved(points: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Points (N, 3) under each of S transforms (S, 4, 4): (S, N, 3)."""
    return points @ transforms[:, :3, :3].transpose(0, 2, 1) + transforms[:, None, :3, 3]


def _facing(seen: np.ndarray | None, transforms: np.ndarray, normal: np.ndarray) -> np.ndarray | bool:
    """Whether each point's nominal outward normal (S, N, 3, or S, N, K, 3 for K candidates; part frame) makes
    less than 90 degrees with its measured normal ``seen`` (N, 3, world, toward the camera that measured it;
    NaN: unknown, which passes) under each transform (S, 4, 4): a nominal surface facing away from the
    camera cannot be what it saw."""
    if seen is None:
        return True
    turned = np.einsum("sij,nj->sni", transforms[:, :3, :3], seen)
    if normal.ndim == 4:
        return ~(np.einsum("sni,snki->snk", turned, normal) <= 0.0)
    return ~(np.einsum("sni,sni->sn", turned, normal) <= 0.0)


def _nearest_facing(tree, sample_normals: np.ndarray, moved: np.ndarray, cut_off: float, seen: np.ndarray | None,
                    transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point of ``moved`` (S, N, 3): the distance to and index of its nearest sample within ``cut_off``
    (of the ``_FACING_CANDIDATES`` nearest, the nearest facing its measured normal ``seen`` when given), and
    whether it has one."""
    # bounded: a far query visits much of the tree, and beyond the cut-off its weight is 0 anyway
    k = 1 if seen is None else _FACING_CANDIDATES
    distance, index = tree.query(moved.reshape(-1, 3), k=k, distance_upper_bound=cut_off)
    shape = moved.shape[:2]
    if seen is None:
        near = np.isfinite(distance).reshape(shape)
        return distance.reshape(shape), np.where(near, index.reshape(shape), 0), near
    distance, index = distance.reshape(*shape, k), index.reshape(*shape, k)
    index = np.where(np.isfinite(distance), index, 0)
    valid = np.isfinite(distance) & _facing(seen, transforms, sample_normals[index])
    first = np.argmax(valid, axis=2)[..., None]
    near = valid.any(axis=2)
    return (np.take_along_axis(distance, first, axis=2)[..., 0], np.take_along_axis(index, first, axis=2)[..., 0],
            near)


def _correspondences(moved: np.ndarray, nominal: NominalSurface, matching: str, cut_off: float,
                     seen: np.ndarray | None = None,
                     transforms: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-plane residuals (S, N), plane normals (S, N, 3) and which points are within ``cut_off`` on a
    nominal surface facing their measured normals ``seen`` (N, 3, world; None: any)."""
    if matching == "surface":
        residual, normal = nominal.signed_distance_gradient(moved.reshape(-1, 3))
        residual, normal = residual.reshape(moved.shape[:2]), normal.reshape(moved.shape)
        return residual, normal, (np.abs(residual) < cut_off) & _facing(seen, transforms, normal)
    if matching == "sparse":
        tree, samples, sample_normals = nominal.coarse_tree, nominal.coarse_samples, nominal.coarse_normals
    else:
        tree, samples, sample_normals = nominal.sample_tree, nominal.samples, nominal.sample_normals
    _, index, near = _nearest_facing(tree, sample_normals, moved, cut_off, seen, transforms)
    normal = sample_normals[index]
    return np.einsum("sni,sni->sn", moved - samples[index], normal), normal, near


def _icp(points: np.ndarray, nominal: NominalSurface, transforms: np.ndarray, distances: np.ndarray,
         matching: str = "samples", seen: np.ndarray | None = None) -> np.ndarray:
    """Point-to-plane ICP with Tukey weights from S starts at once, one iteration per entry of ``distances``
    (the Tukey cut-off, mm).

    ``transforms`` (S, 4, 4) map measured points to the part frame. ``matching``: each point's plane
    is that of its nearest nominal sample (``"samples"``) or sparse sample (``"sparse"``), or that of
    its closest point on the mesh itself (``"surface"``: the signed distance and its gradient, read
    from the distance grid near the surface, for points already close to it); with measured normals
    ``seen`` (N, 3, world), a point whose nominal plane faces away from its normal gets no weight. Every start's points
    are matched in one query per iteration, each start solves its own 6 x 6 normal equations; a start
    with a total weight below 6 stops there. Hand-written on the nominal's prepared cKDTrees: Open3D's
    ``registration_icp`` searches its own tree by radius on every call, which made the 24 starts
    take seconds.
    """
    transforms = np.array(transforms, dtype=np.float64)
    size = float(np.linalg.norm(np.ptp(nominal.coarse_samples, axis=0)))
    active = np.ones(len(transforms), dtype=bool)
    for cut_off in distances:
        moved = _moved(points, transforms[active])
        residual, normal, near = _correspondences(moved, nominal, matching, cut_off, seen, transforms[active])
        u = residual / cut_off
        weight = np.where(near & (np.abs(u) < 1), (1 - u * u) ** 2, 0.0)
        enough = weight.sum(axis=1) >= 6
        active[np.flatnonzero(active)[~enough]] = False
        if not active.any():
            break
        moved, normal, weight, residual = moved[enough], normal[enough], weight[enough], residual[enough]
        design = np.concatenate([np.cross(moved, normal), normal], axis=2)
        weighted = design * weight[..., None]
        step = _least_squares_steps(weighted.transpose(0, 2, 1) @ design,
                                    -np.einsum("sni,sn->si", weighted, residual), size)
        increment = _rotations(step[:, :3])
        transforms[active, :3, :3] = increment @ transforms[active, :3, :3]
        transforms[active, :3, 3] = np.einsum("sij,sj->si", increment, transforms[active, :3, 3]) + step[:, 3:]
    return transforms


def _near_order(points: np.ndarray, nominal: NominalSurface, transforms: np.ndarray, cut_off: float,
                seen: np.ndarray | None = None) -> np.ndarray:
    """Indices of the transforms (S, 4, 4), best first: most points within ``cut_off`` of a sparse nominal
    sample facing their measured normal ``seen`` (to the hundredth), then the lowest median distance of those."""
    distance, _, near = _nearest_facing(nominal.coarse_tree, nominal.coarse_normals, _moved(points, transforms),
                                        cut_off, seen, transforms)
    fraction = np.round(near.mean(axis=1), 2)
    with np.errstate(all="ignore"):
        median = np.where(near.any(axis=1), np.nanmedian(np.where(near, distance, np.nan), axis=1), np.inf)
    return np.lexsort((np.arange(len(transforms)), median, -fraction))


def _score(points: np.ndarray, nominal: NominalSurface, transforms: np.ndarray, max_distance: float,
           seen: np.ndarray | None = None):
    """Per transform (S, 4, 4): the fraction of points within ``max_distance`` of the nominal surface (and,
    given their measured normals ``seen``, on a part of it that faces them) and their RMS distance (inf
    without any)."""
    moved = _moved(points, transforms)
    if seen is None:
        distance = np.abs(nominal.signed_distance(moved.reshape(-1, 3))).reshape(moved.shape[:2])
        inliers = distance <= max_distance
    else:
        distance, gradient = nominal.signed_distance_gradient(moved.reshape(-1, 3))
        distance, gradient = np.abs(distance).reshape(moved.shape[:2]), gradient.reshape(moved.shape)
        inliers = (distance <= max_distance) & _facing(seen, transforms, gradient)
    count = inliers.sum(axis=1)
    with np.errstate(all="ignore"):
        rms = np.where(count > 0, np.sqrt(np.where(inliers, distance**2, 0.0).sum(axis=1) / count), np.inf)
    return inliers.mean(axis=1), rms


def align_nominal(points: np.ndarray, nominal: NominalSurface, max_distance_mm: float = 2.0,
                  start: np.ndarray | None = None, polish: bool = True,
                  normals: np.ndarray | None = None) -> Alignment:
    """Find the rigid transform that puts the nominal part onto measured (cold-equivalent) points.

    Parameters
    ----------
    points : (N, 3) array
        Measured points of the part (a one-sided view is fine), world mm.
    nominal : NominalSurface
        The nominal part.
    max_distance_mm : float
        Correspondence distance of the last ICP stage and the inlier threshold.
    start : (4, 4) array, optional
        A part-to-world transform within ``max_distance_mm`` of the answer (an earlier alignment of
        nearly the same points), which only the polish refines; without it the principal frames'
        axis-to-axis matches are tried.
    polish : bool
        Without a start: refine the winner on 10 000 points; without, the alignment ends on 1000
        points (a first alignment that a later call refines from its result).
    normals : (N, 3) array, optional
        The measured points' unit normals, turned toward the camera that measured each (the cloud's
        ``nx, ny, nz``; NaN where unknown). A point is then matched only to nominal surface whose outward
        normal makes less than 90 degrees with its own.

    Returns
    -------
    Alignment
        The part-to-world transform with its residual.

    Notes
    -----
    Correspondences run from each measured point to its nearest nominal surface sample, never the
    other way, so the part's unseen side does not pull on the fit: the view may be one-sided.
    Each start R0 = E_n P E_m^T, t0 = c_n - R0 c_m (principal axes E and centroids c of the nominal
    samples and the measured points, P one of the 24 signed permutations with det +1; each also with t0
    shifted along each nominal axis so that the measured points' lower or upper end (0.5 and 99.5
    percentiles) meets the nominal's: a one-sided view's centroid lies off the part's toward the viewer,
    by a quarter of a cylinder's diameter across it, and along a cylinder ICP cannot tell a shift from a
    fit until a face pins it; 168 starts; given ``normals``, 6 more: the axis of revolution that the view's
    normal lines meet best (``_axis_of_revolution`` [3]_) put on the nominal's, either way round, with the view's
    centre, lower or upper end on the part's along it: the principal axes of a view of a part about as long as
    it is wide lie at any angle to the part's, so none of the 24 is near the truth) is refined by
    point-to-plane ICP [1]_ with Tukey weights [2]_ on
    300 points against 3000 nominal samples, the weights' cut-off shrinking from a quarter to a thirtieth
    of the part's size over 10 iterations (after 3, only the 6 starts with most points near the nominal go on); the three starts with most
    points near the nominal are refined on 1000 points down to ``max_distance_mm``; the one with most
    points within that distance of the nominal surface (then the lowest residual) wins and is
    polished by 5 iterations at ``max_distance_mm`` on 10 000 points, as a given start is, with each
    point's plane that of its closest point on the mesh (``NominalSurface.signed_distance_gradient``).
    Each step solves the 6 x 6 normal equations with the rotation scaled by the part's size, so that
    both halves are lengths, dropping singular values below 1e-9 of the largest: symmetries of the part
    (a cylinder's rotation about its axis) and directions no seen face pins leave the transform where it
    was along them, which no measure depends on.

    Given ``normals`` (which face the camera that measured each point), a point counts, in every ICP step
    and every ranking of the starts, only where the nominal's outward normal at its match makes less than
    90 degrees with its own normal: a camera cannot see a face turned away from it, nor a point inside the
    solid (the normal-compatibility test of ICP's correspondence rejection [4]_, at the physical bound).
    Matched to samples, a point takes the nearest of its 8 nearest samples that faces it: beside an edge
    the nearest may lie on the other face, about 90 degrees off (rejecting those lost the true pose of a
    stepped shaft 2 % of its coarse matches, and the start was pruned). It rules out the poses that fit a
    one-sided view as well as the truth does, whose matched normals are opposite: a tube's seen outer wall on
    its inner wall (moved by the wall's thickness), a box's seen faces on the faces opposite them. The reported ``rms_mm`` and ``inlier_fraction`` count every point, as without normals.

    References
    ----------
    .. [1] Y. Chen and G. Medioni, "Object modelling by registration of multiple range images",
       Image and Vision Computing 10(3), 1992.
    .. [2] P. Babin, P. Giguere and F. Pomerleau, "Analysis of robust functions for registration
       algorithms", ICRA 2019.
    .. [3] H. Pottmann and T. Randrup, "Rotational and helical surface approximation for reverse
       engineering", Computing 60(4), 1998.
    .. [4] S. Rusinkiewicz and M. Levoy, "Efficient variants of the ICP algorithm", 3DIM 2001.
    """
    points = np.asarray(points, dtype=np.float64)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(f"The normals' shape {normals.shape} is not the points' {points.shape}: give one "
                             "normal per point.")
        normals = normals[finite_rows(points)]
    points = points[finite_rows(points)]
    if len(points) < 10:
        raise ValueError(f"Only {len(points)} measured points of the part; at least 10 are needed to align it.")
    size = float(np.linalg.norm(np.ptp(nominal.samples, axis=0)))

    def subset(wanted: int) -> tuple[np.ndarray, np.ndarray | None]:
        return even_subset(points, wanted), None if normals is None else even_subset(normals, wanted)

    fine, fine_normals = subset(_FINE_POINTS)
    if start is not None:
        transform = np.linalg.inv(start)[None]
    else:
        coarse, coarse_normals = subset(_COARSE_POINTS)
        measured_centre, measured_axes = _principal_frame(fine)
        nominal_centre, nominal_axes = _principal_frame(nominal.samples)
        starts = []
        nominal_extents = np.percentile(nominal.samples @ nominal_axes, [0.5, 99.5], axis=0).T
        for permutation in _start_rotations():
            rotation = nominal_axes @ permutation @ measured_axes.T
            translation = nominal_centre - rotation @ measured_centre
            shifts = [np.zeros(3)]
            # a one-sided view's centroid lies off the part's toward the viewer: along the view, only the near
            # end of the part is seen; so also try the view's lower or upper end on the part's along each axis
            moved = fine @ rotation.T + translation
            for axis, extent in zip(nominal_axes.T, nominal_extents):
                for shift in extent - np.percentile(moved @ axis, [0.5, 99.5]):
                    shifts.append(shift * axis)
            for shift in shifts:
                guess = np.eye(4)
                guess[:3, :3], guess[:3, 3] = rotation, translation + shift
                starts.append(guess)
        # a view of a part about as long as it is wide has principal axes at any angle to the part's: its
        # normals find the axis of revolution, put on the nominal's either way round
        seen_axis = None if fine_normals is None else _axis_of_revolution(*subset(_CANDIDATE_POINTS))
        if seen_axis is not None:
            nominal_axis = _axis_of_revolution(nominal.coarse_samples, nominal.coarse_normals)
            extent = np.percentile(nominal.samples @ nominal_axis[0], [0.5, 99.5])
            for sign in (1.0, -1.0):
                rotation = _turning(seen_axis[0], sign * nominal_axis[0])
                translation = nominal_axis[1] - rotation @ seen_axis[1]
                moved = fine @ rotation.T + translation
                for shift in (0.0, *(extent - np.percentile(moved @ nominal_axis[0], [0.5, 99.5]))):
                    guess = np.eye(4)
                    guess[:3, :3], guess[:3, 3] = rotation, translation + shift * nominal_axis[0]
                    starts.append(guess)
        starts = np.array(starts)
        schedule = np.geomspace(size / 4, size / 30, 10)
        for distances, keep in ((schedule[:3], _PRUNED_STARTS), (schedule[3:], _COARSE_KEEP)):
            refined = _icp(coarse, nominal, starts, distances, matching="sparse", seen=coarse_normals)
            starts = refined[_near_order(coarse, nominal, refined, distances[-1], coarse_normals)[:keep]]
        middle, middle_normals = subset(_CANDIDATE_POINTS)
        refined = _icp(middle, nominal, starts, np.geomspace(8 * max_distance_mm, max_distance_mm, 10),
                       seen=middle_normals)
        fraction, rms = _score(middle, nominal, refined, max_distance_mm, middle_normals)
        best = np.lexsort((np.arange(len(refined)), rms, -np.round(fraction, 3)))[0]
        if not polish:
            fraction, rms = _score(middle, nominal, refined[best:best + 1], max_distance_mm)
            return Alignment(matrix=np.linalg.inv(refined[best]), rms_mm=float(rms[0]),
                             inlier_fraction=float(fraction[0]))
        transform = refined[best:best + 1]
    transform = _icp(fine, nominal, transform, np.full(5, max_distance_mm), matching="surface", seen=fine_normals)
    fraction, rms = _score(fine, nominal, transform, max_distance_mm)
    return Alignment(matrix=np.linalg.inv(transform[0]), rms_mm=float(rms[0]), inlier_fraction=float(fraction[0]))

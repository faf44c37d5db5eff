"""Merging the clouds of a station's heads in one world frame: pose refinement on the overlaps, the overlap
residual, and thinning the overlaps so that they are not doubled.

Every head's cloud is already in the world frame (the rig's calibration). Calibration leaves each head's
pose uncertain by a little; :func:`refine_head_poses` moves each head's cloud by the rigid motion that
best lays it on the others' where they overlap (point-to-plane ICP), within that uncertainty;
:func:`overlap_residuals` measures how far apart the heads' surfaces still are there; and
:func:`thin_overlaps` keeps, where several heads measured the same patch of surface, the points of the
head that saw it most squarely.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from services.open3d_loader import open3d

DEFAULT_MAX_DISTANCE_MM = 2.0
"""Correspondences farther apart than this are no overlap."""
DEFAULT_NOISE_MM = 0.03
"""The point noise along the normal that weighs the data against the prior of the pose (point-to-plane)."""
DEFAULT_BOUND_SIGMAS = 3.0
"""A correction beyond this many standard deviations of the calibration's pose uncertainty is refused."""
PATCH_MM = 4.0
"""The side of the surface patches over which the overlap residual averages the point noise away."""
_NEIGHBOURS = 8
_MIN_OVERLAP = 50
_NORMAL_NEIGHBOURS = 30
"""The neighbours of the PCA normals the merge uses (see :func:`surface_normals`)."""
_MAX_NORMAL_ANGLE_DEG = 10.0
_REFINE_POINTS = 20_000
"""The refinement uses about this many of each head's points (every k-th): a pose has six parameters."""
RESIDUAL_POINTS = 40_000
"""The overlap residual uses about this many of each head's points (every k-th): a 4 mm patch of a full-resolution
head (about 0.4 mm spacing, 110,000 points) keeps about 35 of its 100, enough for its mean to average the noise."""
_CANDIDATE_MARGIN_MM = 0.5
"""The refinement looks for a head's correspondences among its points within the largest distance plus this of
another head's, found again whenever two heads have moved by this much together (a correction is a few
hundredths of a millimetre)."""
_CONVERGED = 1e-3
"""The Gauss-Newton iterations stop when no step is above this share of the calibration's uncertainty (0.05 um
and 1e-5 degrees for the default one)."""
_DEGENERATE = 1e-3
"""Directions whose information from the overlaps is below this share of the best-constrained one's (in units
of the calibration's uncertainty) are left alone by the refinement."""
"""A correspondence whose two normals differ by more is no overlap: at a rim, the nearest point of another head
may lie on the other face (an end face's point for a point of the side), whose plane would pull the head along."""


@dataclass(frozen=True)
class PoseUncertainty:
    """One standard deviation of a head's pose from the calibration: translation (mm) and rotation (degrees),
    each the norm of the vector (isotropic)."""

    translation_mm: float
    rotation_deg: float

    def __post_init__(self) -> None:
        if not (self.translation_mm > 0 and self.rotation_deg > 0):
            raise ValueError(f"A pose uncertainty is positive; got {self.translation_mm} mm, {self.rotation_deg} deg.")


@dataclass(frozen=True)
class PoseCorrection:
    """The rigid motion found for one head's cloud, x -> R (x - centre) + centre + t (world frame, mm).

    ``applied`` is False when it was refused (beyond the bound, or too little overlap): the cloud then
    stays where the calibration put it. ``overlap`` counts the correspondences of the last iteration.
    """

    rotation: np.ndarray
    translation: np.ndarray
    centre: np.ndarray
    applied: bool
    overlap: int
    reason: str = ""

    @property
    def translation_mm(self) -> float:
        return float(np.linalg.norm(self.translation))

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(Rotation.from_matrix(self.rotation).as_rotvec())))

    def apply(self, points: np.ndarray, normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """The points (and normals) moved by the correction when it is applied, else unchanged."""
        if not self.applied:
            return points, normals
        moved = _rotate(points - self.centre, self.rotation) + (self.centre + self.translation)
        return moved, None if normals is None else _rotate(normals, self.rotation)


@dataclass(frozen=True)
class PairResidual:
    """How far head ``first``'s surface lies from head ``second``'s where they overlap (mm, along the normal).

    ``rms_mm`` over every overlapping point (point noise included); ``patch_rms_mm`` of the mean distance
    in each patch of :data:`PATCH_MM` (the noise averaged away: the misregistration of the two
    surfaces); ``points`` the overlapping points.
    """

    first: int
    second: int
    points: int
    rms_mm: float
    patch_rms_mm: float


def surface_normals(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Normals of a head's cloud by PCA over its 30 nearest points (Open3D), turned as the given ones.

    A reconstruction's normals (central differences of neighbouring pixels) scatter by a few degrees
    with the points' noise. Along a direction the overlaps hardly constrain (a cylinder's axis), that
    scatter is information the surface does not hold: the ICP cost would then follow the noise along
    it by tenths of a millimetre. The normals of a patch of 30 points scatter about ten times less.
    """
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(_NORMAL_NEIGHBOURS))
    smooth = np.asarray(cloud.normals)
    flip = np.einsum("ij,ij->i", smooth, normals) < 0
    smooth[flip] *= -1
    return smooth


def _clean(points: Sequence[np.ndarray], normals: Sequence[np.ndarray], most: int | None = None,
           sampled: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each head's finite points (about ``most`` of them, every k-th, when given) and their
    :func:`surface_normals`; ``sampled``: the points and normals are those already (an :class:`OverlapSample`'s)."""
    clean = []
    for p, n in zip(points, normals):
        p, n = np.asarray(p, dtype=np.float64), np.asarray(n, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
            raise ValueError(f"Each head's points and normals must both be (N, 3); got {p.shape} and {n.shape}.")
        good = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
        p, n = p[good], n[good]
        if sampled:
            clean.append((p, n))
            continue
        if most is not None:
            p, n = p[::max(1, len(p) // most)], n[::max(1, len(p) // most)]
        clean.append((p, surface_normals(p, n) if len(p) >= _NORMAL_NEIGHBOURS else n))
    return clean


@dataclass(frozen=True)
class OverlapSample:
    """What the merge needs of one head's cloud, made from it alone (in the service, in the head's own message, so
    that the heads' samples are made in parallel): about ``_REFINE_POINTS`` of its finite points (every k-th) for
    the pose refinement and about :data:`RESIDUAL_POINTS` for the overlap residual, each with its
    :func:`surface_normals` (world mm), and the points' spacing (the median distance from a point to its
    nearest, mm)."""

    refine_points: np.ndarray
    refine_normals: np.ndarray
    residual_points: np.ndarray
    residual_normals: np.ndarray
    spacing_mm: float

    def moved(self, correction: PoseCorrection) -> OverlapSample:
        """The sample moved by the head's pose correction (the PCA normals of moved points are the normals moved)."""
        refine, refine_normals = correction.apply(self.refine_points, self.refine_normals)
        residual, residual_normals = correction.apply(self.residual_points, self.residual_normals)
        return OverlapSample(refine, refine_normals, residual, residual_normals, self.spacing_mm)


def overlap_sample(points: np.ndarray, normals: np.ndarray) -> OverlapSample:
    """One head's :class:`OverlapSample` from its points (N, 3; world mm) and normals (N, 3; non-finite rows
    ignored), exactly as :func:`refine_head_poses` and :func:`overlap_residuals` sample and smooth them."""
    (refine, refine_normals), = _clean([points], [normals], _REFINE_POINTS)
    (residual, residual_normals), = _clean([points], [normals], RESIDUAL_POINTS)
    return OverlapSample(refine, refine_normals, residual, residual_normals, point_spacing(points))


def point_spacing(points: np.ndarray) -> float:
    """The median distance from a point to its nearest neighbour (mm; on up to 5000 of the finite points, every
    k-th, against all of them; 1.0 for fewer than two)."""
    points = np.asarray(points, dtype=np.float64)
    finite = points[np.isfinite(points).all(axis=1)]
    if len(finite) < 2:
        return 1.0
    sample = finite[:: max(1, len(finite) // 5000)]
    distance, _ = cKDTree(finite).query(sample, k=2, workers=-1)
    return float(np.median(distance[:, 1]))


def _identity(centre: np.ndarray, applied: bool, overlap: int, reason: str = "") -> PoseCorrection:
    return PoseCorrection(np.eye(3), np.zeros(3), centre, applied, overlap, reason)


def _local_planes(tree: cKDTree, points: np.ndarray, normals: np.ndarray, queries: np.ndarray,
                  query_normals: np.ndarray, max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query, the tangent plane of the target at its nearest target point (that point, and the mean
    normal of the 8 nearest) and whether the nearest lies within ``max_distance``. The plane goes through the
    nearest point, not the neighbours' mean: on a curved surface the mean lies inside it by about the
    neighbours' spread squared over twice the radius (0.01 to 0.02 mm on the shaft at 1.5 mm spacing), a bias
    the residual would report as misregistration."""
    distance, index = tree.query(queries, k=_NEIGHBOURS, distance_upper_bound=max_distance, workers=-1)
    found = np.isfinite(distance)
    close = found[:, 0]
    index = np.where(found, index, 0)
    weight = found[..., None].astype(np.float64)
    centre = points[index[:, 0]]
    normal = (normals[index] * weight).sum(axis=1)
    length = np.linalg.norm(normal, axis=1)
    good = close & (length > 0.5 * found.sum(axis=1))  # the neighbours' normals roughly agree
    normal /= np.maximum(length, 1e-12)[:, None]
    good &= np.einsum("ij,ij->i", query_normals, normal) >= np.cos(np.radians(_MAX_NORMAL_ANGLE_DEG))
    return centre, normal, good


def _signed_distances(points: np.ndarray, centres: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", points - centres, normals)


def refine_head_poses(points: Sequence[np.ndarray], normals: Sequence[np.ndarray],
                      uncertainty: Sequence[PoseUncertainty], *, reference: int = 0,
                      max_distance_mm: float = DEFAULT_MAX_DISTANCE_MM, noise_mm: float = DEFAULT_NOISE_MM,
                      bound_sigmas: float = DEFAULT_BOUND_SIGMAS, iterations: int = 12,
                      sampled: bool = False) -> list[PoseCorrection]:
    """Rigid corrections laying the heads' clouds on each other where they overlap, within the calibration.

    Parameters
    ----------
    points, normals : sequences of (N_k, 3) arrays
        Each head's points (world mm) and unit normals; non-finite rows are ignored.
    uncertainty : sequence of PoseUncertainty
        Each head's pose uncertainty from the calibration (one standard deviation).
    reference : int
        The head that stays where it is (it fixes the world frame the others are laid on).
    max_distance_mm : float
        Correspondences farther apart are no overlap.
    noise_mm : float
        The points' noise along the normal.
    bound_sigmas : float
        A correction beyond this many standard deviations of the head's uncertainty, in translation or
        rotation, is refused (reported, not applied): the data contradict the calibration.
    iterations : int
        The most Gauss-Newton iterations (each finds the correspondences again); they stop once no step
        is above a thousandth of the head's uncertainty.
    sampled : bool
        The points and normals are each head's :class:`OverlapSample` ``refine_points`` and
        ``refine_normals`` (sampled and smoothed already), used as they are.

    Returns
    -------
    list of PoseCorrection
        One per head (the reference's is the identity).

    Notes
    -----
    All heads' corrections (rotation vector w_k, translation t_k, about the centroid c_k of head k's
    points; x -> R(w_k) (x - c_k) + c_k + t_k) jointly minimise the point-to-plane ICP cost [1]_ over
    every overlap plus a Gaussian prior from the calibration,

        sum_(k, j) sum_i (n_i . (T_k p_i - T_j q_i))^2 / sigma_n^2 + sum_k (|w_k|^2 / sigma_w,k^2 + |t_k|^2 / sigma_t,k^2),

    with p_i head k's points, q_i the nearest point of another head j (within ``max_distance_mm``) and
    n_i the mean normal of j's 8 nearest (normals by PCA over 30 points, :func:`surface_normals`), by Gauss-Newton on R(w) ~ I + [w]x with the reference
    head's correction held at the identity. A head whose correction goes beyond the bound is refused,
    held where the calibration put it, and the others are solved again without moving it.
    Correspondences beyond 3 median absolute deviations of the distances, or whose two normals differ
    by more than 10 degrees (at a rim), are dropped in each iteration. The prior keeps the directions
    the overlaps do not constrain (a cylinder's rotation about its axis, and sliding along it where no end face is shared)
    where the calibration put them, instead of letting noise move them; the steps are taken only along
    directions the overlaps constrain [2]_. Written here rather than with
    Open3D's ``registration_icp``: that registers one pair without a prior, and the heads' overlaps
    must be solved together (a head overlaps two or three others) and are degenerate alone.

    References
    ----------
    .. [1] Y. Chen and G. Medioni, "Object modelling by registration of multiple range images",
       Image and Vision Computing 10(3), 145-155, 1992.
    .. [2] J. Zhang, M. Kaess and S. Singh, "On degeneracy of optimization-based state estimation
       problems", ICRA 2016 (solution remapping).
    """
    count = len(points)
    if len(normals) != count or len(uncertainty) != count:
        raise ValueError(f"points, normals and uncertainty must have one entry per head; got {count}, "
                         f"{len(normals)} and {len(uncertainty)}.")
    if not 0 <= reference < count:
        raise ValueError(f"The reference head must be one of the {count} heads; got {reference}.")
    clean = _clean(points, normals, _REFINE_POINTS, sampled)
    centres = [p.mean(axis=0) if len(p) else np.zeros(3) for p, _ in clean]
    prior = np.zeros((count, 6))
    for k, u in enumerate(uncertainty):
        prior[k] = [1 / np.radians(u.rotation_deg) ** 2] * 3 + [1 / u.translation_mm ** 2] * 3
    held = {reference}
    refused: dict[int, PoseCorrection] = {}
    while True:  # a head whose correction is refused stays put, and the others are solved again without it
        x, overlap = _solve_jointly(clean, centres, prior, held, max_distance_mm, noise_mm, iterations)
        corrections = []
        for k in range(count):
            if k == reference:
                corrections.append(_identity(centres[k], True, int(overlap[k])))
            elif k in refused:
                corrections.append(refused[k])
            elif overlap[k] < _MIN_OVERLAP:
                corrections.append(_identity(centres[k], False, int(overlap[k]),
                                             f"too little overlap ({overlap[k]} points)"))
            else:
                corrections.append(PoseCorrection(Rotation.from_rotvec(x[k, :3]).as_matrix(), x[k, 3:].copy(),
                                                  centres[k], True, int(overlap[k])))
        beyond = [k for k, c in enumerate(corrections) if c.applied and k != reference
                  and (c.translation_mm > bound_sigmas * uncertainty[k].translation_mm
                       or c.rotation_deg > bound_sigmas * uncertainty[k].rotation_deg)]
        if not beyond:
            return corrections
        for k in beyond:
            c, u = corrections[k], uncertainty[k]
            reason = (f"the overlap asks for {c.translation_mm:.3f} mm and {c.rotation_deg:.4f} deg, beyond "
                      f"{bound_sigmas:g} sigma of the calibration ({u.translation_mm:g} mm, {u.rotation_deg:g} deg)")
            refused[k] = PoseCorrection(c.rotation, c.translation, centres[k], False, c.overlap, reason)
            held.add(k)


def _step(data: np.ndarray, gradient: np.ndarray, prior: np.ndarray, x: np.ndarray) -> np.ndarray:
    """One Gauss-Newton step of the data (normal matrix, gradient) plus the prior (precisions ``prior`` about 0),
    taken only along the directions the data constrain.

    In units of the prior's standard deviations the data's normal matrix is H = S J^T J S / sigma_n^2
    (S = diag(sigma)); its eigenvectors of eigenvalue below ``_DEGENERATE`` times the largest are
    directions the overlaps leave open (a cylinder's rotation about its axis, sliding along it). The
    points' noise is not independent (the reconstruction's small systematic errors are correlated over
    the surface), so there even a tiny systematic residual would outweigh the prior; the step leaves
    those directions where the calibration put them (solution remapping: Zhang, Kaess and Singh, ICRA
    2016).
    """
    scale = 1 / np.sqrt(prior)
    scaled = data * np.outer(scale, scale)
    values, vectors = np.linalg.eigh(scaled)
    kept = values > _DEGENERATE * max(values.max(), 1e-300)
    vectors, values = vectors[:, kept], values[kept]
    scaled_gradient = scale * gradient + x / scale  # the prior's gradient is x / sigma^2, scaled by sigma
    return scale * (vectors @ ((vectors.T @ scaled_gradient) / -(values + 1.0)))


def _rotate(vectors: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``vectors @ rotation.T`` for (N, 3) vectors, without BLAS (whose threads cost more than a 3x3 product)."""
    return (vectors[:, :1] * rotation[:, 0] + vectors[:, 1:2] * rotation[:, 1]) + vectors[:, 2:] * rotation[:, 2]


def _near_box(points: np.ndarray, box: tuple[np.ndarray, np.ndarray], distance: float) -> np.ndarray:
    """The rows of ``points`` within ``distance`` of the axis-aligned box (low, high)."""
    return np.flatnonzero(((points >= box[0] - distance) & (points <= box[1] + distance)).all(axis=1))


class _Candidates:
    """For every ordered pair of heads (k, j), the points of k within ``reach`` of j's at the positions they were
    found at; a point of k farther than that from every point of j stays beyond ``reach - margin`` while the two
    heads' points have moved by less than ``margin`` together since (the triangle inequality), so the
    correspondences need only be looked for among the candidates until then."""

    def __init__(self, trees: list[cKDTree | None], reach: float, margin: float) -> None:
        self.trees, self.reach, self.margin = trees, reach, margin
        self.rows: dict[tuple[int, int], np.ndarray] = {}
        self.found_at: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def update(self, moved: list[np.ndarray], to_frame: list) -> None:
        """Find a pair's candidates again when its two heads moved by ``margin`` together since they were found."""
        def shift(now: np.ndarray, then: np.ndarray) -> float:
            return float(np.sqrt(((now - then) ** 2).sum(axis=1).max())) if len(now) else 0.0

        boxes = [(m.min(axis=0), m.max(axis=0)) if len(m) else None for m in moved]
        for k in range(len(moved)):
            for j in range(len(moved)):
                if j == k or self.trees[j] is None or not len(moved[k]):
                    continue
                then = self.found_at.get((k, j))
                if then is not None and shift(moved[k], then[0]) + shift(moved[j], then[1]) <= self.margin:
                    continue
                near = _near_box(moved[k], boxes[j], self.reach)
                distance, _ = self.trees[j].query(to_frame[j](moved[k][near]), k=1,
                                                  distance_upper_bound=self.reach, workers=-1)
                self.rows[k, j] = near[np.isfinite(distance)]
                self.found_at[k, j] = (moved[k], moved[j])


def _correspondences(k: int, moved: list[np.ndarray], to_frame: list, trees: list[cKDTree | None],
                     candidates: _Candidates, max_distance: float) -> tuple[np.ndarray, ...]:
    """Head k's points that have a point of another head within ``max_distance``: their rows, the distances,
    heads and rows (in their heads) of their ``_NEIGHBOURS`` nearest points of the other heads (all together,
    nearest first; inf distance where fewer are that close). Each other head's k-d tree is of its points where
    the calibration put them and is built once: the query points are taken into its frame (a rigid motion
    keeps distances)."""
    others = [j for j in range(len(moved)) if j != k and (k, j) in candidates.rows and len(candidates.rows[k, j])]
    if not others:
        return np.zeros(0, dtype=np.int64), np.zeros((0, _NEIGHBOURS)), np.zeros((0, _NEIGHBOURS), dtype=np.int64), \
            np.zeros((0, _NEIGHBOURS), dtype=np.int64)
    member = np.zeros(len(moved[k]), dtype=bool)
    for j in others:
        member[candidates.rows[k, j]] = True
    rows = np.flatnonzero(member)
    position = np.cumsum(member) - 1  # a candidate's row in ``rows``
    distance = np.full((len(rows), _NEIGHBOURS * len(others)), np.inf)
    owner = np.zeros(distance.shape, dtype=np.int64)
    local = np.zeros(distance.shape, dtype=np.int64)
    for column, j in enumerate(others):
        mine = candidates.rows[k, j]
        d, i = trees[j].query(to_frame[j](moved[k][mine]), k=_NEIGHBOURS, distance_upper_bound=max_distance,
                              workers=-1)
        span = slice(column * _NEIGHBOURS, (column + 1) * _NEIGHBOURS)
        at = position[mine]
        distance[at, span], owner[at, span], local[at, span] = d, j, np.where(np.isfinite(d), i, 0)
    if len(others) > 1:  # the nearest of all the other heads' nearest
        heads_near = np.isfinite(distance[:, ::_NEIGHBOURS])
        first = np.argmax(heads_near, axis=1)  # the one head near, for most points
        columns = first[:, None] * _NEIGHBOURS + np.arange(_NEIGHBOURS)
        several = np.flatnonzero(heads_near.sum(axis=1) > 1)
        columns[several] = np.argsort(distance[several], axis=1, kind="stable")[:, :_NEIGHBOURS]
        distance = np.take_along_axis(distance, columns, axis=1)
        owner, local = np.take_along_axis(owner, columns, axis=1), np.take_along_axis(local, columns, axis=1)
    return rows, distance, owner, local


def _solve_jointly(clean: list[tuple[np.ndarray, np.ndarray]], centres: list[np.ndarray], prior: np.ndarray,
                   held: set[int], max_distance: float, noise: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton iterations of :func:`refine_head_poses` with the heads ``held`` at the identity: every
    head's (rotation vector, translation) and its correspondences in the last iteration."""
    count = len(clean)
    x = np.zeros((count, 6))
    overlap = np.zeros(count, dtype=int)
    trees = [cKDTree(p) if len(p) else None for p, _ in clean]
    candidates = _Candidates(trees, max_distance + _CANDIDATE_MARGIN_MM, _CANDIDATE_MARGIN_MM)
    for _ in range(iterations):
        rotations = [Rotation.from_rotvec(x[k, :3]).as_matrix() for k in range(count)]
        relative = [_rotate(p - c, r) for (p, _), c, r in zip(clean, centres, rotations)]
        moved = [a + c + x[k, 3:] for k, (a, c) in enumerate(zip(relative, centres))]
        moved_normals = [_rotate(n, r) for (_, n), r in zip(clean, rotations)]
        # a world point y is near head j's moved points where R_j^T (y - c_j - t_j) + c_j is near its own
        to_frame = [lambda y, r=r, c=c, t=x[j, 3:].copy(): _rotate(y - c - t, r.T) + c
                    for j, (r, c) in enumerate(zip(rotations, centres))]
        candidates.update(moved, to_frame)
        all_moved, all_normals = np.concatenate(moved), np.concatenate(moved_normals)
        offsets = np.cumsum([0] + [len(m) for m in moved[:-1]])
        normal_matrix = np.zeros((6 * count, 6 * count))  # the data's, J^T J (without 1 / sigma_n^2)
        gradient = np.zeros(6 * count)
        overlap[:] = 0
        for k in range(count):
            at, distance, owner, local = _correspondences(k, moved, to_frame, trees, candidates, max_distance)
            if not len(at):
                continue
            found = np.isfinite(distance)
            good = found[:, 0]
            neighbour = offsets[owner] + local  # rows in all heads' points together
            normal = (all_normals[neighbour] * found[..., None]).sum(axis=1)
            length = np.linalg.norm(normal, axis=1)
            good &= length > 0.5 * found.sum(axis=1)  # the neighbours' normals roughly agree
            normal /= np.maximum(length, 1e-12)[:, None]
            good &= np.einsum("ij,ij->i", moved_normals[k][at], normal) >= np.cos(np.radians(_MAX_NORMAL_ANGLE_DEG))
            nearest_owner, nearest = owner[:, 0], local[:, 0]
            residual = np.einsum("ij,ij->i", moved[k][at] - all_moved[neighbour[:, 0]], normal)
            if good.sum() >= _MIN_OVERLAP:
                spread = 1.4826 * np.median(np.abs(residual[good] - np.median(residual[good])))
                good &= np.abs(residual - np.median(residual[good])) <= max(3 * spread, noise)
            rows = np.flatnonzero(good)
            overlap[k] += len(rows)
            n, r = normal[rows], residual[rows]
            blocks = {k: np.column_stack([np.cross(relative[k][at[rows]], n), n])}
            j_of = nearest_owner[rows]
            for j in np.unique(j_of):
                mine = j_of == j
                b = relative[j][nearest[rows][mine]]
                jacobian = np.zeros((len(rows), 6))
                jacobian[mine] = -np.column_stack([np.cross(b, n[mine]), n[mine]])
                blocks[int(j)] = jacobian
            for a, ja in blocks.items():
                gradient[6 * a:6 * a + 6] += ja.T @ r
                for b, jb in blocks.items():
                    normal_matrix[6 * a:6 * a + 6, 6 * b:6 * b + 6] += ja.T @ jb
        free = np.array([k not in held and overlap[k] >= _MIN_OVERLAP for k in range(count)])
        index = np.flatnonzero(np.repeat(free, 6))
        if not len(index):
            break
        step = _step(normal_matrix[np.ix_(index, index)] / noise**2, gradient[index] / noise**2,
                     prior.ravel()[index], x.reshape(-1)[index])
        x.reshape(-1)[index] += step
        if (np.abs(step) * np.sqrt(prior.ravel()[index])).max() < _CONVERGED:
            break
    return x, overlap


def overlap_residuals(points: Sequence[np.ndarray], normals: Sequence[np.ndarray], *,
                      max_distance_mm: float = DEFAULT_MAX_DISTANCE_MM, patch_mm: float = PATCH_MM,
                      min_points: int = _MIN_OVERLAP, most: int | None = RESIDUAL_POINTS,
                      sampled: bool = False) -> list[PairResidual]:
    """The residual between every pair of heads that overlap (by at least ``min_points`` points each way).

    Each point of one head within ``max_distance_mm`` of the other's is measured along the other's local
    normal (the mean of its 8 nearest, within 10 degrees of the point's own) from the other's nearest point,
    both ways, signed as the first head's
    surface less the second's (the normals point out of the part); distances beyond 5 median absolute
    deviations (stray points at the silhouettes) are left out. ``patch_rms_mm`` is the RMS over patches
    of ``patch_mm`` of the mean distance in each (patches of at least 5 points). Each head contributes about
    ``most`` of its points (every k-th; None: all); ``sampled``: the points and normals are each head's
    :class:`OverlapSample` ``residual_points`` and ``residual_normals``, used as they are.
    """
    clean = _clean(points, normals, most, sampled)
    trees = [cKDTree(p) if len(p) else None for p, _ in clean]
    boxes = [(p.min(axis=0), p.max(axis=0)) if len(p) else None for p, _ in clean]
    residuals = []
    for a in range(len(clean)):
        for b in range(a + 1, len(clean)):
            located, distances = [], []
            for first, second, sign in ((a, b, 1.0), (b, a, -1.0)):  # both ways as a's surface less b's
                if trees[second] is None or not len(clean[first][0]):
                    continue
                near = _near_box(clean[first][0], boxes[second], max_distance_mm)  # the others are no overlap
                mine, mine_normals = clean[first][0][near], clean[first][1][near]
                q, n, good = _local_planes(trees[second], *clean[second], mine, mine_normals, max_distance_mm)
                located.append(mine[good])
                distances.append(sign * _signed_distances(mine[good], q[good], n[good]))
            if not distances or sum(len(d) for d in distances) < 2 * min_points:
                continue
            where, distance = np.concatenate(located), np.concatenate(distances)
            spread = 1.4826 * np.median(np.abs(distance - np.median(distance)))
            keep = np.abs(distance - np.median(distance)) <= 5 * max(spread, 1e-6)
            where, distance = where[keep], distance[keep]
            patch = _cells(where, patch_mm)
            counts = np.bincount(patch)
            means = np.bincount(patch, distance) / counts
            full = counts >= 5
            residuals.append(PairResidual(a, b, int(len(distance)), float(np.sqrt(np.mean(distance**2))),
                                          float(np.sqrt(np.mean(means[full] ** 2))) if full.any() else float("nan")))
    return residuals


def _cells(points: np.ndarray, side: float) -> np.ndarray:
    """Each point's cube of side ``side`` as 0, 1, ... (the cubes that hold points, in the order of their index
    (i, j, k) = floor(p / side)): one integer key per cube sorted, not rows of three."""
    index = np.floor(points / side).astype(np.int64)
    low, high = index.min(axis=0), index.max(axis=0)
    if np.prod((high - low + 1).astype(np.float64)) >= 2.0**62:  # too far apart for one integer per cube
        return np.unique(index, axis=0, return_inverse=True)[1].reshape(-1)
    _, cell = np.unique(np.ravel_multi_index((index - low).T, high - low + 1), return_inverse=True)
    return cell.reshape(-1)


def thin_overlaps(points: np.ndarray, head: np.ndarray, view_angle: np.ndarray, voxel_mm: float) -> np.ndarray:
    """Which points to keep so that an overlap is not doubled: in every voxel of side ``voxel_mm`` that holds
    points of several heads, those of the head that saw the voxel at the smallest mean view angle.

    Parameters
    ----------
    points : (N, 3) array
        World mm.
    head : (N,) int array
        Each point's head.
    view_angle : (N,) array
        The angle between each point's normal and the line of sight to its head's camera (any unit;
        NaN counts as the worst).
    voxel_mm : float
        The voxel's side: about the points' spacing or a few times it.

    Returns
    -------
    keep : (N,) bool array
    """
    if not voxel_mm > 0:
        raise ValueError(f"The voxel's side must be positive; got {voxel_mm}.")
    points = np.asarray(points, dtype=np.float64)
    head = np.asarray(head)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    angle = np.where(np.isfinite(view_angle), view_angle, np.inf)
    voxel = _cells(points, voxel_mm)
    heads = int(head.max()) + 1
    pair = voxel * heads + head
    counts = np.bincount(pair, minlength=(voxel.max() + 1) * heads).reshape(-1, heads)
    finite_angle = np.where(np.isfinite(angle), angle, 1e9)
    sums = np.bincount(pair, finite_angle, minlength=counts.size).reshape(-1, heads)
    mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.inf)
    best = np.argmin(mean, axis=1)
    return best[voxel] == head

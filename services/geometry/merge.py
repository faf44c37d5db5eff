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
        moved = (points - self.centre) @ self.rotation.T + self.centre + self.translation
        return moved, None if normals is None else normals @ self.rotation.T


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


def _identity(centre: np.ndarray, applied: bool, overlap: int, reason: str = "") -> PoseCorrection:
    return PoseCorrection(np.eye(3), np.zeros(3), centre, applied, overlap, reason)


def _local_planes(tree: cKDTree, points: np.ndarray, normals: np.ndarray, queries: np.ndarray,
                  max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query, the plane of its nearest target points (their mean and mean normal) and whether the
    nearest lies within ``max_distance``."""
    distance, index = tree.query(queries, k=_NEIGHBOURS, distance_upper_bound=max_distance)
    found = np.isfinite(distance)
    close = found[:, 0]
    index = np.where(found, index, 0)
    weight = found[..., None].astype(np.float64)
    count = np.maximum(weight.sum(axis=1), 1.0)
    centre = (points[index] * weight).sum(axis=1) / count
    normal = (normals[index] * weight).sum(axis=1)
    length = np.linalg.norm(normal, axis=1)
    good = close & (length > 0.5 * found.sum(axis=1))  # the neighbours' normals roughly agree
    normal /= np.maximum(length, 1e-12)[:, None]
    return centre, normal, good


def _signed_distances(points: np.ndarray, centres: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", points - centres, normals)


def refine_head_poses(points: Sequence[np.ndarray], normals: Sequence[np.ndarray],
                      uncertainty: Sequence[PoseUncertainty], *, reference: int = 0,
                      max_distance_mm: float = DEFAULT_MAX_DISTANCE_MM, noise_mm: float = DEFAULT_NOISE_MM,
                      bound_sigmas: float = DEFAULT_BOUND_SIGMAS, iterations: int = 15,
                      rounds: int = 2) -> list[PoseCorrection]:
    """Rigid corrections laying each head's cloud on the others' where they overlap, within the calibration.

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
    iterations, rounds : int
        Gauss-Newton iterations per head, and rounds over all heads (each head is laid on the others as
        the previous round left them).

    Returns
    -------
    list of PoseCorrection
        One per head (the reference's is the identity).

    Notes
    -----
    Each head k's correction (rotation vector w, translation t, about the centroid c of its points)
    minimises the point-to-plane ICP cost [1]_ plus a Gaussian prior from the calibration,

        sum_i (n_i . (R(w) (p_i - c) + c + t - q_i))^2 / sigma_n^2 + |w|^2 / sigma_w^2 + |t|^2 / sigma_t^2,

    with p_i head k's points, q_i and n_i the mean and mean normal of the 8 nearest points of the
    other heads (within ``max_distance_mm``), by Gauss-Newton on R(w) ~ I + [w]x. Correspondences
    beyond 3 median absolute deviations of the distances are dropped in each iteration. The prior
    keeps the directions the overlap does not constrain (a cylinder's rotation about its axis and
    sliding along it, where no end face is shared) where the calibration put them, instead of letting
    noise move them. Written here rather than with Open3D's ``registration_icp``: its point-to-plane
    estimation has no prior, and a cylinder's overlap leaves it degenerate.

    References
    ----------
    .. [1] Y. Chen and G. Medioni, "Object modelling by registration of multiple range images",
       Image and Vision Computing 10(3), 145-155, 1992.
    """
    count = len(points)
    if len(normals) != count or len(uncertainty) != count:
        raise ValueError(f"points, normals and uncertainty must have one entry per head; got {count}, "
                         f"{len(normals)} and {len(uncertainty)}.")
    if not 0 <= reference < count:
        raise ValueError(f"The reference head must be one of the {count} heads; got {reference}.")
    clean = []
    for p, n in zip(points, normals):
        p, n = np.asarray(p, dtype=np.float64), np.asarray(n, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
            raise ValueError(f"Each head's points and normals must both be (N, 3); got {p.shape} and {n.shape}.")
        good = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
        clean.append((p[good], n[good]))
    centres = [p.mean(axis=0) if len(p) else np.zeros(3) for p, _ in clean]
    corrections = [_identity(centres[k], True, 0) for k in range(count)]
    for _ in range(rounds):
        for k in range(count):
            if k == reference:
                continue
            others = [corrections[j].apply(*clean[j]) for j in range(count) if j != k]
            target_points = np.concatenate([o[0] for o in others])
            target_normals = np.concatenate([o[1] for o in others])
            corrections[k] = _refine_one(clean[k], target_points, target_normals, centres[k], uncertainty[k],
                                         max_distance_mm, noise_mm, bound_sigmas, iterations)
    return corrections


def _refine_one(source: tuple[np.ndarray, np.ndarray], target_points: np.ndarray, target_normals: np.ndarray,
                centre: np.ndarray, uncertainty: PoseUncertainty, max_distance: float, noise: float,
                bound_sigmas: float, iterations: int) -> PoseCorrection:
    points = source[0]
    if len(points) == 0 or len(target_points) == 0:
        return _identity(centre, False, 0, "no overlap")
    tree = cKDTree(target_points)
    prior = np.diag([1 / np.radians(uncertainty.rotation_deg) ** 2] * 3 + [1 / uncertainty.translation_mm ** 2] * 3)
    x = np.zeros(6)  # rotation vector, translation
    overlap = 0
    for _ in range(iterations):
        rotation = Rotation.from_rotvec(x[:3]).as_matrix()
        relative = (points - centre) @ rotation.T
        moved = relative + centre + x[3:]
        q, n, good = _local_planes(tree, target_points, target_normals, moved, max_distance)
        residual = _signed_distances(moved, q, n)
        if good.sum() >= _MIN_OVERLAP:
            spread = 1.4826 * np.median(np.abs(residual[good] - np.median(residual[good])))
            good &= np.abs(residual) <= max(3 * spread, noise)
        overlap = int(good.sum())
        if overlap < _MIN_OVERLAP:
            return _identity(centre, False, overlap, f"too little overlap ({overlap} points)")
        n, r, a = n[good], residual[good], relative[good]
        jacobian = np.column_stack([np.cross(a, n), n])  # d(n . (R a + c + t - q)) / d(w, t) at the current R
        normal_matrix = jacobian.T @ jacobian / noise**2 + prior
        gradient = jacobian.T @ r / noise**2 + prior @ x
        step = -np.linalg.solve(normal_matrix, gradient)
        x += step
        if np.abs(step[:3]).max() < 1e-9 and np.abs(step[3:]).max() < 1e-6:
            break
    correction = PoseCorrection(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:].copy(), centre, True, overlap)
    if (correction.translation_mm > bound_sigmas * uncertainty.translation_mm
            or correction.rotation_deg > bound_sigmas * uncertainty.rotation_deg):
        reason = (f"the overlap asks for {correction.translation_mm:.3f} mm and {correction.rotation_deg:.4f} deg, "
                  f"beyond {bound_sigmas:g} sigma of the calibration ({uncertainty.translation_mm:g} mm, "
                  f"{uncertainty.rotation_deg:g} deg)")
        return PoseCorrection(correction.rotation, correction.translation, centre, False, overlap, reason)
    return correction


def overlap_residuals(points: Sequence[np.ndarray], normals: Sequence[np.ndarray], *,
                      max_distance_mm: float = DEFAULT_MAX_DISTANCE_MM, patch_mm: float = PATCH_MM,
                      min_points: int = _MIN_OVERLAP) -> list[PairResidual]:
    """The residual between every pair of heads that overlap (by at least ``min_points`` points each way).

    Each point of one head within ``max_distance_mm`` of the other's is measured along the other's local
    normal from the plane of the other's 8 nearest points, both ways; distances beyond 5 median absolute
    deviations (stray points at the silhouettes) are left out. ``patch_rms_mm`` is the RMS over patches
    of ``patch_mm`` of the mean distance in each (patches of at least 5 points).
    """
    clean = []
    for p, n in zip(points, normals):
        p, n = np.asarray(p, dtype=np.float64), np.asarray(n, dtype=np.float64)
        good = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1)
        clean.append((p[good], n[good]))
    trees = [cKDTree(p) if len(p) else None for p, _ in clean]
    residuals = []
    for a in range(len(clean)):
        for b in range(a + 1, len(clean)):
            located, distances = [], []
            for first, second in ((a, b), (b, a)):
                if trees[second] is None or not len(clean[first][0]):
                    continue
                q, n, good = _local_planes(trees[second], *clean[second], clean[first][0], max_distance_mm)
                located.append(clean[first][0][good])
                distances.append(_signed_distances(clean[first][0][good], q[good], n[good]))
            if not distances or sum(len(d) for d in distances) < 2 * min_points:
                continue
            where, distance = np.concatenate(located), np.concatenate(distances)
            spread = 1.4826 * np.median(np.abs(distance - np.median(distance)))
            keep = np.abs(distance - np.median(distance)) <= 5 * max(spread, 1e-6)
            where, distance = where[keep], distance[keep]
            cells = np.floor(where / patch_mm).astype(np.int64)
            _, patch, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
            patch = patch.reshape(-1)
            means = np.bincount(patch, distance) / counts
            full = counts >= 5
            residuals.append(PairResidual(a, b, int(len(distance)), float(np.sqrt(np.mean(distance**2))),
                                          float(np.sqrt(np.mean(means[full] ** 2))) if full.any() else float("nan")))
    return residuals


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
    _, voxel = np.unique(np.floor(points / voxel_mm).astype(np.int64), axis=0, return_inverse=True)
    voxel = voxel.reshape(-1)
    heads = int(head.max()) + 1
    pair = voxel * heads + head
    counts = np.bincount(pair, minlength=(voxel.max() + 1) * heads).reshape(-1, heads)
    finite_angle = np.where(np.isfinite(angle), angle, 1e9)
    sums = np.bincount(pair, finite_angle, minlength=counts.size).reshape(-1, heads)
    mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.inf)
    best = np.argmin(mean, axis=1)
    return best[voxel] == head

"""Alignment of the nominal part to measured points: principal-axis starts, then robust point-to-plane ICP."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations, product

import numpy as np


from services.inspection.nominal import NominalSurface

_COARSE_POINTS = 300
_CANDIDATE_POINTS = 3000
_FINE_POINTS = 10000
_COARSE_KEEP = 3
_PRUNED_STARTS = 6


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
        return (np.asarray(points) - translation) @ rotation

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Part-frame points (N, 3) in the world frame."""
        return np.asarray(points) @ self.matrix[:3, :3].T + self.matrix[:3, 3]


def _even_subset(count: int, wanted: int) -> np.ndarray:
    return np.arange(count) if count <= wanted else np.linspace(0, count - 1, wanted).astype(np.intp)


def _principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - centre).T))
    return centre, vectors[:, ::-1]


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


def _rotation(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _samples(nominal: NominalSurface, coarse: bool):
    if coarse:
        return nominal.coarse_tree, nominal.coarse_samples, nominal.coarse_normals
    return nominal.sample_tree, nominal.samples, nominal.sample_normals


def _icp(points: np.ndarray, nominal: NominalSurface, transform: np.ndarray, distances: np.ndarray,
         coarse: bool = False) -> np.ndarray:
    """Point-to-plane ICP with Tukey weights, one iteration per entry of ``distances`` (the Tukey cut-off, mm).

    ``transform`` maps measured points to the part frame; ``coarse`` matches against the nominal's
    sparse samples. Hand-written on the nominal's prepared cKDTrees: Open3D's ``registration_icp``
    searches its own tree by radius on every call, which made the 24 starts take seconds.
    """
    tree, samples, sample_normals = _samples(nominal, coarse)
    rotation, translation = transform[:3, :3].copy(), transform[:3, 3].copy()
    for cut_off in distances:
        moved = points @ rotation.T + translation
        # bounded: a far query visits much of the tree, and beyond the cut-off its weight is 0 anyway
        distance, index = tree.query(moved, distance_upper_bound=cut_off)
        near = np.isfinite(distance)
        moved, index = moved[near], index[near]
        target, normal = samples[index], sample_normals[index]
        residual = np.einsum("ij,ij->i", moved - target, normal)
        u = residual / cut_off
        weight = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        if weight.sum() < 6:
            break
        design = np.column_stack([np.cross(moved, normal), normal])
        system = design.T @ (design * weight[:, None])
        step = np.linalg.lstsq(system, -design.T @ (weight * residual), rcond=None)[0]
        increment = _rotation(step[:3])
        rotation, translation = increment @ rotation, increment @ translation + step[3:]
    result = np.eye(4)
    result[:3, :3], result[:3, 3] = rotation, translation
    return result


def _near_score(points: np.ndarray, nominal: NominalSurface, transform: np.ndarray, cut_off: float):
    """(-fraction of points within ``cut_off`` of a sparse nominal sample, their median distance): lower is better."""
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    distance, _ = nominal.coarse_tree.query(moved, distance_upper_bound=cut_off)
    near = np.isfinite(distance)
    return -round(float(near.mean()), 2), float(np.median(distance[near])) if near.any() else np.inf


def _score(points: np.ndarray, nominal: NominalSurface, transform: np.ndarray, max_distance: float):
    distance = np.abs(nominal.signed_distance(points @ transform[:3, :3].T + transform[:3, 3]))
    inliers = distance <= max_distance
    rms = float(np.sqrt(np.mean(distance[inliers] ** 2))) if inliers.any() else float("inf")
    return float(inliers.mean()), rms


def align_nominal(points: np.ndarray, nominal: NominalSurface, max_distance_mm: float = 2.0,
                  start: np.ndarray | None = None, polish: bool = True) -> Alignment:
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
        A known part-to-world transform to refine; without it the 24 axis-to-axis matches of the
        principal frames are tried.
    polish : bool
        Refine the winner on 10 000 points; without, the alignment ends on 3000 points (a first
        alignment that a later call refines).

    Returns
    -------
    Alignment
        The part-to-world transform with its residual.

    Notes
    -----
    Correspondences run from each measured point to its nearest nominal surface sample, never the
    other way, so the part's unseen side does not pull on the fit: the view may be one-sided.
    Each start R0 = E_n P E_m^T, t0 = c_n - R0 c_m (principal axes E and centroids c of the nominal
    samples and the measured points, P one of the 24 signed permutations with det +1; for the 8 that
    match the first axes, also t0 shifted along the nominal's first axis so that the measured points'
    lower or upper end (0.5 and 99.5 percentiles) meets the nominal's: a one-sided view's centroid lies
    off the part's, and along a cylinder ICP cannot tell a shift from a fit until a face pins it) is
    refined by point-to-plane ICP [1]_ with Tukey weights [2]_ on 300 points against 3000 nominal
    samples, the weights' cut-off shrinking from a quarter to a thirtieth of the part's size over 10
    iterations (after 3, only the 6 starts with most points near the nominal go on); the three starts with most
    points near the nominal are refined on 3000 points down to ``max_distance_mm``; the one with most
    points within that distance of the nominal surface (then the lowest residual) wins and is
    polished by 5 iterations on 10 000 points. Symmetries of the part (a cylinder's rotation about its axis) leave
    the transform undetermined along them, which no measure depends on.

    References
    ----------
    .. [1] Y. Chen and G. Medioni, "Object modelling by registration of multiple range images",
       Image and Vision Computing 10(3), 1992.
    .. [2] P. Babin, P. Giguere and F. Pomerleau, "Analysis of robust functions for registration
       algorithms", ICRA 2019.
    """
    points = np.asarray(points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 10:
        raise ValueError(f"Only {len(points)} measured points of the part; at least 10 are needed to align it.")
    size = float(np.linalg.norm(np.ptp(nominal.samples, axis=0)))
    fine = points[_even_subset(len(points), _FINE_POINTS)]
    if start is not None:
        candidates = [np.linalg.inv(start)]
    else:
        coarse = points[_even_subset(len(points), _COARSE_POINTS)]
        measured_centre, measured_axes = _principal_frame(fine)
        nominal_centre, nominal_axes = _principal_frame(nominal.samples)
        starts = []
        axis = nominal_axes[:, 0]
        nominal_extent = np.percentile(nominal.samples @ axis, [0.5, 99.5])
        for permutation in _start_rotations():
            rotation = nominal_axes @ permutation @ measured_axes.T
            translation = nominal_centre - rotation @ measured_centre
            shifts = [0.0]
            if permutation[0, 0] != 0:  # first axes matched: a one-sided view's centroid lies off the part's
                measured_extent = np.percentile((fine @ rotation.T + translation) @ axis, [0.5, 99.5])
                shifts += list(nominal_extent - measured_extent)  # so also try the view's ends on the part's
            for shift in shifts:
                guess = np.eye(4)
                guess[:3, :3], guess[:3, 3] = rotation, translation + shift * axis
                starts.append(guess)
        schedule = np.geomspace(size / 4, size / 30, 10)
        for distances, keep in ((schedule[:3], _PRUNED_STARTS), (schedule[3:], _COARSE_KEEP)):
            refined = [_icp(coarse, nominal, start, distances, coarse=True) for start in starts]
            scored = sorted((_near_score(coarse, nominal, transform, distances[-1]), index)
                            for index, transform in enumerate(refined))
            starts = [refined[index] for _, index in scored[:keep]]
        candidates = starts
    middle = points[_even_subset(len(points), _CANDIDATE_POINTS)]
    best = None
    for candidate in candidates:
        transform = _icp(middle, nominal, candidate, np.geomspace(8 * max_distance_mm, max_distance_mm, 10))
        fraction, rms = _score(middle, nominal, transform, max_distance_mm)
        key = (-round(fraction, 3), rms)
        if best is None or key < best[0]:
            best = (key, transform)
    if not polish:
        return Alignment(matrix=np.linalg.inv(best[1]), rms_mm=best[0][1], inlier_fraction=-best[0][0])
    transform = _icp(fine, nominal, best[1], np.full(5, max_distance_mm))
    fraction, rms = _score(fine, nominal, transform, max_distance_mm)
    return Alignment(matrix=np.linalg.inv(transform), rms_mm=rms, inlier_fraction=fraction)

"""Geometric models of the infrared-to-visible mapping, as 3x3 matrices on pixel coordinates.

Each model is parameterised as a small update ``G(p)`` applied in the moving
(infrared) image's pixel coordinates, ``H = H_ref @ G(p)``, with ``G(0) = I``.
Parameters are scaled so that one unit moves the image corners by about one
moving pixel, so one optimiser tolerance fits every model and parameter.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

MODELS = ("translation", "rigid", "similarity", "affine", "homography")
PARAMETER_COUNTS = {"translation": 2, "rigid": 3, "similarity": 4, "affine": 6, "homography": 8}


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise ValueError(f"Unknown registration model {model!r}; choose one of {', '.join(MODELS)}.")


def image_corners(width: int, height: int) -> np.ndarray:
    """The centres of an image's four corner pixels, (4, 2), clockwise from the top left."""
    return np.array([[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0], [0.0, height - 1.0]])


def apply_homography(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) pixel coordinates through a 3x3 matrix (with the perspective division)."""
    points = np.asarray(points, dtype=np.float64)
    mapped = points @ matrix[:, :2].T + matrix[:, 2]
    return mapped[:, :2] / mapped[:, 2:3]


def _about_point(linear: np.ndarray, centre: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """x -> centre + shift + linear (x - centre), as a 3x3 matrix."""
    translation = centre + shift - linear @ centre
    return np.array([[linear[0, 0], linear[0, 1], translation[0]], [linear[1, 0], linear[1, 1], translation[1]],
                     [0.0, 0.0, 1.0]])


@functools.cache
def _centre_and_radius(width: int, height: int) -> tuple[np.ndarray, float]:
    """The centre of a ``width`` x ``height`` image (read-only) and its half-diagonal."""
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    centre.flags.writeable = False
    return centre, 0.5 * float(np.hypot(width, height))


def update_matrix(model: str, parameters: np.ndarray, width: int, height: int) -> np.ndarray:
    """The update G(p) of a model on a ``width`` x ``height`` moving image.

    Parameters
    ----------
    model : {"translation", "rigid", "similarity", "affine", "homography"}
        Degrees of freedom: 2, 3, 4, 6 and 8.
    parameters : (n,) array
        Translation (tx, ty) in pixels, then for rigid/similarity the rotation
        and log-scale times the half-diagonal r, for affine the 2x2 linear part
        minus identity times r, for homography the displacements of the four
        corners.
    width, height : int
        Moving image size; rotations and scalings are about its centre.

    Returns
    -------
    (3, 3) float64 matrix.
    """
    _check_model(model)
    p = np.asarray(parameters, dtype=np.float64).ravel()
    if p.size != PARAMETER_COUNTS[model]:
        raise ValueError(f"The {model} model has {PARAMETER_COUNTS[model]} parameters; got {p.size}.")
    centre, radius = _centre_and_radius(width, height)  # the refinement asks thousands of times for one size
    if model == "homography":
        corners = image_corners(width, height)
        moved = corners + p.reshape(4, 2)
        return cv2.getPerspectiveTransform(corners.astype(np.float32), moved.astype(np.float32)).astype(np.float64)
    if model == "translation":
        linear = np.eye(2)
    elif model == "affine":
        linear = np.eye(2) + p[2:].reshape(2, 2) / radius
    else:
        angle = p[2] / radius
        scale = np.exp(p[3] / radius) if model == "similarity" else 1.0
        cosine, sine = np.cos(angle), np.sin(angle)
        linear = scale * np.array([[cosine, -sine], [sine, cosine]])
    return _about_point(linear, centre, p[:2])


def similarity_about_centres(
    moving_centre: np.ndarray, fixed_centre: np.ndarray, scale: float, angle: float, shift: np.ndarray
) -> np.ndarray:
    """The similarity mapping ``moving_centre`` to ``fixed_centre + shift``, scaled and rotated (radians)."""
    c, s = np.cos(angle), np.sin(angle)
    linear = scale * np.array([[c, -s], [s, c]])
    matrix = np.eye(3)
    matrix[:2, :2] = linear
    matrix[:2, 2] = np.asarray(fixed_centre) + np.asarray(shift) - linear @ np.asarray(moving_centre)
    return matrix


def corner_error(true_matrix: np.ndarray, estimated_matrix: np.ndarray, width: int, height: int) -> float:
    """Mean distance, in fixed-image pixels, between the true and estimated images of the moving image's corners.

    Parameters
    ----------
    true_matrix, estimated_matrix : (3, 3) arrays
        Mappings from moving to fixed pixel coordinates.
    width, height : int
        Moving image size.

    Returns
    -------
    float
        (1/4) sum_k || H_true c_k - H_est c_k || over the four corner pixels c_k.
    """
    corners = image_corners(width, height)
    true = apply_homography(np.asarray(true_matrix, dtype=np.float64), corners)
    estimated = apply_homography(np.asarray(estimated_matrix, dtype=np.float64), corners)
    return float(np.linalg.norm(true - estimated, axis=1).mean())

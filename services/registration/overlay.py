"""Pictures for a person to judge a registration: a fused overlay (as the paper's Figure 12) and a checkerboard.

Both draw in the visible (fixed) image's pixel grid: the infrared image is
warped there with the registration matrix, and pixels the infrared camera
does not see show the visible image alone.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.registration.preprocess import to_uint8


def _warped_moving(
    fixed: np.ndarray, moving: np.ndarray, matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fixed image as uint8, the equalised moving one warped onto its grid, and where the latter is defined."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix)) < 1e-12:
        raise ValueError("The registration matrix must be a finite, invertible 3x3 matrix.")
    fixed8 = to_uint8(fixed)
    size = (fixed8.shape[1], fixed8.shape[0])
    equalised = cv2.equalizeHist(to_uint8(moving))  # a hot part would otherwise leave the rest black
    warped = cv2.warpPerspective(equalised, matrix, size, flags=cv2.INTER_LINEAR)
    coverage = cv2.warpPerspective(np.full(np.shape(moving), 255, np.uint8), matrix, size, flags=cv2.INTER_NEAREST)
    return fixed8, warped, coverage > 0


def fused_overlay(fixed: np.ndarray, moving: np.ndarray, matrix: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Grey blend of the visible image and the registered infrared image, like the paper's Figure 12.

    Parameters
    ----------
    fixed : 2-D array
        Visible image.
    moving : 2-D array
        Infrared image.
    matrix : (3, 3) array
        Registration, infrared pixels to visible pixels.
    alpha : float
        Weight of the infrared image where it is defined.

    Returns
    -------
    uint8 array of the visible image's shape: (1 - alpha) V + alpha IR over the
    infrared footprint, V elsewhere.

    References
    ----------
    .. [1] Paper, section 4, Figure 12.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"The blend weight alpha must be in [0, 1]; got {alpha}.")
    fixed8, warped, covered = _warped_moving(fixed, moving, matrix)
    blend = np.rint((1.0 - alpha) * fixed8 + alpha * warped.astype(np.float64)).astype(np.uint8)
    return np.where(covered, blend, fixed8)


def checkerboard_blend(fixed: np.ndarray, moving: np.ndarray, matrix: np.ndarray, tile: int = 32) -> np.ndarray:
    """Alternate square tiles of the visible and the registered infrared image.

    Edges that continue straight across tile borders show a good registration;
    a step at the borders shows the residual misalignment.

    Parameters
    ----------
    fixed, moving, matrix
        As :func:`fused_overlay`.
    tile : int
        Tile side in visible pixels.

    Returns
    -------
    uint8 array of the visible image's shape.
    """
    if tile < 1:
        raise ValueError(f"The checkerboard tile must be at least 1 pixel; got {tile}.")
    fixed8, warped, covered = _warped_moving(fixed, moving, matrix)
    rows, columns = np.indices(fixed8.shape)
    infrared_tile = ((rows // tile + columns // tile) % 2 == 1) & covered
    return np.where(infrared_tile, warped, fixed8)

"""Which cloud points a thermal camera sees: a z-buffer of the cloud in the thermal view."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

# Nearest-pixel assignment puts points up to 1.5 pixel footprints from a bilinear
# corner's centre, so a tilted surface's depth may differ by that many footprints.
_FOOTPRINTS_PER_SAMPLE = 1.5


def depth_buffer(pixels: np.ndarray, depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest depth of the cloud in each pixel of a view (a z-buffer of point splats).

    Parameters
    ----------
    pixels : (N, 2) array
        Pixel coordinates (u, v) of the points in the view; NaN for points that
        do not project.
    depth : (N,) array
        Depth of each point along the view's optical axis, millimetres.
    width, height : int
        Size of the view in pixels.

    Returns
    -------
    buffer : (height, width) float64 array
        Smallest depth of the points whose nearest pixel centre it is; +inf where
        no point falls. An empty pixel takes the smallest depth of its 3x3
        neighbours, so that gaps between sparse splats do not let hidden points
        show through.

    Notes
    -----
    The classic z-buffer [1]_ with points as one-pixel splats,
    Z(i, j) = min {z_k : round(u_k, v_k) = (i, j)}.

    References
    ----------
    .. [1] E. Catmull, "A Subdivision Algorithm for Computer Display of Curved
       Surfaces", PhD thesis, University of Utah, 1974.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    if pixels.ndim != 2 or pixels.shape[1] != 2 or depth.shape != (pixels.shape[0],):
        raise ValueError(f"pixels must be (N, 2) and depth (N,); got {pixels.shape} and {depth.shape}.")
    column, row, inside = _nearest_pixel(pixels, width, height)
    inside &= depth > 0
    buffer = np.full(height * width, np.inf)
    np.minimum.at(buffer, row[inside] * width + column[inside], depth[inside])
    buffer = buffer.reshape(height, width)
    empty = np.isinf(buffer)
    buffer[empty] = ndimage.minimum_filter(buffer, size=3, mode="nearest")[empty]
    return buffer


def depth_tolerance(
    depth: np.ndarray, focal_px: float, view_angle: np.ndarray, max_view_angle: float, absolute_mm: float
) -> np.ndarray:
    """How much deeper than the z-buffer a point may lie and still count as seen, millimetres.

    Notes
    -----
    A pixel at depth z covers z / f millimetres; on a surface tilted by the view
    angle theta, depth changes by (z / f) tan(theta) across it, so

        tol = absolute + 1.5 (z / f) tan(min(theta, theta_max)),

    with theta_max where the angle is unknown (NaN).
    """
    angle = np.where(np.isfinite(view_angle), np.minimum(view_angle, max_view_angle), max_view_angle)
    return absolute_mm + _FOOTPRINTS_PER_SAMPLE * (depth / focal_px) * np.tan(angle)


def _nearest_pixel(pixels: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer column, row of each point's nearest pixel centre and whether it lies in the view."""
    with np.errstate(invalid="ignore"):
        rounded = np.rint(pixels)
        inside = (
            np.isfinite(rounded).all(axis=1)
            & (rounded[:, 0] >= 0) & (rounded[:, 0] < width)
            & (rounded[:, 1] >= 0) & (rounded[:, 1] < height)
        )
    rounded[~inside] = 0
    return rounded[:, 0].astype(np.intp), rounded[:, 1].astype(np.intp), inside


def seen_mask(
    pixels: np.ndarray, depth: np.ndarray, buffer: np.ndarray, tolerance: np.ndarray
) -> np.ndarray:
    """Points in the view whose depth is within ``tolerance`` of the z-buffer at their nearest pixel."""
    height, width = buffer.shape
    column, row, inside = _nearest_pixel(np.asarray(pixels, dtype=np.float64), width, height)
    return inside & (depth > 0) & (depth <= buffer[row, column] + tolerance)

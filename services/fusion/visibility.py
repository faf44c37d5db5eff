"""Which cloud points a thermal camera sees: a z-buffer of the cloud in the thermal view."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

# Nearest-pixel assignment puts points up to 1.5 pixel footprints from a bilinear
# corner's centre, so a tilted surface's depth may differ by that many footprints.
SAMPLE_FOOTPRINTS = 1.5


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


def depth_gradient(
    points_device: np.ndarray, normals_device: np.ndarray, focal_px: float, max_view_angle: float
) -> np.ndarray:
    """How fast each point's surface recedes in the view: depth change per pixel step, millimetres.

    Parameters
    ----------
    points_device, normals_device : (N, 3) arrays
        Points and unit normals in the device frame; NaN normals are unknown.
    focal_px : float
        Focal length in pixels.
    max_view_angle : float
        Radians; steeper surfaces are taken as seen at this angle (and
        unknown normals as seen at it on the optical axis).

    Notes
    -----
    For the tangent plane n . X = d through a point at depth z, the depth at
    normalised image position r is z(r) = d / (n . r), whose gradient per pixel has
    magnitude

        |grad z| = z^2 sqrt(n_x^2 + n_y^2) / (f |n . X|),

    with |n . X| = |X| cos(theta) for the view angle theta, floored at
    cos(theta_max).
    """
    depth = points_device[:, 2]
    distance = np.linalg.norm(points_device, axis=1)
    along = np.abs(np.einsum("ni,ni->n", normals_device, points_device))
    along = np.maximum(along, distance * np.cos(max_view_angle))
    gradient = depth**2 * np.hypot(normals_device[:, 0], normals_device[:, 1]) / (focal_px * along)
    unknown = ~np.isfinite(gradient)
    gradient[unknown] = depth[unknown] / focal_px * np.tan(max_view_angle)
    return gradient


def depth_tolerance(gradient: np.ndarray, absolute_mm: float, footprints: float = SAMPLE_FOOTPRINTS) -> np.ndarray:
    """How much deeper than the z-buffer a point may lie and still count as seen, millimetres.

    tol = absolute + k |grad z| over ``k`` pixel footprints (see :func:`depth_gradient`).
    """
    return absolute_mm + footprints * gradient


def nearest_depth_around(buffer: np.ndarray, radius_px: int) -> np.ndarray:
    """Smallest z-buffer depth within ``radius_px`` pixels (a square window) of each pixel."""
    return ndimage.minimum_filter(buffer, size=2 * radius_px + 1, mode="nearest")


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

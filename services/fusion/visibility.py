"""Which cloud points a thermal camera sees: a z-buffer of the cloud in the thermal view.

The per-point passes are compiled loops (numba): a scan's cloud has half a million points, and numpy's
whole-array expressions made several temporaries of that size per step (the depth test took 7x as long).
"""

from __future__ import annotations

import numba
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
    index = _nearest_pixel_index(pixels, width, height)
    buffer = np.full(height * width, np.inf)
    _splat_nearest(index, depth, buffer)
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
    gradient = np.empty(len(points_device))
    _depth_gradient(np.ascontiguousarray(points_device, dtype=np.float64),
                    np.ascontiguousarray(normals_device, dtype=np.float64), float(focal_px), float(max_view_angle),
                    gradient)
    return gradient


@numba.njit(cache=True, nogil=True)
def _depth_gradient(points, normals, focal, max_view_angle, out):
    floor, unknown_slope = np.cos(max_view_angle), np.tan(max_view_angle)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        along = abs(normals[i, 0] * x + normals[i, 1] * y + normals[i, 2] * z)
        along = max(along, np.sqrt(x * x + y * y + z * z) * floor)
        gradient = z * z * np.hypot(normals[i, 0], normals[i, 1]) / (focal * along)
        out[i] = gradient if np.isfinite(gradient) and np.isfinite(along) else z / focal * unknown_slope


def depth_tolerance(gradient: np.ndarray, absolute_mm: float, footprints: float = SAMPLE_FOOTPRINTS) -> np.ndarray:
    """How much deeper than the z-buffer a point may lie and still count as seen, millimetres.

    tol = absolute + k |grad z| over ``k`` pixel footprints (see :func:`depth_gradient`).
    """
    return absolute_mm + footprints * gradient


def nearest_depth_around(buffer: np.ndarray, radius_px: int) -> np.ndarray:
    """Smallest z-buffer depth within ``radius_px`` pixels (a square window) of each pixel."""
    return ndimage.minimum_filter(buffer, size=2 * radius_px + 1, mode="nearest")


def seen_mask(
    pixels: np.ndarray, depth: np.ndarray, buffer: np.ndarray, tolerance: np.ndarray
) -> np.ndarray:
    """Points in the view whose depth is within ``tolerance`` of the z-buffer at their nearest pixel."""
    height, width = buffer.shape
    index = _nearest_pixel_index(pixels, width, height)
    seen = np.empty(len(index), dtype=bool)
    _within_tolerance(index, np.ascontiguousarray(depth, dtype=np.float64), np.ascontiguousarray(buffer).ravel(),
                      np.ascontiguousarray(tolerance, dtype=np.float64), seen)
    return seen


def _nearest_pixel_index(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Flat index row * width + column of each point's nearest pixel centre; -1 outside the view (or NaN)."""
    index = np.empty(len(pixels), dtype=np.intp)
    _nearest_pixels(np.ascontiguousarray(pixels, dtype=np.float64), width, height, index)
    return index


@numba.njit(cache=True, nogil=True)
def _nearest_pixels(pixels, width, height, out):
    for i in range(pixels.shape[0]):
        column, row = np.rint(pixels[i, 0]), np.rint(pixels[i, 1])
        inside = column >= 0 and column < width and row >= 0 and row < height  # False for NaN
        out[i] = int(row) * width + int(column) if inside else -1


@numba.njit(cache=True, nogil=True)
def _splat_nearest(index, depth, buffer):
    for i in range(index.shape[0]):
        if index[i] >= 0 and depth[i] > 0 and depth[i] < buffer[index[i]]:
            buffer[index[i]] = depth[i]


@numba.njit(cache=True, nogil=True)
def _within_tolerance(index, depth, buffer, tolerance, out):
    for i in range(index.shape[0]):
        out[i] = index[i] >= 0 and depth[i] > 0 and depth[i] <= buffer[index[i]] + tolerance[i]

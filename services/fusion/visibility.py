"""Which cloud points a thermal camera sees: a z-buffer of the cloud in the thermal view.

The per-point passes are numpy expressions that :mod:`services.fusion.fuse` runs on chunks of about 65k
points (see ``POINT_CHUNK``), so that their temporaries stay in the CPU cache; the window minima are
OpenCV erosions.
"""

from __future__ import annotations

import cv2
import numpy as np

# Nearest-pixel assignment puts points up to 1.5 pixel footprints from a bilinear
# corner's centre, so a tilted surface's depth may differ by that many footprints.
SAMPLE_FOOTPRINTS = 1.5


def splat_nearest(buffer: np.ndarray, index: np.ndarray, depth: np.ndarray) -> None:
    """Lower the flat ``buffer`` to each point's depth at its pixel ``index`` (-1: outside; depth <= 0 or NaN:
    not drawn), in place: a z-buffer of point splats, +inf where no point falls (``buffer``'s start).

    Notes
    -----
    The classic z-buffer [1]_ with points as one-pixel splats,
    Z(i, j) = min {z_k : round(u_k, v_k) = (i, j)}; :func:`fill_empty_pixels` then gives each empty pixel the
    smallest depth of its 3x3 neighbours, so that gaps between sparse splats do not let hidden points show
    through.

    References
    ----------
    .. [1] E. Catmull, "A Subdivision Algorithm for Computer Display of Curved
       Surfaces", PhD thesis, University of Utah, 1974.
    """
    drawn = (index >= 0) & (depth > 0)
    np.minimum.at(buffer, index[drawn], depth[drawn])


def fill_empty_pixels(buffer: np.ndarray) -> np.ndarray:
    """``buffer`` with each empty (+inf) pixel given the smallest depth of its 3x3 neighbours, in place."""
    empty = np.isinf(buffer)
    buffer[empty] = nearest_depth_around(buffer, 1)[empty]
    return buffer


TAIL_SIGMAS = 2.5
"""How far the optics' blur reaches, in sigmas: a Gaussian puts 0.6 % of its weight beyond 2.5 sigma
(one side), which on a 1000 degC part beside a cold background moves a long-wave reading by about 5 K,
half the calibration term of the uncertainty budget."""


def footprint_radius(blur_sigma_px: float, stencil_px: float = 1.0) -> int:
    """Half-width (pixels, a square window about a point's nearest pixel) of the scene area whose radiance
    reaches the point's temperature sample.

    The sample mixes pixels up to ``stencil_px`` from the nearest one (1 for the bilinear stencil, 0
    for the nearest pixel alone), each integrates its own area (half a pixel more) and the optics'
    Gaussian blur spreads radiance over ``TAIL_SIGMAS`` sigma more: r = ceil(stencil + 0.5 + 2.5 sigma).
    """
    if not blur_sigma_px >= 0:
        raise ValueError(f"The thermal blur must be a non-negative number of pixels; got {blur_sigma_px}.")
    return int(np.ceil(stencil_px + 0.5 + TAIL_SIGMAS * blur_sigma_px - 1e-9))


def background_depth(buffer: np.ndarray, radius_px: int, depth_step_mm: float = 2.0) -> np.ndarray:
    """Largest z-buffer depth within ``radius_px`` pixels (a square window) of each pixel; +inf where the
    window reaches a pixel on which no surface of the cloud lies.

    ``buffer`` is the raw z-buffer (+inf where no point fell). Gaps in a surface narrower than the window
    add nothing to the maximum: empty pixels between the splats of a cloud sparser than the view, and
    pixels where a farther surface shows through such a gap (the far side of a merged all-round cloud seen
    between the near side's splats) by more than ``depth_step_mm``. Empty pixels outside the cloud's outline
    stay +inf, so that a window over a silhouette sees the empty space (or the farther surface) behind it,
    and so do pixels beyond the image's edge.

    Notes
    -----
    The gaps are what a grey-level opening [1]_ of the depth by the window removes, o = dilate(erode(Z)):
    depth peaks (farther or empty pixels) narrower than the window. A pixel with Z > o + depth_step is a
    gap and takes o; the result is the window maximum of that. For empty gaps alone this is the binary
    closing of the occupied pixels.

    References
    ----------
    .. [1] J. Serra, "Image Analysis and Mathematical Morphology", Academic Press, 1982.
    """
    size = 2 * int(radius_px) + 1
    square = np.ones((size, size), np.uint8)
    depth = np.ascontiguousarray(buffer, dtype=np.float64)
    # beyond the image's edge is empty (+inf) for both steps: a strip of background there is no gap
    opened = cv2.dilate(cv2.erode(depth, square, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf), square,
                        borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    with np.errstate(invalid="ignore"):  # inf - inf: an empty pixel in empty space stays as it is
        gap = depth > opened + depth_step_mm
    filled = np.where(gap, opened, depth)
    # a window maximum (OpenCV's dilation); beyond the image is unknown, so +inf (what a pixel at the image's
    # edge mixes in from outside it is not in the image)
    return cv2.dilate(filled, square, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)


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
    points_device = np.asarray(points_device, dtype=np.float64)
    normals_device = np.asarray(normals_device, dtype=np.float64)
    x, y, z = points_device[:, 0], points_device[:, 1], points_device[:, 2]
    nx, ny, nz = normals_device[:, 0], normals_device[:, 1], normals_device[:, 2]
    along = nx * x
    along += ny * y
    along += nz * z
    np.abs(along, out=along)
    reach = x * x
    reach += y * y
    reach += z * z
    np.sqrt(reach, out=reach)
    reach *= np.cos(max_view_angle)
    np.maximum(along, reach, out=along)  # NaN stays NaN (unknown normal)
    slope = nx * nx
    slope += ny * ny
    gradient = z * z
    gradient *= np.sqrt(slope, out=slope)
    along *= focal_px
    with np.errstate(invalid="ignore", divide="ignore"):
        gradient /= along
    unknown = ~np.isfinite(gradient)  # an unknown normal, or a point at the centre (along = 0)
    unknown |= ~np.isfinite(along)
    if unknown.any():
        gradient[unknown] = z[unknown] / focal_px * np.tan(max_view_angle)
    return gradient


def depth_tolerance(gradient: np.ndarray, absolute_mm: float, footprints: float = SAMPLE_FOOTPRINTS) -> np.ndarray:
    """How much deeper than the z-buffer a point may lie and still count as seen, millimetres.

    tol = absolute + k |grad z| over ``k`` pixel footprints (see :func:`depth_gradient`).
    """
    return absolute_mm + footprints * gradient


def nearest_depth_around(buffer: np.ndarray, radius_px: int) -> np.ndarray:
    """Smallest z-buffer depth within ``radius_px`` pixels (a square window) of each pixel."""
    size = 2 * int(radius_px) + 1
    # replicated borders add no new values to a window minimum: scipy.ndimage's mode="nearest"
    return cv2.erode(np.ascontiguousarray(buffer), np.ones((size, size), np.uint8), borderType=cv2.BORDER_REPLICATE)


def within_tolerance(index: np.ndarray, depth: np.ndarray, buffer: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """Points at flat pixel ``index`` (-1: outside) with 0 < depth <= buffer + tolerance there."""
    limit = buffer[np.maximum(index, 0)]
    limit += tolerance
    seen = depth <= limit  # False for NaN
    seen &= depth > 0
    seen &= index >= 0
    return seen


def nearest_pixel_index(u: np.ndarray, v: np.ndarray, width: int, height: int) -> np.ndarray:
    """Flat index row * width + column of the pixel centres nearest (u, v); -1 outside the view (or NaN)."""
    column, row = np.rint(u), np.rint(v)
    inside = (column >= 0) & (column < width) & (row >= 0) & (row < height)  # False for NaN
    row *= width
    row += column
    return np.where(inside, row, -1.0).astype(np.intp)

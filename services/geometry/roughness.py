"""Roughness of an organised point map: each point's distance from the plane fitted to its neighbourhood."""

from __future__ import annotations

import cv2
import numpy as np


def local_roughness(points: np.ndarray, window: int = 7) -> np.ndarray:
    """Each point's depth residual from the least-squares plane through its pixel neighbourhood.

    Parameters
    ----------
    points : (H, W, 3) float array
        An organised point map (camera pixel -> world or camera point, mm), NaN where there is no point.
    window : int
        Odd side of the square pixel neighbourhood.

    Returns
    -------
    residual : (H, W) float64 array
        z - (a + b u + c v) with (a, b, c) the least-squares fit of z over the points of the window centred
        on the pixel, evaluated at the pixel; NaN where the pixel has no point or fewer than half of the
        window's pixels have one.

    Raises
    ------
    ValueError
        If ``points`` is not an (H, W, 3) map or ``window`` is not an odd number of at least 3.

    Notes
    -----
    The fit's normal equations are built from box sums of the moments (1, u, v, uu, uv, vv, z, uz, vz)
    over the window, taken about each pixel so that they stay well conditioned; the RMS of the residuals
    over a surface smooth on the window's scale is its measurement noise (the surface's curvature adds
    ~ k w^2 / 24 for curvature k over a window w wide).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points must be an (H, W, 3) point map; got shape {points.shape}.")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd number of pixels, at least 3; got {window}.")
    z = points[..., 2]
    height, width = z.shape
    have = np.isfinite(z).astype(np.float64)
    zz = np.where(have > 0, z, 0.0)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)

    def box(image: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(image, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n, su, sv = box(have), box(have * u), box(have * v)
    suu, svv, suv = box(have * u * u), box(have * v * v), box(have * u * v)
    sz, suz, svz = box(zz), box(zz * u), box(zz * v)
    su_c, sv_c = su - n * u, sv - n * v  # moments about the window's centre pixel
    suu_c = suu - 2 * u * su + n * u * u
    svv_c = svv - 2 * v * sv + n * v * v
    suv_c = suv - u * sv - v * su + n * u * v
    suz_c, svz_c = suz - u * sz, svz - v * sz
    enough = (n >= window * window / 2) & (have > 0)
    system = np.stack([np.stack([n, su_c, sv_c], -1), np.stack([su_c, suu_c, suv_c], -1),
                       np.stack([sv_c, suv_c, svv_c], -1)], -2)[enough]
    rhs = np.stack([sz, suz_c, svz_c], -1)[enough]
    out = np.full(z.shape, np.nan)
    out[enough] = z[enough] - np.linalg.solve(system, rhs[..., None])[:, 0, 0]
    return out

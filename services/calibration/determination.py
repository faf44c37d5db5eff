"""Which intrinsics a calibration's views leave poorly determined, said in words with what to add."""

from __future__ import annotations

import numpy as np

from services.calibration.camera import CameraCalibration

Z90 = 1.6448536269514722
"""Half width of the two-sided 90 % interval in standard deviations."""
FOCAL_LIMIT = 0.005
"""A focal length whose 90 % interval is wider than +-0.5 % of it is poorly determined."""
PRINCIPAL_POINT_LIMIT = 0.01
"""A principal point coordinate whose 90 % interval is wider than +-1 % of the image width is poorly determined."""
DISTORTION_LIMIT = 0.01
"""A lens whose displacement at the image corner has a 90 % interval wider than +-1 % of the image width is poorly
determined."""
MIN_TILT_DEG = 10.0  # a board turned less than this about an image axis in every view is not tilted about it


def poorly_determined(calibration: CameraCalibration) -> list[str]:
    """One sentence per group of intrinsics the views do not pin down, each saying which views to add.

    Parameters
    ----------
    calibration : CameraCalibration
        A result of ``calibrate_camera`` (its ``std`` and ``correlation``, and the views' poses).

    Returns
    -------
    list of str
        Empty when every parameter's 90 % interval is within its limit.

    Notes
    -----
    Decided from the calibration's own uncertainty, never from a truth: a parameter is poorly determined
    when the half width of its 90 % interval, ``1.645 sigma``, exceeds ``FOCAL_LIMIT`` of f,
    ``PRINCIPAL_POINT_LIMIT`` of the image width for c_x or c_y, or, for the lens, ``DISTORTION_LIMIT`` of the
    image width for the radial
    displacement ``f (k1 r^3 + k2 r^5 + k3 r^7)`` at the image corner farthest from the principal point,
    whose variance is ``g^T Sigma g`` with ``g = f (r^3, r^5, r^7)`` and ``Sigma`` the coefficients'
    covariance (standard deviations and jackknife correlations). The limits were set on the tuning cameras
    of ``experiments/calibration_random.py`` (seeds 0-11 and 1000-1005) and OpenCV's 13 sample views, whose
    image corners hold no feature (the lens there is extrapolated, and said so). The advice follows the geometry of
    Zhang's method [1]_: the principal point along an axis is fixed by views tilted about the other axis,
    the focal length by strong tilts, the distortion by features near the image corners.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 1330-1334, 2000.
    """
    std, K = calibration.std, calibration.K
    messages = []
    focal = max(std.get("fx", 0.0) / K[0, 0], std.get("fy", 0.0) / K[1, 1])
    if Z90 * focal > FOCAL_LIMIT:
        messages.append(f"focal length poorly determined (+-{100 * Z90 * focal:.2f} % at 90 %): add views tilted "
                        "30 to 45 degrees, at several distances")
    principal = max(std.get("cx", 0.0), std.get("cy", 0.0))
    width = calibration.image_size[0]
    if Z90 * principal > PRINCIPAL_POINT_LIMIT * width:
        messages.append(f"principal point poorly determined (+-{Z90 * std['cx']:.2f} px in x, "
                        f"+-{Z90 * std['cy']:.2f} px in y at 90 %): {_tilt_advice(calibration.rotations)}")
    lens = _corner_displacement_std(calibration)
    if Z90 * lens > DISTORTION_LIMIT * width:
        messages.append(f"distortion poorly determined (+-{Z90 * lens:.2f} px at the image corners at 90 %): "
                        "add views with the board near the image corners")
    return messages


def _tilt_advice(rotations: np.ndarray) -> str:
    """Which tilts the views lack: the board normal's x component is the tilt about the image's vertical axis."""
    normals = np.asarray(rotations)[:, :, 2]
    limit = np.sin(np.radians(MIN_TILT_DEG))
    about_vertical = np.max(np.abs(normals[:, 0])) >= limit
    about_horizontal = np.max(np.abs(normals[:, 1])) >= limit
    if about_vertical and not about_horizontal:
        return "add views tilted about the horizontal axis (top or bottom edge away)"
    if about_horizontal and not about_vertical:
        return "add views tilted about the vertical axis (left or right edge away)"
    return "add views tilted about both axes"


def _corner_displacement_std(calibration: CameraCalibration) -> float:
    """Standard deviation (px) of the radial lens displacement at the image corner farthest from c."""
    names = [name for name in ("k1", "k2", "k3") if name in calibration.std]
    if not names:
        return 0.0
    K = calibration.K
    width, height = calibration.image_size
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], float)
    r = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1])))
    powers = {"k1": 3, "k2": 5, "k3": 7}
    gradient = K[0, 0] * np.array([r ** powers[name] for name in names])
    sigmas = np.array([calibration.std[name] for name in names])
    order = list(calibration.std)
    if calibration.correlation is not None:
        index = [order.index(name) for name in names]
        correlation = calibration.correlation[np.ix_(index, index)]
    else:
        correlation = np.eye(len(names))
    covariance = correlation * np.outer(sigmas, sigmas)
    return float(np.sqrt(max(gradient @ covariance @ gradient, 0.0)))

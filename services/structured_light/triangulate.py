"""Triangulation of camera rays against decoded projector coordinates, honouring lens distortion."""

from __future__ import annotations

import numba
import numpy as np

from services.geometry.camera import normalized_coordinates, pixel_grid
from services.geometry.distortion import distorted_pixel, opencv_distortion_terms

_NEWTON_ITERATIONS = 12
_NEWTON_TOLERANCE_PX = 1e-5  # a hundredth of the decoding noise
_AXES = {"x": 0, "y": 1}


def camera_ray_table(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    """Undistorted normalised coordinates of every pixel centre, computed once per calibration.

    Returns
    -------
    table : (height, width, 2) float32 array
        (x/z, y/z) of the viewing ray through each pixel, in the device frame. float32 keeps a
        1280x800 table at 8 MB; its rounding moves a point at 500 mm by about 0.03 micrometres.
    """
    table = normalized_coordinates(pixel_grid(width, height), K, dist).reshape(height, width, 2)
    return table.astype(np.float32)


# Hand-written with numba because each point needs a few Newton steps of the full OpenCV distortion
# model; cv2.projectPoints per step costs about 10x more on a million points.
@numba.njit(cache=True, inline="always")
def _project_coordinate(X, Y, Z, fx, fy, cx, cy, k, tilt, axis):
    u, v = distorted_pixel(X / Z, Y / Z, fx, fy, cx, cy, k, tilt)
    return u if axis == 0 else v


@numba.njit(parallel=True, cache=True)
def _triangulate_kernel(rays, coordinates, origin, rotation, camera_to_world, centre_world,
                        fx, fy, cx, cy, k, tilt, axis, out):
    focal = fx if axis == 0 else fy
    centre = cx if axis == 0 else cy
    for i in numba.prange(rays.shape[0]):
        # ray direction in the projector frame
        dx = rotation[0, 0] * rays[i, 0] + rotation[0, 1] * rays[i, 1] + rotation[0, 2]
        dy = rotation[1, 0] * rays[i, 0] + rotation[1, 1] * rays[i, 1] + rotation[1, 2]
        dz = rotation[2, 0] * rays[i, 0] + rotation[2, 1] * rays[i, 1] + rotation[2, 2]
        d_axis = dx if axis == 0 else dy
        o_axis = origin[0] if axis == 0 else origin[1]
        target = coordinates[i]
        # start on the undistorted projector plane through the coded line
        n = (target - centre) / focal
        denominator = d_axis - n * dz
        s = np.nan
        if denominator != 0.0:
            s = (n * origin[2] - o_axis) / denominator
        for _ in range(_NEWTON_ITERATIONS):
            if not (s > 0.0):
                break
            Z = origin[2] + s * dz
            if Z <= 0.0:
                s = np.nan
                break
            A = o_axis + s * d_axis
            f = _project_coordinate(origin[0] + s * dx, origin[1] + s * dy, Z, fx, fy, cx, cy, k, tilt, axis) - target
            # quasi-Newton: the slope of the undistorted projection, which differs from the true slope
            # by the (small) distortion, so each step still gains a factor of about 1 / distortion
            slope = focal * (d_axis * Z - A * dz) / (Z * Z)
            if slope == 0.0:
                s = np.nan
                break
            s -= f / slope
            if abs(f) < _NEWTON_TOLERANCE_PX:
                break
        for j in range(3):
            out[i, j] = centre_world[j] + s * (
                camera_to_world[j, 0] * rays[i, 0] + camera_to_world[j, 1] * rays[i, 1] + camera_to_world[j, 2]
            )


def triangulate(
    camera_rays: np.ndarray,
    projector_coordinates: np.ndarray,
    axis: str,
    camera_R: np.ndarray,
    camera_t: np.ndarray,
    projector_K: np.ndarray,
    projector_dist: np.ndarray,
    projector_R: np.ndarray,
    projector_t: np.ndarray,
) -> np.ndarray:
    """Intersect camera rays with the projector's coded lines.

    Parameters
    ----------
    camera_rays : (N, 2) array
        Undistorted normalised camera coordinates (x/z, y/z) of each point's pixel, e.g. rows of
        :func:`camera_ray_table`.
    projector_coordinates : (N,) array
        Decoded projector column (``axis="x"``) or row (``axis="y"``) in distorted projector pixels.
    axis : {"x", "y"}
        Which projector coordinate was coded.
    camera_R, camera_t : arrays
        Camera pose, world to camera.
    projector_K, projector_dist, projector_R, projector_t : arrays
        Projector intrinsics, OpenCV distortion (any valid length) and pose, world to projector.

    Returns
    -------
    points : (N, 3) float32 array
        World points in millimetres; NaN where the ray does not meet the coded line in front of both
        devices.

    Notes
    -----
    A point on the camera ray is X(s) = C + s R_c^T [x, y, 1]^T. With projector distortion the set of
    projector rays that share one coded column is a curved surface, not a plane, so the ray parameter
    solves u_p(R_p X(s) + t_p) = u (the full OpenCV projection of the projector) by a quasi-Newton
    iteration whose slope is that of the undistorted projection, started from the undistorted plane
    x_p - n z_p = 0 with n = (u - c_x) / f_x. This is the
    projector-as-inverse-camera model of structured light [1]_, and replaces the linear plane
    intersection of the paper's two-step method, which ignores lens distortion.

    References
    ----------
    .. [1] S. Zhang and P. S. Huang, "Novel method for structured light system calibration",
       Optical Engineering 45(8), 2006.
    """
    if axis not in _AXES:
        raise ValueError(f"The coded axis must be 'x' or 'y'; got {axis!r}.")
    camera_rays = np.ascontiguousarray(camera_rays)
    projector_coordinates = np.ascontiguousarray(projector_coordinates).ravel()
    if camera_rays.dtype not in (np.float32, np.float64) or projector_coordinates.dtype not in (np.float32, np.float64):
        raise ValueError("camera_rays and projector_coordinates must be float32 or float64 arrays.")
    if camera_rays.ndim != 2 or camera_rays.shape[1] != 2:
        raise ValueError(f"camera_rays must have shape (N, 2); got {camera_rays.shape}.")
    if projector_coordinates.shape[0] != camera_rays.shape[0]:
        raise ValueError(
            f"There are {camera_rays.shape[0]} camera rays but {projector_coordinates.shape[0]} projector coordinates."
        )
    camera_R = np.asarray(camera_R, dtype=np.float64)
    projector_R = np.asarray(projector_R, dtype=np.float64)
    camera_centre = -camera_R.T @ np.asarray(camera_t, dtype=np.float64).ravel()
    origin = projector_R @ camera_centre + np.asarray(projector_t, dtype=np.float64).ravel()
    rotation = projector_R @ camera_R.T
    terms, tilt = opencv_distortion_terms(projector_dist)
    K = np.asarray(projector_K, dtype=np.float64)
    points = np.empty((camera_rays.shape[0], 3), dtype=np.float32)
    _triangulate_kernel(camera_rays, projector_coordinates, origin, np.ascontiguousarray(rotation),
                        np.ascontiguousarray(camera_R.T), camera_centre,
                        K[0, 0], K[1, 1], K[0, 2], K[1, 2], terms, tilt, _AXES[axis],
                        points)
    return points

"""Triangulation of camera rays against decoded projector coordinates, honouring lens distortion.

:func:`triangulate` solves each point exactly; :func:`triangulation_table` and :func:`triangulate_map`
do the same for every pixel of a camera image from a table computed once per calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.geometry.camera import normalized_coordinates, pixel_grid
from services.geometry.camera_model import CameraModel
from services.geometry.distortion import distorted_pixel, opencv_distortion_terms
from services.numba_options import SAFE_FASTMATH

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


@numba.njit(cache=True, inline="always")
def _exact_ray_parameter(dx, dy, dz, coordinate, origin, fx, fy, cx, cy, k, tilt, axis):
    """Ray parameter s where o + s d (projector frame) meets the coded line through the full distortion
    model; NaN if it does not in front of both devices."""
    focal = fx if axis == 0 else fy
    centre = cx if axis == 0 else cy
    d_axis = dx if axis == 0 else dy
    o_axis = origin[0] if axis == 0 else origin[1]
    # start on the undistorted projector plane through the coded line
    n = (coordinate - centre) / focal
    denominator = d_axis - n * dz
    s = np.nan
    if denominator != 0.0:
        s = (n * origin[2] - o_axis) / denominator
    for _ in range(_NEWTON_ITERATIONS):
        if not (s > 0.0):
            return np.nan
        Z = origin[2] + s * dz
        if Z <= 0.0:
            return np.nan
        A = o_axis + s * d_axis
        f = _project_coordinate(origin[0] + s * dx, origin[1] + s * dy, Z, fx, fy, cx, cy, k, tilt, axis) - coordinate
        # quasi-Newton: the slope of the undistorted projection, which differs from the true slope
        # by the (small) distortion, so each step still gains a factor of about 1 / distortion
        slope = focal * (d_axis * Z - A * dz) / (Z * Z)
        if slope == 0.0:
            return np.nan
        s -= f / slope
        if abs(f) < _NEWTON_TOLERANCE_PX:
            break
    return s


@numba.njit(parallel=True, cache=True)
def _triangulate_kernel(rays, coordinates, origin, rotation, camera_to_world, centre_world,
                        fx, fy, cx, cy, k, tilt, axis, out):
    for i in numba.prange(rays.shape[0]):
        x, y = rays[i, 0], rays[i, 1]
        s = _exact_ray_parameter(rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2],
                                 rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2],
                                 rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2],
                                 coordinates[i], origin, fx, fy, cx, cy, k, tilt, axis)
        for j in range(3):
            out[i, j] = centre_world[j] + s * (camera_to_world[j, 0] * x + camera_to_world[j, 1] * y
                                               + camera_to_world[j, 2])


def _geometry(camera_R, camera_t, projector_R, projector_t):
    """Camera centre (world), camera centre in the projector frame, camera-to-projector and
    camera-to-world rotations."""
    camera_R = np.asarray(camera_R, dtype=np.float64)
    projector_R = np.asarray(projector_R, dtype=np.float64)
    centre = -camera_R.T @ np.asarray(camera_t, dtype=np.float64).ravel()
    origin = projector_R @ centre + np.asarray(projector_t, dtype=np.float64).ravel()
    return centre, origin, np.ascontiguousarray(projector_R @ camera_R.T), np.ascontiguousarray(camera_R.T)


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
    centre, origin, rotation, camera_to_world = _geometry(camera_R, camera_t, projector_R, projector_t)
    terms, tilt = opencv_distortion_terms(projector_dist)
    K = np.asarray(projector_K, dtype=np.float64)
    points = np.empty((camera_rays.shape[0], 3), dtype=np.float32)
    _triangulate_kernel(camera_rays, projector_coordinates, origin, rotation, camera_to_world, centre,
                        K[0, 0], K[1, 1], K[0, 2], K[1, 2], terms, tilt, _AXES[axis], points)
    return points


_LINE_NODES = 256  # epipolar lines sampled across the camera's view; the cell check guards the accuracy
_LINE_SOLVER_ITERATIONS = 30
_LINE_SOLVER_TOLERANCE_PX = 1e-9
_TABLE_TOLERANCE_PX = 1e-4  # cells interpolating worse than this are solved exactly instead
# per-pixel geometry channels: epipolar line position, undistorted normalised camera coordinates
_LINE, _RAY_X, _RAY_Y = range(3)


@dataclass(frozen=True)
class TriangulationTable:
    """What triangulating the pixels of one camera against one projector axis needs, per calibration.

    Attributes
    ----------
    axis : {"x", "y"}
        The coded projector axis.
    pixel_geometry : (H, W, 3) float32 array
        Per camera pixel: the fractional index of its epipolar line in ``line_offsets`` (NaN when the
        line runs along the coded axis) and its viewing ray (x/z, y/z) (:func:`camera_ray_table`).
    line_offsets : (size + 2, Q) float32 array
        Undistorted minus pinhole normalised coded coordinate, at coded coordinates -1, 0, ..., size
        and at Q epipolar lines (see :func:`triangulation_table`).
    exact_cells : (size + 1, Q - 1) bool array
        Cells where bilinear interpolation of ``line_offsets`` is not accurate enough (strong
        distortion, or lines that barely cross the coded axis); their pixels are solved exactly.
    origin : (3,) array
        Camera centre in the projector frame.
    rotation, camera_to_world : (3, 3) arrays
        Camera to projector and camera to world rotations.
    centre_world : (3,) array
        Camera centre in the world.
    projector_K, distortion_terms, tilt : arrays
        The projector's model, for the exactly solved pixels.
    """

    axis: str
    pixel_geometry: np.ndarray
    line_offsets: np.ndarray
    exact_cells: np.ndarray
    origin: np.ndarray
    rotation: np.ndarray
    camera_to_world: np.ndarray
    centre_world: np.ndarray
    projector_K: np.ndarray
    distortion_terms: np.ndarray
    tilt: np.ndarray


def _reference_coordinate(origin: np.ndarray, axis: int) -> float:
    """Normalised coded coordinate at which epipolar lines are told apart: 0, or 2 away from the epipole
    when the epipole (the camera seen by the projector) lies within 45 degrees of the projector's axis."""
    if abs(origin[axis]) >= abs(origin[2]):
        return 0.0
    epipole = origin[axis] / origin[2]
    return epipole - 2.0 if epipole >= 0 else epipole + 2.0


# Hand-written with numba: no library inverts OpenCV's distortion along an epipolar line or triangulates
# against such a table, and per-pixel numpy would need a dozen full-image temporaries.
@numba.njit(cache=True, inline="always")
def _line_intercept(d_x, d_y, d_z, o_x, o_y, o_z, reference, axis):
    """Other normalised coordinate at which the epipolar line of the ray o + s d (projector frame) crosses
    coded coordinate ``reference``: the line is l = o x d in homogeneous coordinates."""
    l_x = o_y * d_z - o_z * d_y
    l_y = o_z * d_x - o_x * d_z
    l_w = o_x * d_y - o_y * d_x
    l_coded, l_other = (l_x, l_y) if axis == 0 else (l_y, l_x)
    return -(l_coded * reference + l_w) / l_other if l_other != 0.0 else np.nan


@numba.njit(parallel=True, cache=True)
def _line_intercepts_kernel(rays, origin, rotation, reference, axis, out):
    for i in numba.prange(rays.shape[0]):
        x, y = np.float64(rays[i, 0]), np.float64(rays[i, 1])
        d_x = rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2]
        d_y = rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2]
        d_z = rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2]
        out[i] = _line_intercept(d_x, d_y, d_z, origin[0], origin[1], origin[2], reference, axis)


@numba.njit(cache=True, inline="always")
def _coded_pixel_on_line(n, slope, intercept, fx, fy, cx, cy, k, tilt, axis):
    other = intercept + slope * n
    if axis == 0:
        return distorted_pixel(n, other, fx, fy, cx, cy, k, tilt)[0]
    return distorted_pixel(other, n, fx, fy, cx, cy, k, tilt)[1]


@numba.njit(cache=True)
def _line_offset(coordinate, intercept, reference, origin, fx, fy, cx, cy, k, tilt, axis):
    """Undistorted minus pinhole normalised coded coordinate of the point of one epipolar line that the
    projector shows at ``coordinate``, by Newton's method; NaN if it does not converge."""
    o_coded, o_other = (origin[0], origin[1]) if axis == 0 else (origin[1], origin[0])
    towards_epipole = o_coded - reference * origin[2]
    if towards_epipole == 0.0:
        return np.nan
    pinhole = (coordinate - (cx if axis == 0 else cy)) / (fx if axis == 0 else fy)
    # the line through (reference, intercept) and the epipole: other = intercept + slope * (n - reference)
    slope = (o_other - intercept * origin[2]) / towards_epipole
    base = intercept - slope * reference
    n, step = pinhole, 1e-7
    for _ in range(_LINE_SOLVER_ITERATIONS):
        f = _coded_pixel_on_line(n, slope, base, fx, fy, cx, cy, k, tilt, axis) - coordinate
        if abs(f) < _LINE_SOLVER_TOLERANCE_PX:
            return n - pinhole
        derivative = (_coded_pixel_on_line(n + step, slope, base, fx, fy, cx, cy, k, tilt, axis)
                      - _coded_pixel_on_line(n - step, slope, base, fx, fy, cx, cy, k, tilt, axis)) / (2 * step)
        if not derivative != 0.0:
            return np.nan
        n -= f / derivative
    return np.nan


@numba.njit(parallel=True, cache=True)
def _line_offsets_kernel(first_line, line_step, reference, origin, fx, fy, cx, cy, k, tilt, axis, offsets,
                         exact_cells):
    for c in numba.prange(offsets.shape[0]):
        for q in range(offsets.shape[1]):
            offsets[c, q] = _line_offset(c - 1.0, first_line + q * line_step, reference, origin, fx, fy, cx, cy, k,
                                         tilt, axis)
    tolerance = _TABLE_TOLERANCE_PX / (fx if axis == 0 else fy)
    for c in numba.prange(exact_cells.shape[0]):
        for q in range(exact_cells.shape[1]):
            # bilinear interpolation of a smooth function errs most at the centre or the edge midpoints
            centre = _line_offset(c - 0.5, first_line + (q + 0.5) * line_step, reference, origin, fx, fy, cx, cy,
                                  k, tilt, axis)
            along_c = _line_offset(c - 0.5, first_line + q * line_step, reference, origin, fx, fy, cx, cy, k,
                                   tilt, axis)
            along_q = _line_offset(c - 1.0, first_line + (q + 0.5) * line_step, reference, origin, fx, fy, cx, cy,
                                   k, tilt, axis)
            error = max(abs(0.25 * (offsets[c, q] + offsets[c, q + 1] + offsets[c + 1, q] + offsets[c + 1, q + 1])
                            - centre),
                        abs(0.5 * (offsets[c, q] + offsets[c + 1, q]) - along_c),
                        abs(0.5 * (offsets[c, q] + offsets[c, q + 1]) - along_q))
            exact_cells[c, q] = not error <= tolerance


def triangulation_table(camera: CameraModel, projector: CameraModel, axis: str) -> TriangulationTable:
    """Precompute, once per calibration, the triangulation of every camera pixel against a coded axis.

    Parameters
    ----------
    camera, projector : CameraModel
        The calibrated camera and projector (intrinsics, OpenCV distortion, world-to-device pose).
    axis : {"x", "y"}
        The coded projector axis.

    Returns
    -------
    TriangulationTable
        For :func:`triangulate_map`: 12 bytes per camera pixel (12 MB at 1280x800) and 5 kB per
        projector pixel along the coded axis.

    Notes
    -----
    The viewing ray o + s d of a camera pixel (in the projector frame) projects onto a straight
    epipolar line of the projector's undistorted normalised image, and all these lines pass through the
    epipole o, so one number names a line: where it crosses a reference coded coordinate (0, or 2 away
    from the epipole when that is within 45 degrees of the projector's axis), from the line
    l = o x d. Along a line the distorted coded coordinate c is a smooth function of the undistorted one
    n; its inverse n(c, line) is tabulated at every projector pixel and at 256 lines spanning the
    camera's view, as an offset from the pinhole value (c - c_0) / f. A pixel then needs a bilinear
    lookup and the pinhole intersection s = (n o_z - o_n) / (d_n - n d_z) [1]_ instead of iterating
    the distortion model. Cells whose interpolation misses the exact solution at their centre or edge
    midpoints by more than 1e-4 projector pixels are marked, and their pixels solved as
    :func:`triangulate` does.

    References
    ----------
    .. [1] R. Hartley and A. Zisserman, "Multiple View Geometry in Computer Vision", 2nd ed.,
       Cambridge University Press, 2004, section 9.1 (epipolar geometry).
    """
    if axis not in _AXES:
        raise ValueError(f"The coded axis must be 'x' or 'y'; got {axis!r}.")
    a = _AXES[axis]
    width, height = camera.size
    rays = camera_ray_table(camera.K, camera.dist, width, height).reshape(-1, 2)
    centre, origin, rotation, camera_to_world = _geometry(camera.R, camera.t, projector.R, projector.t)
    reference = _reference_coordinate(origin, a)
    intercepts = np.empty(len(rays))
    _line_intercepts_kernel(rays, origin, rotation, reference, a, intercepts)
    finite = intercepts[np.isfinite(intercepts)]
    if finite.size == 0:
        raise ValueError(f"Every epipolar line runs along projector {axis}, so no pixel can be triangulated "
                         f"against projector {axis} coordinates.")
    step = max(float(finite.max() - finite.min()), 1e-9) / (_LINE_NODES - 3)
    first = float(finite.min()) - step
    geometry = np.empty((height, width, 3), dtype=np.float32)
    geometry[..., _LINE] = ((intercepts - first) / step).reshape(height, width)
    geometry[..., _RAY_X:] = rays.reshape(height, width, 2)
    K = np.array(projector.K)
    terms, tilt = opencv_distortion_terms(projector.dist)
    offsets = np.empty((projector.size[a] + 2, _LINE_NODES), dtype=np.float32)
    exact_cells = np.empty((projector.size[a] + 1, _LINE_NODES - 1), dtype=np.bool_)
    _line_offsets_kernel(first, step, reference, origin, K[0, 0], K[1, 1], K[0, 2], K[1, 2], terms, tilt, a, offsets,
                         exact_cells)
    return TriangulationTable(
        axis=axis, pixel_geometry=geometry, line_offsets=offsets, exact_cells=exact_cells, origin=origin,
        rotation=rotation, camera_to_world=camera_to_world, centre_world=centre, projector_K=K,
        distortion_terms=terms, tilt=tilt,
    )


@numba.njit(cache=True)
def _exactly_solved_ray_parameter(dx, dy, dz, coordinate, origin, fx, fy, cx, cy, k, tilt, axis):
    """:func:`_exact_ray_parameter` as a call, keeping the table loop small."""
    return _exact_ray_parameter(dx, dy, dz, coordinate, origin, fx, fy, cx, cy, k, tilt, axis)


@numba.njit(parallel=True, cache=True, fastmath=SAFE_FASTMATH)
def _triangulate_map_kernel(geometry, coordinates, line_offsets, exact_cells, origin, rotation, camera_to_world,
                            centre_world, fx, fy, cx, cy, k, tilt, axis, out):
    height, width = coordinates.shape
    cells, lines = exact_cells.shape
    inverse_focal = 1.0 / (fx if axis == 0 else fy)
    principal = cx if axis == 0 else cy
    o_axis, o_z = origin[axis], origin[2]
    # scalars, so that the loop does not reload them from arrays that ``out`` might alias
    ra0, ra1, ra2 = rotation[axis, 0], rotation[axis, 1], rotation[axis, 2]
    rz0, rz1, rz2 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    wx0, wx1, wx2 = camera_to_world[0, 0], camera_to_world[0, 1], camera_to_world[0, 2]
    wy0, wy1, wy2 = camera_to_world[1, 0], camera_to_world[1, 1], camera_to_world[1, 2]
    wz0, wz1, wz2 = camera_to_world[2, 0], camera_to_world[2, 1], camera_to_world[2, 2]
    c_x, c_y, c_z = centre_world[0], centre_world[1], centre_world[2]
    for row in numba.prange(height):
        for col in range(width):
            coordinate = coordinates[row, col]
            x, y = np.float64(geometry[row, col, _RAY_X]), np.float64(geometry[row, col, _RAY_Y])
            s = np.nan
            if np.isfinite(coordinate):
                fq = geometry[row, col, _LINE]
                fc = coordinate + 1.0
                if fq >= 0.0 and fq < lines and fc >= 0.0 and fc < cells and not exact_cells[int(fc), int(fq)]:
                    q, c = int(fq), int(fc)
                    wq, wc = fq - q, fc - c
                    offset = ((1.0 - wc) * ((1.0 - wq) * line_offsets[c, q] + wq * line_offsets[c, q + 1])
                              + wc * ((1.0 - wq) * line_offsets[c + 1, q] + wq * line_offsets[c + 1, q + 1]))
                    n = (coordinate - principal) * inverse_focal + offset
                    d_z = rz0 * x + rz1 * y + rz2
                    s = (n * o_z - o_axis) / (ra0 * x + ra1 * y + ra2 - n * d_z)
                    if not (s > 0.0 and o_z + s * d_z > 0.0):
                        s = np.nan
                else:
                    s = _exactly_solved_ray_parameter(
                        rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2],
                        rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2],
                        rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2],
                        coordinate, origin, fx, fy, cx, cy, k, tilt, axis)
            out[row, col, 0] = c_x + s * (wx0 * x + wx1 * y + wx2)
            out[row, col, 1] = c_y + s * (wy0 * x + wy1 * y + wy2)
            out[row, col, 2] = c_z + s * (wz0 * x + wz1 * y + wz2)


def triangulate_map(table: TriangulationTable, coordinates: np.ndarray) -> np.ndarray:
    """Triangulate every camera pixel that has a decoded projector coordinate, as :func:`triangulate`.

    Parameters
    ----------
    table : TriangulationTable
        From :func:`triangulation_table` for this camera, projector and coded axis.
    coordinates : (H, W) float32 array
        Decoded projector coordinate per camera pixel, NaN where there is none.

    Returns
    -------
    points_map : (H, W, 3) float32 array
        World points in millimetres per camera pixel; NaN where there is no coordinate or the ray does
        not meet the coded surface in front of both devices.
    """
    if coordinates.shape != table.pixel_geometry.shape[:2]:
        raise ValueError(f"The coordinate map is {coordinates.shape[1]}x{coordinates.shape[0]} but the "
                         f"triangulation table is for a {table.pixel_geometry.shape[1]}x"
                         f"{table.pixel_geometry.shape[0]} camera.")
    K = table.projector_K
    points_map = np.empty((*coordinates.shape, 3), dtype=np.float32)
    _triangulate_map_kernel(table.pixel_geometry, np.ascontiguousarray(coordinates, dtype=np.float32),
                            table.line_offsets, table.exact_cells, table.origin, table.rotation,
                            table.camera_to_world, table.centre_world,
                            K[0, 0], K[1, 1], K[0, 2], K[1, 2], table.distortion_terms, table.tilt,
                            _AXES[table.axis], points_map)
    return points_map

"""Triangulation of camera rays against decoded projector coordinates, honouring lens distortion.

:func:`triangulate` solves each point exactly; :func:`triangulation_table` and :func:`triangulate_map`
do the same for every pixel of a camera image from a table computed once per calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import normalized_coordinates, pixel_grid
from services.geometry.camera_model import CameraModel
from services.geometry.distortion import distorted_pixels, opencv_distortion_terms
from services.geometry.rigid import rigid_transform
from services.structured_light.row_bands import map_row_bands

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


def _coded_pixel(X, Y, Z, K, terms, tilt, axis):
    """Distorted projector coordinate along ``axis`` of points in the projector frame."""
    u, v = distorted_pixels(X / Z, Y / Z, K, terms, tilt)
    return u if axis == 0 else v


def _exact_ray_parameters(d, coordinates, origin, K, terms, tilt, axis):
    """Ray parameters s where o + s d (projector frame, one ray per row of ``d``) meet their coded lines
    through the full distortion model; NaN where they do not in front of both devices.

    Quasi-Newton on whole arrays: each step works on the rays not yet converged or given up.
    """
    focal, centre = K[axis, axis], K[axis, 2]
    d_axis, d_z = d[:, axis], d[:, 2]
    o_axis, o_z = origin[axis], origin[2]
    coordinates = coordinates.astype(np.float64)
    # start on the undistorted projector plane through the coded line
    n = (coordinates - centre) / focal
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n * o_z - o_axis) / (d_axis - n * d_z)
        active = np.flatnonzero(np.isfinite(s))
        s[~np.isfinite(s)] = np.nan
        for _ in range(_NEWTON_ITERATIONS):
            if active.size == 0:
                break
            si, da, dz = s[active], d_axis[active], d_z[active]
            Z = o_z + si * dz
            A = o_axis + si * da
            f = _coded_pixel(origin[0] + si * d[active, 0], origin[1] + si * d[active, 1], Z, K, terms, tilt,
                             axis) - coordinates[active]
            # quasi-Newton: the slope of the undistorted projection, which differs from the true slope by
            # the (small) distortion, so each step still gains a factor of about 1 / distortion
            slope = focal * (da * Z - A * dz) / (Z * Z)
            behind = ~(si > 0.0) | ~(Z > 0.0) | (slope == 0.0)
            s[active] = np.where(behind, np.nan, si - f / slope)
            active = active[~behind & ~(np.abs(f) < _NEWTON_TOLERANCE_PX)]
    return s


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
    rays = np.column_stack([camera_rays.astype(np.float64), np.ones(len(camera_rays))])
    s = _exact_ray_parameters(rigid_transform(rays, rotation, np.zeros(3)), projector_coordinates, origin,
                              np.asarray(projector_K, np.float64), terms, tilt, _AXES[axis])
    return (centre + s[:, None] * rigid_transform(rays, camera_to_world, np.zeros(3))).astype(np.float32)


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


def _line_intercepts(rays, origin, rotation, reference, axis):
    """Other normalised coordinate at which the epipolar line of each ray o + s d (projector frame)
    crosses coded coordinate ``reference``: the line is l = o x d in homogeneous coordinates."""
    d = cv2.transform(rays.astype(np.float64).reshape(-1, 1, 2), rotation).reshape(-1, 3)  # rotation @ (x, y, 1)
    line = np.cross(origin, d)
    l_coded, l_other = (line[:, 0], line[:, 1]) if axis == 0 else (line[:, 1], line[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(l_other != 0.0, -(l_coded * reference + line[:, 2]) / l_other, np.nan)


def _coded_pixel_on_line(n, slope, base, K, terms, tilt, axis):
    other = base + slope * n
    if axis == 0:
        return distorted_pixels(n, other, K, terms, tilt)[0]
    return distorted_pixels(other, n, K, terms, tilt)[1]


def _line_offsets(coordinates, intercepts, reference, origin, K, terms, tilt, axis):
    """Undistorted minus pinhole normalised coded coordinate of the points of epipolar lines (named by
    ``intercepts``) that the projector shows at ``coordinates`` (arrays broadcast together), by Newton's
    method on whole arrays; NaN where it does not converge."""
    o_coded, o_other = (origin[0], origin[1]) if axis == 0 else (origin[1], origin[0])
    towards_epipole = o_coded - reference * origin[2]
    coordinates, intercepts = np.broadcast_arrays(np.asarray(coordinates, np.float64),
                                                  np.asarray(intercepts, np.float64))
    offsets = np.full(coordinates.shape, np.nan)
    if towards_epipole == 0.0:
        return offsets
    pinhole = ((coordinates - K[axis, 2]) / K[axis, axis]).ravel()
    # the line through (reference, intercept) and the epipole: other = intercept + slope * (n - reference)
    slope = ((o_other - intercepts * origin[2]) / towards_epipole).ravel()
    base = intercepts.ravel() - slope * reference
    target = coordinates.ravel()
    n, step = pinhole.copy(), 1e-7
    active = np.arange(n.size)
    result = offsets.reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(_LINE_SOLVER_ITERATIONS):
            if active.size == 0:
                break
            ni, si, bi = n[active], slope[active], base[active]
            f = _coded_pixel_on_line(ni, si, bi, K, terms, tilt, axis) - target[active]
            converged = np.abs(f) < _LINE_SOLVER_TOLERANCE_PX
            result[active[converged]] = ni[converged] - pinhole[active[converged]]
            derivative = (_coded_pixel_on_line(ni + step, si, bi, K, terms, tilt, axis)
                          - _coded_pixel_on_line(ni - step, si, bi, K, terms, tilt, axis)) / (2 * step)
            going = ~converged & (derivative != 0.0) & np.isfinite(derivative)
            n[active] = ni - f / derivative
            active = active[going]
    return offsets


def _exact_cells(offsets, first_line, line_step, reference, origin, K, terms, tilt, axis):
    """Cells where bilinear interpolation of ``offsets`` misses the exact offset at the cell's centre or
    edge midpoints (where a smooth function's bilinear interpolation errs most) by more than the
    tolerance, or any of these is NaN."""
    cells, lines = offsets.shape[0] - 1, offsets.shape[1] - 1
    c = np.arange(cells)[:, None] - 1.0
    q = first_line + np.arange(lines)[None, :] * line_step
    centre = _line_offsets(c + 0.5, q + 0.5 * line_step, reference, origin, K, terms, tilt, axis)
    along_c = _line_offsets(c + 0.5, q, reference, origin, K, terms, tilt, axis)
    along_q = _line_offsets(c, q + 0.5 * line_step, reference, origin, K, terms, tilt, axis)
    o = offsets.astype(np.float64)
    error = np.maximum.reduce([np.abs(0.25 * (o[:-1, :-1] + o[:-1, 1:] + o[1:, :-1] + o[1:, 1:]) - centre),
                               np.abs(0.5 * (o[:-1, :-1] + o[1:, :-1]) - along_c),
                               np.abs(0.5 * (o[:-1, :-1] + o[:-1, 1:]) - along_q)])
    return ~(error <= _TABLE_TOLERANCE_PX / K[axis, axis])


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
    intercepts = _line_intercepts(rays, origin, rotation, reference, a)
    finite = intercepts[np.isfinite(intercepts)]
    if finite.size == 0:
        raise ValueError(f"Every epipolar line runs along projector {axis}, so no pixel can be triangulated "
                         f"against projector {axis} coordinates.")
    step = max(float(finite.max() - finite.min()), 1e-9) / (_LINE_NODES - 3)
    first = float(finite.min()) - step
    geometry = np.empty((height, width, 3), dtype=np.float32)
    geometry[..., _LINE] = ((intercepts - first) / step).reshape(height, width)
    geometry[..., _RAY_X:] = rays.reshape(height, width, 2)
    K = np.array(projector.K, dtype=np.float64)
    terms, tilt = opencv_distortion_terms(projector.dist)
    coded = np.arange(-1, projector.size[a] + 1)[:, None]
    lines = first + np.arange(_LINE_NODES)[None, :] * step
    offsets = _line_offsets(coded, lines, reference, origin, K, terms, tilt, a).astype(np.float32)
    exact_cells = _exact_cells(offsets, first, step, reference, origin, K, terms, tilt, a)
    return TriangulationTable(
        axis=axis, pixel_geometry=geometry, line_offsets=offsets, exact_cells=exact_cells, origin=origin,
        rotation=rotation, camera_to_world=camera_to_world, centre_world=centre, projector_K=K,
        distortion_terms=terms, tilt=tilt,
    )


def _cell_corners(table: TriangulationTable) -> np.ndarray:
    """The four ``line_offsets`` of each table cell, (c, q), (c, q + 1), (c + 1, q), (c + 1, q + 1), as one
    row per cell so that a pixel's bilinear lookup is one gather; NaN for the cells to solve exactly, and a
    last row of NaN for the pixels outside the table."""
    corners = _CELL_CORNERS.get(id(table))
    if corners is None or corners[0] is not table:
        offsets = table.line_offsets
        rows = np.stack([offsets[:-1, :-1], offsets[:-1, 1:], offsets[1:, :-1], offsets[1:, 1:]], axis=-1)
        rows[table.exact_cells] = np.nan
        corners = (table, np.concatenate([rows.reshape(-1, 4), np.full((1, 4), np.nan, np.float32)]))
        _CELL_CORNERS.clear()  # one calibration at a time: a process rarely triangulates against two
        _CELL_CORNERS[id(table)] = corners
    return corners[1]


_CELL_CORNERS: dict[int, tuple[TriangulationTable, np.ndarray]] = {}


def _affine(pixel: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """(3, 4) ``matrix`` @ (line, x, y, 1) of each ``pixel_geometry`` row, by OpenCV, in the dtype of ``pixel``
    (see :func:`~services.geometry.rigid.rigid_transform` for why not numpy's matmul; OpenCV's three-row
    transform is also twenty times faster than its two-row one)."""
    return cv2.transform(pixel.reshape(-1, 1, 3), matrix).reshape(len(pixel), -1)


def _ray_parameters(table: TriangulationTable, corners: np.ndarray, coordinate: np.ndarray,
                    pixel: np.ndarray) -> np.ndarray:
    """Ray parameters of decoded pixels (``coordinate`` and their ``pixel_geometry`` rows) by the table
    (and its :func:`_cell_corners`): the bilinear lookup of the (small) offset in float32, the rest in
    float64."""
    axis = _AXES[table.axis]
    cells, lines = table.exact_cells.shape
    fq = pixel[:, _LINE].astype(np.float32)
    with np.errstate(invalid="ignore"):
        q, c = fq.astype(np.int32), (coordinate + np.float32(1.0)).astype(np.int32)
        inside = (fq >= 0.0) & (fq < lines) & (coordinate >= -1.0) & (coordinate < cells - 1)  # False where NaN
    corner = np.take(corners, np.where(inside, c * lines + q, cells * lines), axis=0)
    # both differences are exact in float32 (Sterbenz), so the lookup adds no rounding to the coordinate
    wq, wc = fq - q, coordinate - (c - 1)
    top = corner[:, 0] + wq * (corner[:, 1] - corner[:, 0])
    bottom = corner[:, 2] + wq * (corner[:, 3] - corner[:, 2])
    n = (coordinate.astype(np.float64) - table.projector_K[axis, 2]) / table.projector_K[axis, axis]
    n += top + wc * (bottom - top)
    d = _affine(pixel, np.column_stack([np.zeros(3), table.rotation]))  # the ray in the projector frame
    d_axis, d_z = d[:, axis], d[:, 2]
    o = table.origin
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n * o[2] - o[axis]) / (d_axis - n * d_z)
        s[~((s > 0.0) & (o[2] + s * d_z > 0.0))] = np.nan
    exact = np.flatnonzero(np.isnan(n))
    if exact.size:  # outside the table or where it interpolates too coarsely: the exact solver
        s[exact] = _exact_ray_parameters(d[exact], coordinate[exact], o, table.projector_K, table.distortion_terms,
                                         table.tilt, axis)
    return s


def _triangulate_pixels(table: TriangulationTable, corners: np.ndarray, coordinate: np.ndarray,
                        pixel: np.ndarray) -> np.ndarray:
    """(N, 3) float32 world points of decoded pixels, from their coordinates and ``pixel_geometry`` rows
    (computed in float64, then rounded once)."""
    pixel = pixel.astype(np.float64)
    s = _ray_parameters(table, corners, coordinate, pixel)
    to_world = np.zeros((3, 4))
    to_world[:, 1:] = table.camera_to_world
    points = _affine(pixel, to_world)  # the ray direction in the world
    for j in range(3):  # per column: numpy broadcasts over rows of three slowly
        points[:, j] *= s
        points[:, j] += table.centre_world[j]
    return points.astype(np.float32)


_POINT = np.dtype((np.void, 12))  # a float32 point as one item, so that numpy scatters whole points


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
    height, width = coordinates.shape
    coordinates = np.ascontiguousarray(coordinates, dtype=np.float32).reshape(-1)
    geometry = table.pixel_geometry.reshape(-1, 3)
    points_map = np.empty((height * width, 3), dtype=np.float32)
    corners = _cell_corners(table)

    def triangulate_band(rows: slice) -> None:
        band = slice(rows.start * width, rows.stop * width)
        out = points_map[band]
        out.fill(np.nan)
        decoded = np.flatnonzero(np.isfinite(coordinates[band]))
        if decoded.size:
            points = _triangulate_pixels(table, corners, coordinates[band][decoded],
                                         np.take(geometry[band], decoded, axis=0))
            np.put(out.view(_POINT).reshape(-1), decoded, points.view(_POINT))

    map_row_bands(triangulate_band, height, width)
    return points_map.reshape(height, width, 3)

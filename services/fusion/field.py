"""A point cloud plus thermal views to a temperature field (the cloud with temperatures and colours)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from services.geometry.cloud import PointCloud
from services.fusion.carving import Witness, restore_consistent, unseen_space
from services.fusion.colormap import DEFAULT_COLORMAP, temperature_colors
from services.fusion.fuse import DEFAULT_MAX_VIEW_ANGLE_DEG, Rows, ThermalView, fuse_rows, rows_of
from services.fusion.normals import estimate_normals, normals_at

FIELD_PROPERTIES = ("temperature", "view_angle", "red", "green", "blue")


def cloud_normals(cloud: PointCloud, viewpoint: np.ndarray) -> np.ndarray:
    """The cloud's ``nx, ny, nz`` where given and finite, else estimated by PCA facing ``viewpoint``."""
    if all(name in cloud for name in ("nx", "ny", "nz")):
        normals = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]]).astype(np.float64)
        missing = np.flatnonzero(_missing_normals(cloud))
        if len(missing):
            normals[missing] = _estimated_normals(cloud, missing, viewpoint)
        return normals
    return estimate_normals(cloud.points, viewpoint)


def _coordinates(cloud: PointCloud) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return cloud["x"], cloud["y"], cloud["z"]


def _missing_normals(cloud: PointCloud) -> np.ndarray:
    """Points without a finite normal."""
    return ~(np.isfinite(cloud["nx"]) & np.isfinite(cloud["ny"]) & np.isfinite(cloud["nz"]))


def _estimated_normals(cloud: PointCloud, index: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """PCA normals of the points ``index`` (NaN for non-finite points), neighbours from the whole cloud."""
    columns = _coordinates(cloud)
    finite = np.isfinite(columns[0]) & np.isfinite(columns[1]) & np.isfinite(columns[2])
    estimated = np.full((len(index), 3), np.nan)
    wanted = finite[index]
    if wanted.any():
        estimated[wanted] = normals_at(columns, index[wanted], viewpoint, finite=finite)
    return estimated


def _stacked_rows(columns: tuple[np.ndarray, ...], rows: slice) -> np.ndarray:
    out = np.empty((len(columns[0][rows]), 3))
    for axis, column in enumerate(columns):
        out[:, axis] = column[rows]
    return out


def _cloud_rows(cloud: PointCloud, viewpoint: np.ndarray) -> tuple[Rows, Rows]:
    """Chunk readers (see :func:`services.fusion.fuse.fuse_rows`) of the cloud's points and of
    :func:`cloud_normals`, which stack the chunk's columns rather than the whole cloud's."""
    columns = _coordinates(cloud)
    if not all(name in cloud for name in ("nx", "ny", "nz")):
        return (lambda rows: _stacked_rows(columns, rows)), rows_of(estimate_normals(cloud.points, viewpoint))
    normal_columns = (cloud["nx"], cloud["ny"], cloud["nz"])
    missing = np.flatnonzero(_missing_normals(cloud))
    estimated = _estimated_normals(cloud, missing, viewpoint)

    def normals_of(rows: slice) -> np.ndarray:
        normals = _stacked_rows(normal_columns, rows)
        first, last = np.searchsorted(missing, [rows.start, rows.stop])
        normals[missing[first:last] - rows.start] = estimated[first:last]
        return normals

    return (lambda rows: _stacked_rows(columns, rows)), normals_of


def temperature_field(
    cloud: PointCloud | Mapping[str, np.ndarray],
    views: Sequence[ThermalView],
    viewpoint: np.ndarray,
    max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
    colormap: str = DEFAULT_COLORMAP,
    witnesses: Sequence[Witness] = (),
) -> PointCloud:
    """The cloud's properties plus ``temperature``, ``view_angle`` and perceptual ``red, green, blue``.

    Parameters
    ----------
    cloud : PointCloud or mapping of 1-D arrays
        At least ``x, y, z`` (world mm); ``nx, ny, nz`` are used when present.
    views : sequence of ThermalView
        Calibrated thermal cameras and their frames in degrees C.
    viewpoint : (3,) array
        Where the cloud was measured from (the camera centre), to orient
        estimated normals.
    max_view_angle_deg : float
        View-angle limit, see :func:`services.fusion.fuse.fuse_temperature`.
    colormap : str
        Colour map for the RGB properties (see :func:`services.fusion.colormap.colormap_lut`).
    witnesses : sequence of Witness
        The cameras (and projectors) that measured the cloud, with their rows:
        a point whose thermal ray passes through space none of them saw free
        keeps its reading only where the readings on its smooth surface vouch
        for it (:func:`services.fusion.carving.restore_consistent`). Empty: the
        cloud's own points are the only occluders.

    Returns
    -------
    field : PointCloud
        The input properties (existing temperature/colour properties replaced)
        and float32 ``temperature`` (degrees C, NaN unseen), float32
        ``view_angle`` (degrees), uint8 ``red, green, blue``.
    """
    if not isinstance(cloud, PointCloud):
        cloud = PointCloud(dict(cloud))
    absent = [name for name in ("x", "y", "z") if name not in cloud]
    if absent:
        raise ValueError(f"The cloud lacks the coordinate properties {absent}.")
    points_of, normals_of = _cloud_rows(cloud, viewpoint)
    unseen = None
    if witnesses:
        # the witnesses' images at about two pixels per thermal pixel: cameras finer than that add work alone
        ratio = min(witness.camera.K[0, 0] / view.device.K[0, 0] for witness in witnesses for view in views)
        unseen = unseen_space(np.column_stack(_coordinates(cloud)), witnesses, factor=max(1, round(ratio / 2)))
    fused = fuse_rows(len(cloud), points_of, normals_of, views, max_view_angle_deg, unseen=unseen)
    temperature = fused.temperature
    if unseen is not None:
        temperature = restore_consistent(fused.unguarded, temperature, unseen).astype(np.float32)
    rgb = temperature_colors(temperature, name=colormap)
    return cloud.without(*FIELD_PROPERTIES).with_properties(
        temperature=temperature, view_angle=fused.view_angle, red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])

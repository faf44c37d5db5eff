"""A point cloud plus thermal views to a temperature field (the cloud with temperatures and colours)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from services.geometry.cloud import PointCloud
from services.fusion.colormap import DEFAULT_COLORMAP, temperature_colors
from services.fusion.fuse import DEFAULT_MAX_VIEW_ANGLE_DEG, ThermalView, fuse_temperature
from services.fusion.normals import estimate_normals

FIELD_PROPERTIES = ("temperature", "view_angle", "red", "green", "blue")


def cloud_normals(cloud: PointCloud, viewpoint: np.ndarray) -> np.ndarray:
    """The cloud's ``nx, ny, nz`` where given and finite, else estimated by PCA facing ``viewpoint``."""
    points = cloud.points
    if all(name in cloud for name in ("nx", "ny", "nz")):
        normals = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]]).astype(np.float64)
        missing = ~np.isfinite(normals).all(axis=1)
        if missing.any():
            normals[missing] = estimate_normals(points, viewpoint, where=missing)[missing]
        return normals
    return estimate_normals(points, viewpoint)


def temperature_field(
    cloud: PointCloud | Mapping[str, np.ndarray],
    views: Sequence[ThermalView],
    viewpoint: np.ndarray,
    max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
    colormap: str = DEFAULT_COLORMAP,
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
        Matplotlib colour map for the RGB properties.

    Returns
    -------
    field : PointCloud
        The input properties (existing temperature/colour properties replaced)
        and float32 ``temperature`` (degrees C, NaN unseen), float32
        ``view_angle`` (degrees), uint8 ``red, green, blue``.
    """
    if not isinstance(cloud, PointCloud):
        cloud = PointCloud(dict(cloud))
    fused = fuse_temperature(cloud.points, cloud_normals(cloud, viewpoint), views, max_view_angle_deg)
    rgb = temperature_colors(fused.temperature, name=colormap)
    return cloud.without(*FIELD_PROPERTIES).with_properties(
        temperature=fused.temperature, view_angle=fused.view_angle, red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])

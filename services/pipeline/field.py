"""Use cases: a cloud plus thermal frames to a temperature field, and a capture straight to a field."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.errors import InputError
from services.formats.rig import Rig
from services.fusion.carving import Witness
from services.fusion.field import temperature_field
from services.fusion.fuse import DEFAULT_MAX_VIEW_ANGLE_DEG, ThermalView
from services.geometry.cloud import PointCloud

ThermalFrames = Sequence[tuple[str | None, np.ndarray]]
"""Thermal frames in degrees Celsius, each (h, w) or (F, h, w), with the rig's thermal device that took them
(None: the rig's only thermal camera)."""


def thermal_views(rig: Rig, thermal: ThermalFrames) -> list[ThermalView]:
    """The frames grouped into one view per thermal device of the rig; sizes are checked against it."""
    grouped: dict[str, list[np.ndarray]] = {}
    for name, frames in thermal:
        device_name, device = rig.device(name, "thermal")
        frames = np.asarray(frames)
        stack = frames[None] if frames.ndim == 2 else frames
        if stack.ndim != 3 or stack.shape[1:] != (device.height, device.width):
            raise InputError(f"thermal frames of {device_name!r} are of shape {frames.shape} but the rig's "
                             f"{device_name!r} is {device.width}x{device.height}")
        grouped.setdefault(device_name, []).append(stack)
    if not grouped:
        raise InputError("at least one thermal frame is needed to fuse a temperature field")
    return [ThermalView(rig.devices[name], np.concatenate(stacks)) for name, stacks in grouped.items()]


def measuring_viewpoint(rig: Rig, views: Sequence[ThermalView]) -> np.ndarray:
    """Where the cloud was measured from: the rig's only camera's centre, else the first thermal camera's.

    A station's merged cloud was measured from several heads: :func:`station_normals` orients its normals
    toward each point's own head first, so that this viewpoint orients none of them."""
    cameras = [device for device in rig.devices.values() if device.kind == "camera"]
    return (cameras[0] if len(cameras) == 1 else views[0].device).centre


def measuring_cameras(cloud: PointCloud, rig: Rig) -> list[Witness]:
    """The cameras that measured the cloud, each with its rows and the projector that lit them: a merged station
    cloud's heads by its ``head`` property, else the rig's only camera for every point (none when the rig has
    several cameras and the cloud says not which measured what); the cloud's ``u, v`` locate the points in the
    camera's image where it has them."""
    pixels = np.column_stack([cloud["u"], cloud["v"]]) if "u" in cloud and "v" in cloud else None
    if "head" in cloud and len(rig.heads) >= 2:
        head = np.asarray(cloud["head"])
        witnesses = []
        for index, station_head in enumerate(rig.heads):
            rows = np.flatnonzero(head == index)
            witnesses += [Witness(rig.devices[station_head.camera], rows,
                                  pixels=None if pixels is None else pixels[rows]),
                          Witness(rig.devices[station_head.projector], rows, skirts=False)]
        return witnesses
    cameras = [device for device in rig.devices.values() if device.kind == "camera"]
    projectors = [device for device in rig.devices.values() if device.kind == "projector"]
    if len(cameras) != 1:
        return []
    return [Witness(cameras[0], pixels=pixels)] + ([Witness(projectors[0], skirts=False)] if len(projectors) == 1
                                                    else [])


def station_normals(cloud: PointCloud, rig: Rig) -> PointCloud:
    """A merged station cloud (with ``head``, the index in ``rig.heads``) with every normal facing the camera of
    the head that measured the point: given normals kept, missing ones estimated (PCA) from that head's points
    and turned toward its camera. Other clouds are returned as they are."""
    from services.fusion.field import cloud_normals

    if "head" not in cloud or len(rig.heads) < 2:
        return cloud
    head = np.asarray(cloud["head"])
    if len(head) and (head.min() < 0 or head.max() >= len(rig.heads)):
        raise InputError(f"the cloud's head property runs from {head.min()} to {head.max()} but the rig has "
                         f"{len(rig.heads)} heads")
    normals = np.full((len(cloud), 3), np.nan, dtype=np.float32)
    for index, station_head in enumerate(rig.heads):
        rows = np.flatnonzero(head == index)
        if len(rows):
            part = PointCloud({name: np.asarray(values)[rows] for name, values in cloud.items()})
            normals[rows] = cloud_normals(part, rig.devices[station_head.camera].centre)
    return cloud.with_properties(nx=normals[:, 0], ny=normals[:, 1], nz=normals[:, 2])


def fuse_field(*, cloud: PointCloud, rig: Rig, thermal: ThermalFrames,
               max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG, source: str = "the cloud") -> PointCloud:
    """Give every point of ``cloud`` its temperature from the rig's thermal camera(s).

    A station's merged cloud (``head`` property) takes its temperature from every thermal camera that sees a
    point, whichever head measured it; its normals face each point's own head (:func:`station_normals`).

    Returns the field: the cloud with ``temperature`` (degrees C, NaN unseen), ``view_angle`` (degrees)
    and ``red, green, blue`` (see :func:`services.fusion.field.temperature_field`).

    Raises
    ------
    InputError
        When the cloud has no coordinates, a frame does not fit its device or the angle is impossible.
    """
    missing = [name for name in ("x", "y", "z") if name not in cloud]
    if missing:
        raise InputError(f"{source}: the cloud has no {', '.join(missing)} vertex properties")
    if not 0.0 < max_view_angle_deg < 90.0:
        raise InputError(f"the maximum view angle must be in (0, 90) degrees; got {max_view_angle_deg}")
    views = thermal_views(rig, thermal)
    return temperature_field(station_normals(cloud, rig), views, measuring_viewpoint(rig, views), max_view_angle_deg,
                             witnesses=measuring_cameras(cloud, rig))

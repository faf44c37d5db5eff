"""Use cases: a cloud plus thermal frames to a temperature field, and a capture straight to a field."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.errors import InputError
from services.formats.rig import Rig
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
    """Where the cloud was measured from: the rig's only camera's centre, else the first thermal camera's."""
    cameras = [device for device in rig.devices.values() if device.kind == "camera"]
    return (cameras[0] if len(cameras) == 1 else views[0].device).centre


def fuse_field(*, cloud: PointCloud, rig: Rig, thermal: ThermalFrames,
               max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG, source: str = "the cloud") -> PointCloud:
    """Give every point of ``cloud`` its temperature from the rig's thermal camera(s).

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
    return temperature_field(cloud, views, measuring_viewpoint(rig, views), max_view_angle_deg)

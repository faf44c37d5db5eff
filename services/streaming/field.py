"""Logging a 3D temperature field to Rerun: coloured points, temperatures, device frusta, thermal image.

Entity tree (world frame = the rig's world frame, OpenCV axes, millimetres):

- ``world``: view coordinates RDF (x right, y down, z forward), static.
- ``world/field``: ``Points3D`` coloured by temperature, with the per-point
  ``temperature`` (degrees Celsius, NaN unseen) alongside as a component.
- ``world/devices/<name>``: ``Transform3D`` of the device pose; our poses map world
  to device (x_dev = R x_world + t), Rerun's child-from-parent relation.
- ``world/devices/<name>/image``: ``Pinhole`` (K, resolution; lens distortion is
  not drawn), and for the thermal camera the colour-mapped thermal frame.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from services.formats.rig import Rig
from services.fusion.colormap import temperature_colors

FIELD_ENTITY = "world/field"
DEVICES_ENTITY = "world/devices"
_DEVICE_COLORS = {"camera": (80, 160, 255), "projector": (255, 220, 80), "thermal": (255, 90, 60)}


def _temperature_range(*temperatures: np.ndarray) -> tuple[float, float] | None:
    finite = np.concatenate([np.asarray(t, dtype=np.float64).ravel() for t in temperatures])
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return None
    return float(finite.min()), float(finite.max())


def log_rig(recording: rr.RecordingStream, rig: Rig) -> None:
    """Log every device of ``rig`` as a frustum: its pose and its pinhole intrinsics."""
    recording.log("world", rr.ViewCoordinates.RDF, static=True)
    for name, device in rig.devices.items():
        recording.log(
            f"{DEVICES_ENTITY}/{name}",
            rr.Transform3D(translation=device.t_array, mat3x3=device.R_array,
                           relation=rr.TransformRelation.ChildFromParent),
        )
        recording.log(
            f"{DEVICES_ENTITY}/{name}/image",
            rr.Pinhole(image_from_camera=device.K_array, resolution=[device.width, device.height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=100.0,
                       color=_DEVICE_COLORS[device.kind]),
        )


def log_field(
    recording: rr.RecordingStream,
    field: dict[str, np.ndarray],
    rig: Rig,
    thermal_image: np.ndarray | None = None,
    thermal_device: str | None = None,
) -> None:
    """Log one 3D temperature field with the rig and, optionally, the thermal frame it was fused from.

    Parameters
    ----------
    recording : rerun.RecordingStream
        Where to log; the caller sets its timeline (e.g. the scan number).
    field : dict of 1-D arrays
        A field as read from ``field.ply``: ``x, y, z`` (world mm) and
        ``temperature`` (degrees Celsius, NaN where unseen).
    rig : Rig
        The calibration the field was computed with.
    thermal_image : (h, w) float array, optional
        The thermal frame in degrees Celsius.
    thermal_device : str, optional
        The rig's thermal camera that took ``thermal_image``; default its only one.

    Notes
    -----
    Points and thermal image share one colour scale, the perceptual map of
    ``services.fusion.colormap`` from the lowest to the highest temperature seen,
    so a colour means the same temperature in both views.
    """
    missing = [name for name in ("x", "y", "z", "temperature") if name not in field]
    if missing:
        raise ValueError(f"The field lacks the propert{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)}.")
    positions = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float32)
    temperature = np.asarray(field["temperature"], dtype=np.float32)
    scale = _temperature_range(temperature, *(() if thermal_image is None else (thermal_image,)))
    low, high = scale if scale is not None else (None, None)
    log_rig(recording, rig)
    recording.log(
        FIELD_ENTITY,
        rr.Points3D(positions, colors=temperature_colors(temperature, low, high)),
        rr.AnyValues(temperature=temperature),
    )
    if thermal_image is not None:
        name, device = rig.device(thermal_device, "thermal")
        thermal_image = np.asarray(thermal_image, dtype=np.float32)
        if thermal_image.shape != (device.height, device.width):
            raise ValueError(
                f"The thermal image is {thermal_image.shape[1]}x{thermal_image.shape[0]} but rig device {name!r} "
                f"is {device.width}x{device.height}."
            )
        recording.log(f"{DEVICES_ENTITY}/{name}/image", rr.Image(temperature_colors(thermal_image, low, high)))

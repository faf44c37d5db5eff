"""Logging a 3D temperature field to Rerun: coloured points, temperatures, device frusta, thermal image.

Entity tree (world frame = the rig's world frame, OpenCV axes, millimetres):

- ``world``: view coordinates RDF (x right, y down, z forward), static.
- ``world/field``: ``Points3D`` coloured by temperature, with the per-point
  ``temperature`` (degrees Celsius, NaN unseen) alongside as a component.
- ``world/deviation``: the inspected part's points (as measured, beside the field) coloured by their
  deviation from the nominal part (diverging map over the surface tolerance: blue missing material,
  red excess), with the per-point ``deviation`` (mm) alongside; cleared for a scan not inspected.
- ``world/heads/<head>``: a station's heads' clouds, each its own layer (``Points3D`` in the head's colour
  ``HEAD_COLORS``, as the head measured it before the merge); a single-head scan logs none.
- ``verdict``: the inspection's verdict and features as a Markdown ``TextDocument``; cleared for a scan
  not inspected.
- ``world/devices/<name>``: ``Transform3D`` of the device pose; our poses map world
  to device (x_dev = R x_world + t), Rerun's child-from-parent relation.
- ``world/devices/<name>/image``: ``Pinhole`` (K, resolution; lens distortion is
  not drawn), and for the thermal camera the colour-mapped thermal frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import rerun as rr

from services.formats.rig import Rig
from services.fusion.colormap import temperature_colors
from services.geometry.cloud import PointCloud

FIELD_ENTITY = "world/field"
DEVIATION_ENTITY = "world/deviation"
DEVICES_ENTITY = "world/devices"
VERDICT_ENTITY = "verdict"
HEADS_ENTITY = "world/heads"
HEAD_COLORS = ((230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180), (70, 240, 240),
               (240, 50, 230), (210, 245, 60))
"""Each head's layer colour, by its index in the rig's heads (repeating after eight)."""
_DEVICE_COLORS = {"camera": (80, 160, 255), "projector": (255, 220, 80), "thermal": (255, 90, 60)}


def _rig_entities(rig: Rig) -> list[tuple[str, tuple]]:
    """Every device of ``rig`` as a frustum: its pose and its pinhole intrinsics."""
    entities = []
    for name, device in rig.devices.items():
        entities.append((f"{DEVICES_ENTITY}/{name}", (
            rr.Transform3D(translation=device.t, mat3x3=device.R, relation=rr.TransformRelation.ChildFromParent),)))
        entities.append((f"{DEVICES_ENTITY}/{name}/image", (
            rr.Pinhole(image_from_camera=device.K, resolution=[device.width, device.height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=100.0,
                       color=_DEVICE_COLORS[device.kind]),)))
    return entities


@dataclass(frozen=True)
class FieldScene:
    """What a viewer shows of one field: ``(entity path, archetypes)`` in log order, built once per field and
    logged to any number of recordings (the scan's ``.rrd`` and the station's live view)."""

    entities: tuple[tuple[str, tuple], ...]


def field_scene(
    field: PointCloud | Mapping[str, np.ndarray],
    rig: Rig,
    thermal_image: np.ndarray | None = None,
    thermal_device: str | None = None,
    deviation: Mapping[str, np.ndarray] | None = None,
    verdict: str | None = None,
    heads: Mapping[str, PointCloud | Mapping[str, np.ndarray]] | None = None,
) -> FieldScene:
    """The field with the rig's device frusta and, optionally, the thermal frame it was fused from.

    Parameters
    ----------
    field : PointCloud or mapping of 1-D arrays
        A field as :func:`services.fusion.field.temperature_field` makes it or ``field.ply`` holds it:
        ``x, y, z`` (world mm), ``temperature`` (degrees Celsius, NaN where unseen) and, when present,
        its colours ``red, green, blue``.
    rig : Rig
        The calibration the field was computed with.
    thermal_image : (h, w) float array, optional
        The thermal frame in degrees Celsius.
    thermal_device : str, optional
        The rig's thermal camera that took ``thermal_image``; default its only one.
    deviation : mapping of 1-D arrays, optional
        The inspection's deviation cloud (``services.pipeline.inspect.InspectionOutcome.deviation``): the
        field's points with ``deviation`` (mm, NaN off the part) and its colours ``red, green, blue``.
    verdict : str, optional
        The inspection's verdict as Markdown (:func:`verdict_markdown`).
    heads : mapping of head name to cloud, optional
        A station's heads' clouds (``x, y, z``), each logged as its own layer ``world/heads/<head>``.

    Notes
    -----
    The points keep the field's own colours (the perceptual map of ``services.fusion.colormap`` from the
    field's lowest to its highest temperature), computed once by the fusion; the thermal image is mapped
    on the same scale, so a colour means the same temperature in both views.
    """
    missing = [name for name in ("x", "y", "z", "temperature") if name not in field]
    if missing:
        raise ValueError(f"The field lacks the propert{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)}.")
    positions = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float32)
    temperature = np.asarray(field["temperature"], dtype=np.float32)
    seen = temperature[np.isfinite(temperature)]
    low, high = (float(seen.min()), float(seen.max())) if seen.size else (None, None)
    if all(name in field for name in ("red", "green", "blue")):
        colours = np.column_stack([field["red"], field["green"], field["blue"]]).astype(np.uint8)
    else:
        colours = temperature_colors(temperature, low, high)
    entities = [*_rig_entities(rig),
                (FIELD_ENTITY, (rr.Points3D(positions, colors=colours), rr.AnyValues(temperature=temperature))),
                (DEVIATION_ENTITY, _deviation_layer(deviation)),
                (VERDICT_ENTITY, (rr.Clear(recursive=False),) if verdict is None else
                 (rr.TextDocument(verdict, media_type=rr.MediaType.MARKDOWN),))]
    for index, (head, cloud) in enumerate((heads or {}).items()):
        points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float32)
        entities.append((f"{HEADS_ENTITY}/{head}", (rr.Points3D(points, colors=HEAD_COLORS[index % len(HEAD_COLORS)]),)))
    if thermal_image is not None:
        name, device = rig.device(thermal_device, "thermal")
        thermal_image = np.asarray(thermal_image, dtype=np.float32)
        if thermal_image.shape != (device.height, device.width):
            raise ValueError(
                f"The thermal image is {thermal_image.shape[1]}x{thermal_image.shape[0]} but rig device {name!r} "
                f"is {device.width}x{device.height}."
            )
        entities.append((f"{DEVICES_ENTITY}/{name}/image", (rr.Image(temperature_colors(thermal_image, low, high)),)))
    return FieldScene(tuple(entities))


def verdict_markdown(report: Mapping) -> str:
    """An inspection report (docs/inspection.md) as a short Markdown page: the verdict, then one table row per
    feature and the surface, the verdict first (a narrow panel still shows it)."""
    lines = [f"# {report.get('part', 'part')}: {report['verdict']}", "",
             "| feature | verdict | deviation | U (k=2) | cold | nominal |", "|---|---|---|---|---|---|"]
    for feature in report.get("features", []):
        if feature.get("deviation") is None:
            lines.append(f"| {feature['name']} | {feature['verdict']} | | | | |")
            continue
        lines.append(f"| {feature['name']} | {feature['verdict']} | {feature['deviation']:+.3f} | "
                     f"{feature['uncertainty']:.3f} | {feature['cold']:.3f} | {feature['nominal']:.3f} |")
    surface = report.get("surface")
    if surface and surface.get("cell_min") is not None:
        lines.append(f"| surface | {surface['verdict']} | {surface['cell_min']:+.3f}..{surface['cell_max']:+.3f} | "
                     f"{surface['uncertainty']:.3f} | | |")
    return "\n".join(lines) + "\n"


def _deviation_layer(deviation: Mapping[str, np.ndarray] | None) -> tuple:
    """The part's points coloured by deviation, or a clear (a scan without inspection must not keep showing
    the previous part's map in the live view)."""
    if deviation is None:
        return (rr.Clear(recursive=False),)
    values = np.asarray(deviation["deviation"], dtype=np.float32)
    part = np.isfinite(values)
    positions = np.column_stack([deviation["x"], deviation["y"], deviation["z"]]).astype(np.float32)[part]
    colours = np.column_stack([deviation["red"], deviation["green"], deviation["blue"]]).astype(np.uint8)[part]
    return rr.Points3D(positions, colors=colours), rr.AnyValues(deviation=values[part])


def log_field(recording: rr.RecordingStream, scene: FieldScene) -> None:
    """Log a field's scene (see :func:`field_scene`); the caller sets the recording's timeline."""
    recording.log("world", rr.ViewCoordinates.RDF, static=True)
    for path, archetypes in scene.entities:
        recording.log(path, *archetypes)

"""Use cases of a station of several heads: one head's capture to its cloud, and the heads' clouds to one merged
cloud (each callable on its own, so that a worker can reconstruct one head per message and another merge).

The merged cloud is the heads' clouds in the rig's world frame, each head's moved by its pose
refinement on the overlaps (:func:`services.geometry.merge.refine_head_poses`), the overlaps thinned
(:func:`services.geometry.merge.thin_overlaps`), with an int ``head`` property: the index of the head
in ``rig.heads`` that measured the point.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from services.errors import InputError
from services.formats.rig import Rig
from services.formats.sequence import Sequence as Manifest
from services.formats.station_capture import HeadFrames
from services.geometry.cloud import PointCloud
from services.geometry.merge import (PairResidual, PoseCorrection, PoseUncertainty, overlap_residuals,
                                     refine_head_poses, thin_overlaps)
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.tables import TriangulationTables
from services.structured_light import defaults
from services.structured_light.reconstruct import Reconstruction

DEFAULT_POSE_UNCERTAINTY = PoseUncertainty(translation_mm=0.05, rotation_deg=0.01)
"""A head's pose uncertainty when the calibration gives none: the station calibration's target (issue 36)."""
HEAD_PROPERTY = "head"
_THINNING_SPACINGS = 2.5


@dataclass(frozen=True)
class HeadCorrection:
    """The pose refinement of one head: its size (mm, degrees), whether it was applied, and why not."""

    head: str
    translation_mm: float
    rotation_deg: float
    applied: bool
    overlap_points: int
    reason: str = ""


@dataclass(frozen=True)
class OverlapResidual:
    """The residual between two heads' surfaces where they overlap (see ``merge.PairResidual``), mm."""

    first: str
    second: str
    points: int
    rms_mm: float
    patch_rms_mm: float


@dataclass(frozen=True)
class MergeReport:
    """What the merge did: per head the points measured and kept, the pose corrections, and the overlap
    residuals before and after the refinement."""

    heads: tuple[str, ...]
    measured_points: tuple[int, ...]
    kept_points: tuple[int, ...]
    corrections: tuple[HeadCorrection, ...]
    residuals_before: tuple[OverlapResidual, ...]
    residuals: tuple[OverlapResidual, ...]


@dataclass(frozen=True)
class MergedCloud:
    """The station's merged cloud (with ``head``) and the report of the merge."""

    cloud: PointCloud
    report: MergeReport


def reconstruct_head(*, frames: np.ndarray, sequence: Manifest, rig: Rig, head: str, tables: TriangulationTables,
                     saturation_level: float | None = None, max_indirect: float = defaults.MAX_INDIRECT,
                     consistency: float = defaults.CONSISTENCY, source: str | None = None) -> Reconstruction:
    """Decode and triangulate one head's capture with that head's camera and projector
    (:func:`services.pipeline.reconstruct.reconstruct_capture`; its parameters and errors).

    ``head`` names a head of ``rig`` (``rig.heads``; a version-1 rig's one head is ``head``).
    """
    station_head = rig.head(head)
    return reconstruct_capture(frames=frames, sequence=sequence, rig=rig, tables=tables, camera=station_head.camera,
                               projector=station_head.projector, saturation_level=saturation_level,
                               max_indirect=max_indirect, consistency=consistency,
                               source=source or f"the capture of head {head!r}")


def _normals(cloud: PointCloud) -> np.ndarray:
    if not all(name in cloud for name in ("nx", "ny", "nz")):
        return np.full((len(cloud), 3), np.nan)
    return np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]]).astype(np.float64)


def _view_angles(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    towards = centre - points
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", towards, normals), -1.0, 1.0)))


def _named(residuals: list[PairResidual], names: Sequence[str]) -> tuple[OverlapResidual, ...]:
    return tuple(OverlapResidual(names[r.first], names[r.second], r.points, r.rms_mm, r.patch_rms_mm)
                 for r in residuals)


def _spacing(points: np.ndarray) -> float:
    """The median distance from a point to its nearest neighbour (on up to 5000 points)."""
    finite = points[np.isfinite(points).all(axis=1)]
    if len(finite) < 2:
        return 1.0
    sample = finite[:: max(1, len(finite) // 5000)]
    distance, _ = cKDTree(finite).query(sample, k=2)
    return float(np.median(distance[:, 1]))


def merge_heads(*, clouds: Mapping[str, PointCloud], rig: Rig,
                uncertainty: PoseUncertainty | Mapping[str, PoseUncertainty] = DEFAULT_POSE_UNCERTAINTY,
                refine: bool = True, thin: bool = True, voxel_mm: float | None = None) -> MergedCloud:
    """Merge the heads' clouds into one cloud in the world frame.

    Parameters
    ----------
    clouds : mapping of head name to PointCloud
        Every head of ``rig`` (``rig.heads``) and only those, each its reconstruction (world mm, with normals).
    rig : Rig
        The station's calibration.
    uncertainty : PoseUncertainty or mapping of head name to it
        Each head's pose uncertainty from the calibration (one for all, or one per head): the refinement
        stays within it, and a correction beyond 3 of it is refused and reported.
    refine, thin : bool
        Refine the heads' poses on the overlaps; thin the overlaps.
    voxel_mm : float, optional
        The thinning's voxel; default 2.5 times the points' median spacing.

    Returns
    -------
    MergedCloud
        The cloud with the properties all heads' clouds share and int32 ``head`` (the index in ``rig.heads``),
        and the :class:`MergeReport`.

    Raises
    ------
    InputError
        When a head of the rig has no cloud or a cloud names no head of the rig.
    """
    names = [head.name for head in rig.heads]
    missing, unknown = [n for n in names if n not in clouds], [n for n in clouds if n not in names]
    if missing or unknown:
        raise InputError(f"the clouds to merge must be one per head of the rig ({names}); "
                         + "; ".join(filter(None, [f"missing {missing}" if missing else "",
                                                   f"not heads of the rig {unknown}" if unknown else ""])))
    if isinstance(uncertainty, PoseUncertainty):
        uncertainty = {name: uncertainty for name in names}
    ordered = [clouds[name] for name in names]
    points = [cloud.points for cloud in ordered]
    normals = [_normals(cloud) for cloud in ordered]
    before = _named(overlap_residuals(points, normals), names)
    if refine and len(names) > 1:
        corrections = refine_head_poses(points, normals, [uncertainty[name] for name in names])
    else:
        corrections = [PoseCorrection(np.eye(3), np.zeros(3), np.zeros(3), False, 0, "not refined")
                       for _ in names]
    moved = [correction.apply(p, n) for correction, p, n in zip(corrections, points, normals)]
    after = _named(overlap_residuals([m[0] for m in moved], [m[1] for m in moved]), names) if refine else before
    shared = [name for name in ordered[0] if all(name in cloud for cloud in ordered)]
    columns = {name: np.concatenate([cloud[name] for cloud in ordered]) for name in shared}
    all_points = np.concatenate([m[0] for m in moved])
    all_normals = np.concatenate([m[1] for m in moved])
    for axis, name in enumerate(("x", "y", "z")):
        columns[name] = all_points[:, axis].astype(columns[name].dtype)
    if "nx" in columns:
        for axis, name in enumerate(("nx", "ny", "nz")):
            columns[name] = all_normals[:, axis].astype(columns[name].dtype)
    head = np.concatenate([np.full(len(cloud), index, dtype=np.int32) for index, cloud in enumerate(ordered)])
    keep = np.ones(len(head), dtype=bool)
    if thin and len(names) > 1 and len(head):
        angle = np.concatenate([_view_angles(m[0], m[1], rig.devices[h.camera].centre)
                                for m, h in zip(moved, rig.heads)])
        voxel = voxel_mm or _THINNING_SPACINGS * _spacing(points[0])
        keep = thin_overlaps(all_points, head, angle, voxel)
    cloud = PointCloud({name: values[keep] for name, values in columns.items()} | {HEAD_PROPERTY: head[keep]},
                       ordered[0].units)
    report = MergeReport(
        heads=tuple(names), measured_points=tuple(len(c) for c in ordered),
        kept_points=tuple(int(np.count_nonzero(head[keep] == index)) for index in range(len(names))),
        corrections=tuple(HeadCorrection(name, c.translation_mm, c.rotation_deg, c.applied, c.overlap, c.reason)
                          for name, c in zip(names, corrections)),
        residuals_before=before, residuals=after)
    return MergedCloud(cloud, report)


def reconstruct_station(*, heads: Sequence[HeadFrames], rig: Rig, tables: TriangulationTables,
                        saturation_level: float | None = None,
                        uncertainty: PoseUncertainty | Mapping[str, PoseUncertainty] = DEFAULT_POSE_UNCERTAINTY,
                        source: str = "the station capture") -> MergedCloud:
    """Every head's capture reconstructed (:func:`reconstruct_head`, one after another in this process) and
    merged (:func:`merge_heads`): the embedded path; a scaled-out service runs the heads as messages."""
    clouds = {capture.head: reconstruct_head(frames=capture.frames, sequence=capture.sequence, rig=rig,
                                             head=capture.head, tables=tables, saturation_level=saturation_level,
                                             source=f"{source}: head {capture.head!r}").cloud
              for capture in heads}
    return merge_heads(clouds=clouds, rig=rig, uncertainty=uncertainty)

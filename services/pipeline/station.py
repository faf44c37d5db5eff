"""Use cases of a station of several heads: one head's capture to its cloud, and the heads' clouds to one merged
cloud (each callable on its own, so that a worker can reconstruct one head per message and another merge).

The merged cloud is the heads' clouds in the rig's world frame, each head's moved by its pose
refinement on the overlaps (:func:`services.geometry.merge.refine_head_poses`), the overlaps thinned
(:func:`services.geometry.merge.thin_overlaps`), with an int ``head`` property: the index of the head
in ``rig.heads`` that measured the point.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from services.errors import InputError
from services.formats.rig import Rig
from services.formats.sequence import Sequence as Manifest
from services.formats.station_capture import HeadFrames
from services.geometry.cloud import PointCloud
from services.geometry.merge import (OverlapSample, PairResidual, PoseCorrection, PoseUncertainty, overlap_residuals,
                                     overlap_sample, refine_head_poses, thin_overlaps)
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.tables import TriangulationTables
from services.structured_light import defaults
from services.structured_light.reconstruct import Reconstruction

if TYPE_CHECKING:  # the service's stages load the inspection, the store and Rerun on first use, not the commands
    from services.inspection.inspect import PreparedPart
    from services.pipeline.scan import ScanOutcome, StageClock, StoredScan
    from services.storage.artifacts import ArtifactStore
    from services.streaming.field import FieldScene

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
    """Before the refinement; empty when the merge was asked not to measure them."""
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


def merge_heads(*, clouds: Mapping[str, PointCloud], rig: Rig,
                uncertainty: PoseUncertainty | Mapping[str, PoseUncertainty] = DEFAULT_POSE_UNCERTAINTY,
                refine: bool = True, thin: bool = True, voxel_mm: float | None = None,
                residuals_before: bool = True, samples: Mapping[str, OverlapSample] | None = None) -> MergedCloud:
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
    residuals_before : bool
        Also measure the overlaps' residuals before the refinement (``MergeReport.residuals_before``: as
        long as the residual after it; empty when False).
    samples : mapping of head name to OverlapSample, optional
        Each head's :func:`services.geometry.merge.overlap_sample` of its cloud, when made already (the
        service makes it in the head's own message: :func:`scan_head`); made here otherwise.

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
    sampled = [samples[name] if samples is not None and name in samples else overlap_sample(p, n)
               for name, p, n in zip(names, points, normals)]

    def residuals(heads: list[OverlapSample]) -> tuple[OverlapResidual, ...]:
        return _named(overlap_residuals([h.residual_points for h in heads], [h.residual_normals for h in heads],
                                        sampled=True), names)

    before = residuals(sampled) if residuals_before or not refine else ()
    if refine and len(names) > 1:
        corrections = refine_head_poses([h.refine_points for h in sampled], [h.refine_normals for h in sampled],
                                        [uncertainty[name] for name in names], sampled=True)
    else:
        corrections = [PoseCorrection(np.eye(3), np.zeros(3), np.zeros(3), False, 0, "not refined")
                       for _ in names]
    moved = [correction.apply(p, n) for correction, p, n in zip(corrections, points, normals)]
    after = residuals([h.moved(c) for h, c in zip(sampled, corrections)]) if refine else before
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
        voxel = voxel_mm or _THINNING_SPACINGS * sampled[0].spacing_mm
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


# ---------------------------------------------------------------------------------------------------------------
# The station scan in the service: one message per head (scan_head), then one that merges, fuses, inspects and
# stores (scan_merge); embedded and scaled out alike (services/pipeline/jobs.py).


@dataclass(frozen=True)
class HeadScan:
    """One head of a station scan: its cloud (world mm), the seconds its reconstruction took, and the cloud's
    :class:`~services.geometry.merge.OverlapSample` for the merge (None: the merge makes it) and the seconds it
    took; or ``error`` (a device lost in the capture, nothing decoded) and no cloud."""

    head: str
    cloud: PointCloud | None
    seconds: float | None = None
    error: str | None = None
    sample: OverlapSample | None = None
    sample_seconds: float | None = None


def station_capture_artifacts(*, heads: Sequence[HeadFrames], exposures: Mapping[str, dict],
                              thermal: Mapping[str, np.ndarray]) -> dict[str, bytes]:
    """The files of a station scan's capture, known before any processing (the station capture layout's names):
    per head ``heads/<head>/frames.npy``, ``sequence.json`` and ``exposure.json``; per thermal camera
    ``thermal/<device>.npy`` (float32 degrees C)."""
    from services.formats.sequence import sequence_to_json
    from services.formats.stored_scan import exposure_bytes, head_artifact, npy_bytes, thermal_artifact

    files: dict[str, bytes] = {}
    for capture in heads:
        files[head_artifact(capture.head, "frames.npy")] = npy_bytes(capture.frames)
        files[head_artifact(capture.head, "sequence.json")] = sequence_to_json(capture.sequence).encode()
        files[head_artifact(capture.head, "exposure.json")] = exposure_bytes(exposures.get(capture.head))
    for device, frames in thermal.items():
        files[thermal_artifact(device)] = npy_bytes(np.asarray(frames, dtype=np.float32))
    return files


def scan_head(*, frames: np.ndarray, sequence: Manifest, rig: Rig, head: str, tables: TriangulationTables,
              saturation_level: float | None = None) -> HeadScan:
    """One head of a station scan (:func:`reconstruct_head`) and the sample of its cloud the merge works on
    (:func:`services.geometry.merge.overlap_sample`: made here, in the head's own message, the heads' in
    parallel when there are several workers); its failure kept as the head's ``error`` rather than raised: a
    head whose frames decode to nothing (bad frames, a part it does not see) fails the scan's verdict, not the
    job, so that the other heads' results are kept."""
    import time

    started = time.perf_counter()
    try:
        cloud = reconstruct_head(frames=frames, sequence=sequence, rig=rig, head=head, tables=tables,
                                 saturation_level=saturation_level).cloud
    except InputError as error:
        return HeadScan(head, None, round(time.perf_counter() - started, 3), f"head {head!r}: {error}")
    if len(cloud) == 0:
        return HeadScan(head, None, round(time.perf_counter() - started, 3),
                        f"head {head!r}: nothing decoded (no point measured)")
    seconds = round(time.perf_counter() - started, 3)
    started = time.perf_counter()
    sample = overlap_sample(cloud.points, _normals(cloud))
    return HeadScan(head, cloud, seconds, sample=sample, sample_seconds=round(time.perf_counter() - started, 3))


@dataclass(frozen=True)
class StationScanOutcome:
    """A station scan's merged cloud and report (None when a head failed) and the scan's outcome."""

    merged: MergedCloud | None
    outcome: ScanOutcome


def _station_summary(heads: Sequence[HeadScan], merged: MergedCloud | None):
    from services.formats.stored_scan import HeadSummary, OverlapSummary, StationSummary

    report = None if merged is None else merged.report
    summaries = []
    for index, head in enumerate(heads):
        summary = HeadSummary(head=head.head, measured_points=0 if head.cloud is None else len(head.cloud),
                              kept_points=0, reconstruct_seconds=head.seconds, error=head.error)
        if report is not None:
            correction = report.corrections[index]
            summary = summary.model_copy(update={
                "kept_points": report.kept_points[index], "correction_mm": round(correction.translation_mm, 5),
                "correction_deg": round(correction.rotation_deg, 6), "correction_applied": correction.applied,
                "correction_note": correction.reason})
        summaries.append(summary)
    overlaps = [] if report is None else [
        OverlapSummary(first=r.first, second=r.second, points=r.points, rms_mm=round(r.rms_mm, 5),
                       patch_rms_mm=round(r.patch_rms_mm, 5)) for r in report.residuals]
    return StationSummary(heads=summaries, overlaps=overlaps,
                          failed_heads=[head.head for head in heads if head.error is not None])


def process_station_scan(*, heads: Sequence[HeadScan], rig: Rig, thermal: Mapping[str, np.ndarray],
                         part: PreparedPart | None = None, clock: StageClock | None = None,
                         uncertainty: PoseUncertainty | Mapping[str, PoseUncertainty] = DEFAULT_POSE_UNCERTAINTY,
                         ) -> StationScanOutcome:
    """Merge the heads' clouds (:func:`merge_heads`), fuse the field from every thermal camera
    (:func:`services.pipeline.field.fuse_field`), summarise and, given the part type, inspect it all round.

    ``heads`` are every head of ``rig`` in its order. When any head failed (its ``error``), nothing is merged
    and the scan cannot be judged: the outcome has an empty field and ``inspection_error`` naming the heads
    (NotDecidable with a part type), never a verdict from the heads left.
    """
    from services.geometry.cloud import PointCloud as Cloud
    from services.pipeline.scan import ScanOutcome, StageClock, fuse_and_inspect
    from services.pipeline.summary import field_summary

    clock = clock or StageClock()
    names = [head.name for head in rig.heads]
    if [head.head for head in heads] != names:
        raise InputError(f"a station scan needs one result per head of the rig, in its order ({names}); got "
                         f"{[head.head for head in heads]}")
    failed = [head for head in heads if head.error is not None]
    if failed:
        empty = Cloud({name: np.zeros(0, np.float32) for name in ("x", "y", "z", "temperature")})
        reason = ("; ".join(head.error for head in failed)
                  + f": the part is not judged from the other heads ({len(heads) - len(failed)} of {len(heads)})")
        summary = field_summary(empty).model_copy(update={"station": _station_summary(heads, None)})
        return StationScanOutcome(None, ScanOutcome(empty, empty, summary, None, reason))
    clock.start("merge", 0.6)
    merged = merge_heads(clouds={head.head: head.cloud for head in heads}, rig=rig, uncertainty=uncertainty,
                         residuals_before=False,
                         samples={head.head: head.sample for head in heads if head.sample is not None})
    field_, inspection, inspection_error = fuse_and_inspect(
        cloud=merged.cloud, rig=rig, thermal=list(thermal.items()), part=part, clock=clock,
        source="the station scan", fractions=(0.7, 0.75))
    summary = field_summary(field_).model_copy(update={"station": _station_summary(heads, merged)})
    return StationScanOutcome(merged, ScanOutcome(merged.cloud, field_, summary, inspection, inspection_error))


def store_station_scan(*, scan_id: str, heads: Sequence[HeadScan], rig: Rig, thermal: Mapping[str, np.ndarray],
                       store: ArtifactStore, part: PreparedPart | None = None, clock: StageClock | None = None,
                       captured_at: float | None = None,
                       publish: Callable[[FieldScene, float | None], None] | None = None,
                       uncertainty: PoseUncertainty | Mapping[str, PoseUncertainty] = DEFAULT_POSE_UNCERTAINTY,
                       ) -> StoredScan:
    """:func:`process_station_scan` with its files stored and the field streamed: the merged ``cloud.ply``, the
    ``field.ply``, the inspection's files and the Rerun recording ``field.rrd`` (each head's cloud its own layer,
    and the merged field; the scene also given to ``publish``). A scan with a failed head stores no field and
    streams nothing. Returns a :class:`services.pipeline.scan.StoredScan` of the files stored here."""
    from services.formats.stored_scan import RECORDING
    from services.pipeline.scan import StageClock, StoredScan, cloud_artifacts, field_artifacts
    from services.storage.artifacts import ArtifactWriter
    from services.streaming.field import field_scene, verdict_markdown
    from services.streaming.recording import scan_recording

    clock = clock or StageClock()
    with ArtifactWriter(store) as writer:
        result = process_station_scan(heads=heads, rig=rig, thermal=thermal, part=part, clock=clock,
                                      uncertainty=uncertainty)
        outcome = result.outcome
        if result.merged is not None:
            writer.put_made(lambda: {**cloud_artifacts(outcome.cloud), **field_artifacts(outcome)})
            clock.start("stream", 0.8)
            deviation = None if outcome.inspection is None else outcome.inspection.deviation
            verdict = None if outcome.inspection is None else verdict_markdown(outcome.inspection.report)
            device, frames = next(iter(thermal.items()))
            scene = field_scene(outcome.field, rig, np.asarray(frames)[0] if np.ndim(frames) == 3 else frames,
                                thermal_device=device, deviation=deviation, verdict=verdict,
                                heads={head.head: head.cloud for head in heads})
            writer.put({RECORDING.name: scan_recording(scan_id, scene, captured_at)})
            if publish is not None:
                publish(scene, captured_at)
        clock.start("store", 0.9)
        artifacts = writer.digests()
    clock.stop()
    return StoredScan(outcome, artifacts)

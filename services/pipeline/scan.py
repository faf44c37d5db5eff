"""Use case: one scan's captured frames to its cloud, field, summary, inspection (when it has a part type),
stored artifacts and Rerun recording."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.errors import InputError
from services.formats.ply import cloud_to_ply
from services.formats.rig import Rig
from services.formats.sequence import Sequence, sequence_to_json
from services.formats.stored_scan import (CLOUD, EXPOSURE, FIELD, FRAMES, RECORDING, SEQUENCE, THERMAL, FieldSummary,
                                          exposure_bytes, npy_bytes)
from services.geometry.cloud import PointCloud
from services.inspection.inspect import PreparedPart
from services.pipeline.field import ThermalFrames, fuse_field
from services.pipeline.inspect import InspectionOutcome, inspect_part, inspection_artifacts, report_digest
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.summary import field_summary, glow_summary
from services.pipeline.tables import TriangulationTables
from services.storage.artifacts import ArtifactStore, ArtifactWriter
from services.streaming.field import FieldScene, field_scene, verdict_markdown
from services.streaming.recording import scan_recording

Progress = Callable[[str, float], None]
"""Called with a stage's name and the job's fraction done when the stage starts."""


@dataclass
class StageClock:
    """Reports each stage as it starts and keeps the seconds each took."""

    progress: Progress | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    _current: tuple[str, float] | None = None

    def start(self, name: str, fraction: float) -> None:
        self.stop()
        if self.progress is not None:
            self.progress(name, fraction)
        self._current = (name, time.perf_counter())

    def stop(self) -> None:
        if self._current is not None:
            name, started = self._current
            self.seconds[name] = round(time.perf_counter() - started, 3)
            self._current = None


@dataclass(frozen=True)
class ScanOutcome:
    cloud: PointCloud
    field: PointCloud
    summary: FieldSummary
    inspection: InspectionOutcome | None = None
    inspection_error: str | None = None
    """Why a scan with a part type could not be inspected (no part hot enough in the field...): the scan
    keeps its field, the verdict is NotDecidable."""


def process_scan(*, frames: np.ndarray, sequence: Sequence, thermal: np.ndarray, rig: Rig,
                 tables: TriangulationTables, exposure: dict[str, Any] | None = None,
                 part: PreparedPart | None = None, clock: StageClock | None = None,
                 on_cloud: Callable[[PointCloud], None] | None = None) -> ScanOutcome:
    """Reconstruct the capture, fuse the thermal frames (F, h, w) of the rig's thermal camera, summarise and,
    given the scan's part type, inspect the field (:func:`services.pipeline.inspect.inspect_part`).

    ``exposure`` is the capture's exposure record (the gateway's: mode, exposures, ``saturation_level``);
    the summary holds the field's and what a hot part's glow did (``glow``). A field the part cannot be
    inspected in does not fail the scan: ``inspection_error`` says why. ``on_cloud`` is given the
    reconstruction's cloud before the fusion starts (which does not change it), e.g. to store it meanwhile.
    """
    exposure = exposure or {}
    clock = clock or StageClock()
    clock.start("reconstruct", 0.3)
    reconstruction = reconstruct_capture(frames=frames, sequence=sequence, rig=rig, tables=tables,
                                         saturation_level=exposure.get("saturation_level"), source="the scan")
    if on_cloud is not None:
        on_cloud(reconstruction.cloud)
    field_, inspection, inspection_error = fuse_and_inspect(
        cloud=reconstruction.cloud, rig=rig, thermal=[(None, thermal)], part=part, clock=clock, source="the scan",
        fractions=(0.55, 0.62))
    summary = field_summary(field_).model_copy(update={"glow": glow_summary(reconstruction.glow, exposure)})
    return ScanOutcome(reconstruction.cloud, field_, summary, inspection, inspection_error)


def fuse_and_inspect(*, cloud: PointCloud, rig: Rig, thermal: ThermalFrames, part: PreparedPart | None,
                     clock: StageClock, source: str, fractions: tuple[float, float]
                     ) -> tuple[PointCloud, InspectionOutcome | None, str | None]:
    """A scan's cloud fused (:func:`services.pipeline.field.fuse_field`) and, given its part type, inspected:
    the field, the inspection and why it could not be made (``None`` when it was or no part type was
    given). ``fractions`` are the job's progress at the two stages."""
    clock.start("fuse", fractions[0])
    field_ = fuse_field(cloud=cloud, rig=rig, thermal=thermal, source=source)
    inspection, inspection_error = None, None
    if part is not None:
        clock.start("inspect", fractions[1])
        try:
            inspection = inspect_part(field=field_, part=part,
                                      source=f"{source}'s field (part type {part.part.name!r})")
        except InputError as error:
            inspection_error = str(error)
    clock.stop()
    return field_, inspection, inspection_error


@dataclass(frozen=True)
class StoredScan:
    """A processed scan and the digests of its stored artifacts (name to SHA-256)."""

    outcome: ScanOutcome
    artifacts: dict[str, str]


def scan_capture(*, scan_id: str, frames: np.ndarray, sequence: Sequence, thermal: np.ndarray, rig: Rig,
                 tables: TriangulationTables, store: ArtifactStore, exposure: dict[str, Any] | None = None,
                 captured_at: float | None = None, part: PreparedPart | None = None,
                 clock: StageClock | None = None,
                 publish: Callable[[FieldScene, float | None], None] | None = None) -> StoredScan:
    """:func:`process_scan` with every file stored as soon as it is known, and the field streamed.

    The capture's files are stored while the reconstruction runs, the cloud's while the fusion runs (an
    :class:`~services.storage.artifacts.ArtifactWriter`); then the field, the inspection's files and the
    scan's Rerun recording ``field.rrd`` (its scene also given to ``publish``, e.g. the station's live
    view). Returns once every file is stored; a failed write raises.
    """
    clock = clock or StageClock()
    with ArtifactWriter(store) as writer:
        writer.put(capture_artifacts(frames=frames, sequence=sequence, thermal=thermal, exposure=exposure))
        outcome = process_scan(frames=frames, sequence=sequence, thermal=thermal, rig=rig, tables=tables,
                               exposure=exposure, part=part, clock=clock,
                               on_cloud=lambda cloud: writer.put_made(lambda: cloud_artifacts(cloud)))
        writer.put_made(lambda: field_artifacts(outcome))
        clock.start("stream", 0.7)
        deviation = None if outcome.inspection is None else outcome.inspection.deviation
        verdict = None if outcome.inspection is None else verdict_markdown(outcome.inspection.report)
        scene = field_scene(outcome.field, rig, thermal[0], deviation=deviation, verdict=verdict)
        writer.put({RECORDING.name: scan_recording(scan_id, scene, captured_at)})
        if publish is not None:
            publish(scene, captured_at)
        clock.start("store", 0.85)  # what storing adds after the stream: the rest of the writes
        artifacts = writer.digests()
    clock.stop()
    return StoredScan(outcome, artifacts)


def scan_result(*, scan_id: str, stored: StoredScan, part_type_id: str | None,
                stage_seconds: dict[str, float]) -> dict[str, Any]:
    """A scan job's JSON-safe result: its artifacts, summary, stage seconds, glow and, with a part type, the
    verdict and the features (``NotDecidable``, none and ``inspection_error`` when it could not be inspected)."""
    outcome = stored.outcome
    inspected: dict[str, Any] = {}
    if outcome.inspection is not None:
        inspected = {"part_type_id": part_type_id, **report_digest(outcome.inspection.report)}
    elif outcome.inspection_error is not None:
        inspected = {"part_type_id": part_type_id, "verdict": "NotDecidable", "features": [],
                     "inspection_error": outcome.inspection_error}
    summary = outcome.summary.model_dump(mode="json")
    return {"scan_id": scan_id, "artifacts": stored.artifacts, "summary": summary,
            "stage_seconds": stage_seconds, "glow": summary["glow"], **inspected}


def scan_artifacts(*, frames: np.ndarray, sequence: Sequence, thermal: np.ndarray, outcome: ScanOutcome,
                   exposure: dict[str, Any] | None = None) -> dict[str, bytes]:
    """The files a scan keeps: its :func:`capture_artifacts`, :func:`cloud_artifacts` and
    :func:`field_artifacts`."""
    return {**capture_artifacts(frames=frames, sequence=sequence, thermal=thermal, exposure=exposure),
            **cloud_artifacts(outcome.cloud), **field_artifacts(outcome)}


def capture_artifacts(*, frames: np.ndarray, sequence: Sequence, thermal: np.ndarray,
                      exposure: dict[str, Any] | None = None) -> dict[str, bytes]:
    """The files of the capture itself, known before any processing: ``frames.npy``, ``thermal.npy`` (float32
    degrees C), ``sequence.json`` and ``exposure.json``."""
    return {
        FRAMES.name: npy_bytes(frames),
        THERMAL.name: npy_bytes(thermal.astype(np.float32)),
        SEQUENCE.name: sequence_to_json(sequence).encode(),
        EXPOSURE.name: exposure_bytes(exposure),
    }


def cloud_artifacts(cloud: PointCloud) -> dict[str, bytes]:
    """The file of the scan's reconstruction, known before the fusion: ``cloud.ply``."""
    return {CLOUD.name: cloud_to_ply(cloud)}


def field_artifacts(outcome: ScanOutcome) -> dict[str, bytes]:
    """The files of the scan's results after the reconstruction: ``field.ply`` and, when inspected,
    ``report.json`` and ``deviation.ply``."""
    inspected = {} if outcome.inspection is None else inspection_artifacts(outcome.inspection)
    return {FIELD.name: cloud_to_ply(outcome.field), **inspected}

"""The stored scan: what a scan keeps (its artifacts' names, media types and encodings) and the typed records
that travel with it between the worker, the database, MQTT and the API (its summary and its exposure).

Every layer imports these names from here: the scan use case writes the artifacts, the workers read them
back, the API serves them, retention expires the raw ones. The summary is declared once, as the pydantic
models below; the API's schemas use them as they are.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, Field

if TYPE_CHECKING:
    from services.geometry.merge import OverlapSample

OCTET_STREAM = "application/octet-stream"


@dataclass(frozen=True)
class Artifact:
    """One file a scan keeps, under ``name`` in the scan's ``artifacts`` (name to SHA-256 in the store).

    ``raw``: part of the capture, expired first by retention (``raw_frames_days``); ``served``: downloadable
    as ``GET /v1/scans/{id}/{name}``; ``inspected``: only a scan inspected against a part type has it."""

    name: str
    media_type: str
    raw: bool = False
    served: bool = True
    inspected: bool = False


FRAMES = Artifact("frames.npy", OCTET_STREAM, raw=True)
"""The camera frames, one ``.npy`` array (frames, height, width), uint8 or uint16."""
THERMAL = Artifact("thermal.npy", OCTET_STREAM, raw=True)
"""The thermal frames, one ``.npy`` array (frames, height, width), float32 degrees C."""
SEQUENCE = Artifact("sequence.json", "application/json", raw=True, served=False)
"""The capture's sequence manifest (docs/sequence-manifest.md)."""
EXPOSURE = Artifact("exposure.json", "application/json", served=False)
"""How the camera was exposed: :class:`Exposure` as JSON."""
CLOUD = Artifact("cloud.ply", OCTET_STREAM)
FIELD = Artifact("field.ply", OCTET_STREAM)
RECORDING = Artifact("field.rrd", OCTET_STREAM)
"""The scan's Rerun recording (docs/streaming.md)."""
REPORT = Artifact("report.json", "application/json", inspected=True)
"""The inspection report (docs/inspection.md)."""
DEVIATION = Artifact("deviation.ply", OCTET_STREAM, inspected=True)
"""The cold-equivalent cloud with each point's ``deviation``."""

ARTIFACTS: dict[str, Artifact] = {artifact.name: artifact for artifact in (
    FRAMES, THERMAL, SEQUENCE, EXPOSURE, CLOUD, FIELD, RECORDING, REPORT, DEVIATION)}
SERVED: dict[str, Artifact] = {name: artifact for name, artifact in ARTIFACTS.items() if artifact.served}
RAW: tuple[str, ...] = tuple(name for name, artifact in ARTIFACTS.items() if artifact.raw)


def npy_bytes(array: np.ndarray) -> bytes:
    """An array as ``.npy`` bytes (uncompressed: storing must not slow the scan; the API encodes on request)."""
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


OVERLAP_SAMPLE = "overlap.npz"
"""A station head's file (``heads/<head>/overlap.npz``) of its cloud's sample the merge works on
(``services.geometry.merge.OverlapSample``): one uncompressed ``.npz`` of float64 arrays, read without pickle."""
_OVERLAP_ARRAYS = ("refine_points", "refine_normals", "residual_points", "residual_normals")


def overlap_sample_bytes(sample: OverlapSample) -> bytes:
    """A head's overlap sample as :data:`OVERLAP_SAMPLE`'s bytes."""
    buffer = io.BytesIO()
    np.savez(buffer, **{name: getattr(sample, name) for name in _OVERLAP_ARRAYS},
             spacing_mm=np.float64(sample.spacing_mm))
    return buffer.getvalue()


def overlap_sample_from_bytes(data: bytes) -> OverlapSample:
    """A head's overlap sample read back from :data:`OVERLAP_SAMPLE`'s bytes."""
    from services.geometry.merge import OverlapSample

    with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
        return OverlapSample(*(arrays[name] for name in _OVERLAP_ARRAYS), float(arrays["spacing_mm"]))


class Exposure(BaseModel):
    """How the gateway exposed the camera for a capture (``exposure.json``); unknown keys are kept."""

    model_config = {"extra": "allow"}

    mode: str = Field("fixed", description="fixed, auto or hdr (docs/hot-parts.md).")
    exposures_us: list[float | None] | None = Field(None, description="The exposure of each frame, microseconds.")
    saturation_level: float | None = Field(None, description="The frames' level of saturation, if not full scale.")


def exposure_bytes(exposure: Exposure | dict[str, Any] | None) -> bytes:
    """``exposure.json``'s bytes."""
    if exposure is None:
        exposure = Exposure()
    elif not isinstance(exposure, Exposure):
        exposure = Exposure.model_validate(exposure)
    return json.dumps(exposure.model_dump(exclude_none=True)).encode()


def exposure_from_bytes(data: bytes | None) -> Exposure:
    """An ``exposure.json`` read back (a scan stored without one was exposed as set: fixed)."""
    return Exposure() if data is None else Exposure.model_validate_json(data)


class TemperatureSummary(BaseModel):
    min: float
    max: float
    mean: float
    percentiles: dict[str, float] = Field(description="p5, p25, p50, p75, p95 in degrees Celsius.")


class GlowSummary(BaseModel):
    glowing_fraction: float = Field(description="Share of the camera's pixels where the part's glow is at least "
                                                "2 % of full scale and at least the reflected pattern.")
    saturated_fraction: float = Field(description="Share of the glowing pixels the glow saturates.")
    lost_fraction: float = Field(description="Share of the glowing pixels whose pattern the glow's shot noise "
                                             "buries, even over a window of neighbours (surfaces the projector "
                                             "does not light are not counted).")
    lost_to_glow: float = Field(description="saturated_fraction + lost_fraction.")
    measured_fraction: float = Field(1.0, description="Share of the glowing pixels measured (given a projector "
                                                      "coordinate); below 1 % the scan is refused.")
    glow_level: float = Field(description="99th percentile of the glow, as a fraction of full scale.")
    drift: float = Field(description="Median relative change of the glow over the sequence (negative: cooling).")
    hint: str | None = Field(description="What to change when the glow costs more than 5 % of the part.")
    exposure_mode: str
    exposures_us: list[float | None] | None


def head_artifact(head: str, name: str) -> str:
    """The name under which a station scan keeps head ``head``'s file ``name`` (``frames.npy``, ``sequence.json``,
    ``exposure.json``, ``cloud.ply``, ``overlap.npz``): ``heads/<head>/<name>``, the station capture layout's (docs/station.md)."""
    return f"heads/{head}/{name}"


def thermal_artifact(device: str) -> str:
    """The name under which a station scan keeps thermal camera ``device``'s frames (float32 degrees C, ``.npy``)."""
    return f"thermal/{device}.npy"


def is_raw(name: str) -> bool:
    """Whether the artifact (or a head job's parameter) ``name`` is part of the capture, expired first by retention:
    a single-head scan's :data:`RAW` files, a station head's ``heads/<head>/frames.npy`` and ``sequence.json`` (and
    a head job's ``frames.npy`` and ``sequence.json`` parameters), a thermal camera's ``thermal/<device>.npy``."""
    return name.rsplit("/", 1)[-1] in RAW or (name.startswith("thermal/") and name.endswith(".npy"))


class HeadSummary(BaseModel):
    """One head of a station scan: its points, its time, its pose correction in the merge, or why it failed."""

    head: str
    measured_points: int = Field(description="Points the head's reconstruction measured.")
    kept_points: int = Field(description="Points of the head the merged cloud keeps (the overlaps thinned).")
    reconstruct_seconds: float | None = Field(description="The head's decoding and triangulation (its own message).")
    correction_mm: float | None = Field(None, description="The merge's pose correction of the head: translation.")
    correction_deg: float | None = Field(None, description="The merge's pose correction of the head: rotation.")
    correction_applied: bool | None = Field(None, description="Whether the correction was applied (else why not in "
                                                               "correction_note).")
    correction_note: str = ""
    error: str | None = Field(None, description="Why the head failed (a device lost, nothing decoded): the scan "
                                                "is then NotDecidable, never judged from the heads left.")


class OverlapSummary(BaseModel):
    """The residual between two heads' surfaces where they overlap, after the merge (mm)."""

    first: str
    second: str
    points: int
    rms_mm: float = Field(description="Per point: each point's distance from the other head's surface.")
    patch_rms_mm: float = Field(description="RMS over 4 mm patches of the mean distance: the misregistration.")


class StationSummary(BaseModel):
    """What the heads of a station scan did (docs/station.md, "The service")."""

    heads: list[HeadSummary]
    overlaps: list[OverlapSummary]
    failed_heads: list[str] = Field(description="The heads that failed; a scan with any is NotDecidable.")


class FieldSummary(BaseModel):
    """What the scan endpoint, MQTT and the demo report of a scan's field."""

    point_count: int
    points_with_temperature: int
    bbox_min: list[float] = Field(description="World millimetres.")
    bbox_max: list[float]
    temperature: TemperatureSummary | None
    glow: GlowSummary | None = Field(None, description="What a hot part's glow did (sequences closed by a black frame).")
    station: StationSummary | None = Field(None, description="A station scan's heads: points, times, pose "
                                                             "corrections, overlap residuals, failures.")

"""Request and response bodies of the API (separate from the database models)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from services.formats.board import MIN_VIEWS, BoardSpec
from services.formats.stored_scan import FieldSummary  # one declaration for the worker, MQTT and the API

JobStatus = Literal["queued", "running", "succeeded", "failed"]


class JobOut(BaseModel):
    job_id: str
    kind: str
    status: JobStatus
    stage: str
    fraction: float = Field(ge=0, le=1)
    attempts: int
    worker: str | None = Field(description="host:pid of the worker process that ran the last attempt.")
    error: str | None
    result: dict[str, Any]
    scan_id: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    links: dict[str, str]


class ScanRequest(BaseModel):
    """Everything is optional: an empty body scans with the station's active calibration set."""

    model_config = ConfigDict(extra="forbid")

    part_id: str | None = Field(None, max_length=200, description="The MES's identifier of the part.")
    calibration_set_id: str | None = Field(None, description="Defaults to the station's active calibration set.")
    part_type_id: str | None = Field(None, description="The part type to inspect the field against; default the "
                                                       "station's selected one (none selected: no inspection).")


class ScanJobRequest(BaseModel):
    """One processing step again on a stored scan."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["reconstruct", "fuse", "register"]
    calibration_set_id: str | None = Field(
        None, description="reconstruct, fuse: the calibration set to use; default the scan's own.")
    cloud_job_id: str | None = Field(
        None, description="fuse: a succeeded reconstruct job of this scan whose cloud to fuse; "
                          "default the scan's cloud.")
    model: Literal["translation", "rigid", "similarity", "affine", "homography"] = Field(
        "similarity", description="register: the geometric model mapping thermal to camera pixels.")


class StereoCaptureRequest(BaseModel):
    """A calibration capture job: the gateway films a board with the camera and the device, then the device is
    placed relative to the camera from those views (``calibrate stereo``)."""

    model_config = ConfigDict(extra="forbid")

    board: BoardSpec = Field(description="The board both devices see (docs/calibration.md): for the thermal camera "
                                         "a hollowed chessboard before a heater.")
    views: int = Field(12, ge=MIN_VIEWS, le=100, description="Board poses to film.")
    interval_s: float = Field(2.0, ge=0, le=60, description="Seconds the operator has to move the board between "
                                                            "views (the simulated station moves it at once).")
    name: str = Field(min_length=1, max_length=200, description="Name of the new calibration set.")
    device: str = Field("thermal", min_length=1, max_length=100, description="The rig's device to place.")
    activate: bool = Field(False, description="Make the new calibration set the station's active one.")


class Accepted(BaseModel):
    job_id: str
    scan_id: str | None = None
    status: JobStatus
    links: dict[str, str]


Verdict = Literal["OK", "NotOK", "NotDecidable"]


class FeatureResult(BaseModel):
    """One feature of the inspection report (docs/inspection.md, REPORT.json): values in mm, cold at 20 degC."""

    model_config = ConfigDict(extra="allow")

    name: str
    type: str
    measure: str | None
    hot: float | None
    cold: float | None
    nominal: float | None
    deviation: float | None = Field(description="cold - nominal.")
    tolerance: list[float]
    uncertainty: float | None = Field(description="Expanded uncertainty (k = 2) of the cold value.")
    verdict: Verdict


class ScanOut(BaseModel):
    scan_id: str
    station: str
    part_id: str | None
    calibration_set_id: str
    part_type_id: str | None = Field(description="The part type the scan is inspected against (none: not inspected).")
    job_id: str
    status: JobStatus
    created_at: datetime
    summary: FieldSummary | None
    verdict: Verdict | None = Field(description="The inspection's overall verdict, once the job succeeded.")
    features: list[FeatureResult] | None
    links: dict[str, str]


class PartTypeOut(BaseModel):
    part_type_id: str
    name: str = Field(description="The part file's name.")
    station: str
    material: str
    selected: bool = Field(description="Scans that name no part type are inspected against the selected one.")
    created_at: datetime
    links: dict[str, str]


class CalibrationSetOut(BaseModel):
    calibration_set_id: str
    name: str
    station: str
    active: bool
    source: str = Field(description="upload, calibration (a calibrate job), or simulator (the simulated rig's "
                                    "true calibration).")
    created_at: datetime
    links: dict[str, str]


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    status: Literal["ready"]
    checks: dict[str, str]


class ApiKeyOut(BaseModel):
    api_key_id: str
    name: str
    scopes: list[str]
    created_at: datetime
    revoked_at: datetime | None


class ApiKeyCreated(ApiKeyOut):
    secret: str = Field(description="The key itself, shown only in this answer (the database keeps its SHA-256).")


class ApiKeyRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field("api key", min_length=1, max_length=200)
    scopes: list[Literal["read", "operate", "admin"]] = Field(min_length=1, max_length=3)

"""The gateway's own small HTTP API, used by the workers: devices, health, capture.

- ``GET /healthz``: 200 when every device is open, else 503; both list the devices.
- ``GET /v1/devices``: the devices with name, kind, driver, resolution, identity.
- ``GET /v1/sequence``: the sequence manifest every capture projects.
- ``POST /v1/captures`` ``{"thermal_frames": 1}``: runs one capture and answers the
  ``.npz`` archive of :mod:`device_gateway.transfer` (a station of several heads: every head one after
  another, then the thermal cameras, as the station capture archive).
- ``POST /v1/board-views`` ``{"board": {...}, "views": 12, "interval_s": 2}``: films a
  calibration board in that many poses with both cameras (``.npz`` board views).

Errors are RFC 9457 ``application/problem+json``: 422 for a bad request, 413 for a body
over the limit, 503 when a device is unavailable or was lost during the capture (it is
re-opened; retry).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from services.bodylimit import BodySizeLimit
from device_gateway.devices import DeviceError
from device_gateway.station import ExposureControl, MultiHeadStation, Station
from device_gateway.transfer import (BOARD_VIEWS_MEDIA_TYPE, MEDIA_TYPE, STATION_MEDIA_TYPE, encode_board_views,
                                     encode_capture, encode_station_capture)
from services.formats.board import BoardSpec
from services.formats.sequence import Sequence
from services.problems import problem_response
from services.settings import Settings

logger = logging.getLogger(__name__)


class CaptureRequest(BaseModel):
    thermal_frames: int = Field(1, ge=1, le=64, description="Thermal frames grabbed after the last pattern.")
    exposure: Literal["fixed", "auto", "hdr"] = Field(
        "fixed", description="The camera's own exposure, metered for a glowing part, or metered and HDR-merged.")


class BoardViewsRequest(BaseModel):
    board: BoardSpec = Field(description="The board (docs/calibration.md), as in a board file.")
    views: int = Field(12, ge=3, le=100, description="Board poses to film.")
    interval_s: float = Field(2.0, ge=0, le=60, description="Seconds a person has to move the board between views.")


class DeviceStatus(BaseModel):
    name: str
    kind: str
    driver: str
    width: int
    height: int
    model: str
    serial: str
    open: bool


class Health(BaseModel):
    status: str = Field(description="ok when every device is open, else degraded")
    devices: dict[str, bool]


def _station(request: Request) -> Station | MultiHeadStation:
    return request.app.state.station


StationDep = Annotated[Station | MultiHeadStation, Depends(_station)]


def create_app(station: Station | MultiHeadStation, sequence: Sequence, patterns: np.ndarray,
               max_body_bytes: int = Settings.model_fields["max_body_bytes"].default) -> FastAPI:
    """The gateway app serving ``station``, projecting ``patterns`` (described by ``sequence``) per capture;
    a request body (the JSON of a capture or board-views request) over ``max_body_bytes`` is refused with 413
    before it is read (``THERMOFIELD_MAX_BODY_BYTES``)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            station.open()
            if isinstance(station, MultiHeadStation):
                station.prepare(patterns)
            else:
                station.camera.prepare(patterns)
        except DeviceError as error:
            logger.warning("starting with devices unavailable (captures will retry): %s", error)
        yield
        station.close()

    app = FastAPI(title="thermofield device gateway", version="1", lifespan=lifespan)
    app.state.station = station
    app.add_middleware(BodySizeLimit, limits=lambda: (max_body_bytes, max_body_bytes))

    @app.exception_handler(DeviceError)
    async def device_error(request: Request, error: DeviceError) -> JSONResponse:
        return problem_response(503, "device-unavailable", str(error), request.url.path)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, error: RequestValidationError) -> JSONResponse:
        details = "; ".join(f"{'.'.join(map(str, item['loc']))}: {item['msg']}" for item in error.errors())
        return problem_response(422, "validation-error", details, request.url.path)

    @app.get("/healthz", operation_id="health", response_model=Health,
             responses={503: {"model": Health, "description": "A device is not open."}})
    def health(station: StationDep) -> Any:
        devices = station.health()
        healthy = all(devices.values())
        body = Health(status="ok" if healthy else "degraded", devices=devices)
        return body if healthy else JSONResponse(body.model_dump(), status_code=503)

    @app.get("/v1/devices", operation_id="listDevices", response_model=list[DeviceStatus])
    def list_devices(station: StationDep) -> list[DeviceStatus]:
        return [DeviceStatus(**dataclasses.asdict(device.info), open=device.is_open) for device in station.devices]

    @app.get("/v1/sequence", operation_id="getSequence", response_model=Sequence)
    def get_sequence() -> Sequence:
        return sequence

    @app.post("/v1/captures", operation_id="capture", response_class=Response,
              responses={200: {"content": {MEDIA_TYPE: {}, STATION_MEDIA_TYPE: {}},
                               "description": "The capture archive (a station of several heads: the station's)."}})
    def capture(station: StationDep, body: CaptureRequest | None = None) -> Response:
        request = body or CaptureRequest()
        result = station.capture(sequence, patterns, thermal_frames=request.thermal_frames,
                                 exposure=ExposureControl(mode=request.exposure))
        if isinstance(station, MultiHeadStation):
            return Response(encode_station_capture(result), media_type=STATION_MEDIA_TYPE)
        return Response(encode_capture(result), media_type=MEDIA_TYPE)

    @app.post("/v1/board-views", operation_id="boardViews", response_class=Response,
              responses={200: {"content": {BOARD_VIEWS_MEDIA_TYPE: {}}, "description": "The board views archive."}})
    def board_views(station: StationDep, body: BoardViewsRequest, request: Request) -> Response:
        if isinstance(station, MultiHeadStation):
            return problem_response(409, "conflict", "a station of several heads films no paired board views: "
                                    "calibrate it from uploaded views (POST /v1/calibration-sets/{id}/station)",
                                    request.url.path)
        views = station.board_views(body.board, body.views, body.interval_s)
        return Response(encode_board_views(views), media_type=BOARD_VIEWS_MEDIA_TYPE)

    return app

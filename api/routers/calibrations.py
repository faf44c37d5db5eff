"""Calibration sets: upload a rig file, calibrate a device or a station from board images; list, get, download,
activate."""

from __future__ import annotations

import hashlib
import json
from pathlib import PurePath
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from api.deps import AdminKey, JobQueueDep, ReaderKey, RuntimeDep, SessionDep
from api.dispatch import start_job
from api.idempotency import IdempotencyKeyHeader, Outcome, request_digest, respond_once
from api.artifacts import stored_bytes
from api.problems import Problem, problem_responses
from api.uploads import read_limited
from api.schemas import Accepted, CalibrationSetOut, StereoCaptureRequest
from services.db.calibrations import (activate_calibration, add_calibration_set, calibration_set,
                                      station_calibration_sets)
from services.db.models import CalibrationSet
from services.formats.board import MIN_VIEWS, parse_board
from services.formats.images import FRAME_SUFFIXES, decode_image
from services.formats.rig import Rig, parse_rig, rig_to_json

router = APIRouter(prefix="/calibration-sets", tags=["calibration"])
_MAX_RIG_BYTES = 1 << 20


def calibration_out(calibration: CalibrationSet) -> CalibrationSetOut:
    links = {"self": f"/v1/calibration-sets/{calibration.id}"}
    if calibration.rig_sha256:
        links["rig"] = f"/v1/calibration-sets/{calibration.id}/rig.json"
    return CalibrationSetOut(calibration_set_id=calibration.id, name=calibration.name, station=calibration.station,
                             active=calibration.active, source=calibration.source,
                             created_at=calibration.created_at, links=links)


def _existing_calibration(calibration_set_id: str, session: SessionDep, _: ReaderKey) -> CalibrationSet:
    calibration = calibration_set(session, calibration_set_id)
    if calibration is None:
        raise Problem(404, "not-found", f"There is no calibration set {calibration_set_id!r}.")
    return calibration


ExistingCalibration = Annotated[CalibrationSet, Depends(_existing_calibration)]


@router.post("", name="create_calibration_set", status_code=201, response_model=CalibrationSetOut,
             responses=problem_responses(413))
async def create_calibration_set(request: Request, session: SessionDep, runtime: RuntimeDep, key: AdminKey,
                                 rig: Annotated[UploadFile, File(description="A rig file (docs/rig-file.md).")],
                                 name: Annotated[str, Form(min_length=1, max_length=200)],
                                 activate: Annotated[bool, Form()] = False,
                                 idempotency_key: IdempotencyKeyHeader = None):
    """Store an uploaded, validated rig file as a calibration set of this station."""
    text = await read_limited(rig, "rig", _MAX_RIG_BYTES)
    parsed = parse_rig(text.decode("utf-8", errors="replace"), f"rig ({rig.filename})")
    rig_digest = runtime.store.put_bytes(rig_to_json(parsed).encode())

    def create() -> Outcome:
        calibration = add_calibration_set(session, name=name, station=runtime.settings.station,
                                          rig_sha256=rig_digest, source="upload", activate=activate)
        out = calibration_out(calibration)
        return Outcome(201, out.model_dump(mode="json"), out.links["self"])

    request_sha256 = request_digest(request, json.dumps({"name": name, "activate": activate}).encode() + text)
    return await run_in_threadpool(respond_once, session, key, idempotency_key, request_sha256, create,
                                   runtime.settings.idempotency_ttl_s)


@router.post("/{calibration_set_id}/stereo", name="start_stereo_calibration", status_code=202,
             response_model=Accepted, responses={202: {"headers": {"Location": {"description": "The job."}}},
                                                 **problem_responses(404, 409, 413)})
async def start_stereo_calibration(
    request: Request, key: AdminKey, calibration: ExistingCalibration, session: SessionDep, runtime: RuntimeDep,
    queue: JobQueueDep,
    board: Annotated[UploadFile, File(description="Board specification JSON (docs/calibration.md).")],
    reference_images: Annotated[list[UploadFile], File(min_length=MIN_VIEWS,
                                                       description="Board images of the rig's camera.")],
    device_images: Annotated[list[UploadFile], File(min_length=MIN_VIEWS, description="The same board poses seen "
                                                                                      "by the device, in the same "
                                                                                      "order: board images, or the "
                                                                                      "thermal camera's radiometric "
                                                                                      "files (FLIR R-JPEG, float "
                                                                                      "TIFF in degrees C).")],
    name: Annotated[str, Form(min_length=1, max_length=200)],
    device: Annotated[str, Form(min_length=1, max_length=100)] = "thermal",
    activate: Annotated[bool, Form()] = False,
    idempotency_key: IdempotencyKeyHeader = None,
):
    """Re-place a device (default the thermal camera) relative to the camera from paired board images: a
    ``calibrate`` job that creates a new calibration set from this one (``result.calibration_set_id``)."""
    rig = _rig_of(runtime, calibration)
    _require_thermal_device(rig, calibration, device)
    if len(reference_images) != len(device_images):
        raise Problem(422, "invalid-input", f"reference_images, device_images: give the same number of images; got "
                                            f"{len(reference_images)} and {len(device_images)}.")
    board_text = await read_limited(board, "board", _MAX_RIG_BYTES)
    parse_board(board_text.decode("utf-8", errors="replace"), f"board ({board.filename})")
    hasher = hashlib.sha256(board_text)
    _, camera = rig.device(None, "camera")
    sizes = {"reference_images": (camera.width, camera.height),
             "device_images": (rig.devices[device].width, rig.devices[device].height)}
    # the thermal reader brings the radiometric model, science the API does not load at start
    from services.formats.flir import JPEG_SUFFIXES
    from services.formats.thermal import is_radiometric_file

    checked = {}  # every upload is checked before anything is stored
    for field, uploads in (("reference_images", reference_images), ("device_images", device_images)):
        checked[field] = []
        suffixes = FRAME_SUFFIXES + (JPEG_SUFFIXES if field == "device_images" else ())
        for upload in uploads:
            suffix = PurePath(upload.filename or "").suffix.lower()
            if suffix not in suffixes:
                raise Problem(422, "invalid-input", f"{field}: {upload.filename!r} is not one of "
                                                    f"{', '.join(suffixes)}.")
            content = await read_limited(upload, field, runtime.settings.max_image_bytes)
            # a thermal camera's own file (FLIR R-JPEG, float TIFF in degrees C) is read for its temperatures,
            # as the worker will read it
            radiometric = field == "device_images" and is_radiometric_file(content, suffix)
            hasher.update(content)
            checked[field].append((content, suffix, f"{field}: {upload.filename!r}", sizes[field], radiometric))
    settings = runtime.settings
    await request.app.state.decoders.run(
        check_board_images, [image for uploads in checked.values() for image in uploads],
        settings.max_image_pixels, settings.decode_memory_bytes, source="the board images")
    images = {field: [[runtime.store.put_bytes(content), suffix] for content, suffix, *_ in uploads]
              for field, uploads in checked.items()}
    params = {"calibration_set_id": calibration.id, "station": calibration.station, "device": device,
              "name": name, "activate": activate, "board": runtime.store.put_bytes(board_text), **images}

    form = json.dumps({"name": name, "device": device, "activate": activate}).encode() + hasher.digest()
    request_sha256 = request_digest(request, form)
    return await run_in_threadpool(respond_once, session, key, idempotency_key, request_sha256,
                                   lambda: start_job(runtime, queue, session, "calibrate", params),
                                   runtime.settings.idempotency_ttl_s)


@router.post("/{calibration_set_id}/station", name="start_station_calibration", status_code=202,
             response_model=Accepted, responses={202: {"headers": {"Location": {"description": "The job."}}},
                                                 **problem_responses(404, 409, 413)})
async def start_station_calibration(
    request: Request, key: AdminKey, calibration: ExistingCalibration, session: SessionDep, runtime: RuntimeDep,
    queue: JobQueueDep,
    board: Annotated[UploadFile, File(description="Board specification JSON (docs/calibration.md).")],
    images: Annotated[list[UploadFile], File(min_length=2, description="Board views, each named HEAD/FILE (a head "
                                                                       "of the station) or THERMAL/FILE (one of its "
                                                                       "thermal cameras); one FILE under several "
                                                                       "names is one board pose seen by those "
                                                                       "cameras at once.")],
    name: Annotated[str, Form(min_length=1, max_length=200)],
    world: Annotated[str | None, Form(max_length=100, description="The head or device fixing the world frame "
                                                                  "(default the first head's camera).")] = None,
    intrinsics: Annotated[Literal["refined", "fixed"], Form()] = "refined",
    activate: Annotated[bool, Form()] = False,
    idempotency_key: IdempotencyKeyHeader = None,
):
    """Calibrate a station's heads (and thermal cameras) to one world frame from uploaded board views (``thermofield
    calibrate station``): a ``calibrate_station`` job that creates a new calibration set from this one, which must
    be a station (a version-2 rig with heads)."""
    rig = _rig_of(runtime, calibration)
    if not rig.station_heads:
        raise Problem(422, "invalid-input", f"calibration set {calibration.id} is not a station (its rig lists no "
                                            "heads); upload a version-2 rig first.")
    cameras = {h.name: rig.devices[h.camera] for h in rig.heads}
    cameras.update({n: d for n, d in rig.devices.items() if d.kind == "thermal"})
    board_text = await read_limited(board, "board", _MAX_RIG_BYTES)
    parse_board(board_text.decode("utf-8", errors="replace"), f"board ({board.filename})")
    hasher = hashlib.sha256(board_text)
    from services.formats.flir import JPEG_SUFFIXES
    from services.formats.thermal import is_radiometric_file

    checked = []  # every upload is checked before anything is stored
    for upload in images:
        path = PurePath(upload.filename or "")
        camera, suffix = (path.parts[0] if len(path.parts) == 2 else None), path.suffix.lower()
        if camera not in cameras:
            raise Problem(422, "invalid-input", f"images: {upload.filename!r} must be named HEAD/FILE or THERMAL/FILE "
                                                f"with one of {sorted(cameras)}.")
        suffixes = FRAME_SUFFIXES + (JPEG_SUFFIXES if cameras[camera].kind == "thermal" else ())
        if suffix not in suffixes:
            raise Problem(422, "invalid-input", f"images: {upload.filename!r} is not one of {', '.join(suffixes)}.")
        content = await read_limited(upload, "images", runtime.settings.max_image_bytes)
        hasher.update(upload.filename.encode() + content)
        radiometric = cameras[camera].kind == "thermal" and is_radiometric_file(content, suffix)
        checked.append((camera, path.name, content, suffix, f"images: {upload.filename!r}", cameras[camera].size,
                        radiometric))
    settings = runtime.settings
    await request.app.state.decoders.run(check_board_images, [item[2:] for item in checked], settings.max_image_pixels,
                                         settings.decode_memory_bytes, source="the board images")
    views: dict[str, list] = {}
    for camera, label, content, suffix, *_ in checked:
        views.setdefault(camera, []).append([runtime.store.put_bytes(content), suffix, label])
    params = {"calibration_set_id": calibration.id, "station": calibration.station, "name": name, "world": world,
              "intrinsics": intrinsics, "activate": activate, "board": runtime.store.put_bytes(board_text),
              "views": views}
    form = json.dumps({"name": name, "world": world, "intrinsics": intrinsics, "activate": activate}).encode()
    request_sha256 = request_digest(request, form + hasher.digest())
    return await run_in_threadpool(respond_once, session, key, idempotency_key, request_sha256,
                                   lambda: start_job(runtime, queue, session, "calibrate_station", params),
                                   runtime.settings.idempotency_ttl_s)


@router.post("/{calibration_set_id}/stereo-captures", name="start_stereo_capture", status_code=202,
             response_model=Accepted, responses={202: {"headers": {"Location": {"description": "The job."}}},
                                                 **problem_responses(404, 409)})
async def start_stereo_capture(request: Request, key: AdminKey, calibration: ExistingCalibration,
                               body: StereoCaptureRequest, session: SessionDep, runtime: RuntimeDep, queue: JobQueueDep,
                               idempotency_key: IdempotencyKeyHeader = None):
    """A calibration capture job: the gateway films the board in ``views`` poses with the camera and the device
    (default the thermal camera), which is then placed relative to the camera: a ``calibrate`` job that creates a
    new calibration set from this one (``result.calibration_set_id``)."""
    rig = _rig_of(runtime, calibration)
    _require_thermal_device(rig, calibration, body.device)
    board = runtime.store.put_bytes(json.dumps(body.model_dump(mode="json")["board"]).encode())
    params = {"calibration_set_id": calibration.id, "station": calibration.station, "device": body.device,
              "name": body.name, "activate": body.activate, "board": board,
              "capture": {"views": body.views, "interval_s": body.interval_s}}
    digest = request_digest(request, await request.body())
    return await run_in_threadpool(respond_once, session, key, idempotency_key, digest,
                                   lambda: start_job(runtime, queue, session, "calibrate", params),
                                   runtime.settings.idempotency_ttl_s)


def _rig_of(runtime, calibration: CalibrationSet) -> Rig:
    """The calibration set's rig, to derive a new set from; 409 while it has none."""
    if calibration.rig_sha256 is None:
        raise Problem(409, "not-ready", f"Calibration set {calibration.id} has no rig yet to start from.")
    owner = f"calibration set {calibration.id}"
    return parse_rig(stored_bytes(runtime.store, calibration.rig_sha256, owner).decode(), owner)


def check_board_images(images: list[tuple[bytes, str, str, tuple[int, int], bool]], max_pixels: int,
                       max_bytes: int) -> None:
    """Each ``(content, suffix, source, (width, height), radiometric)`` decodes to an 8- or 16-bit image of its
    device's size, or a radiometric thermal file to its temperatures (:func:`services.formats.thermal.
    decode_thermal_frame`), or an ``InputError`` names it; the header is checked before the pixels are decoded
    (:func:`services.formats.images.decode_image`). Run in a decoding process (api/decoding.py)."""
    for content, suffix, source, size, radiometric in images:
        if radiometric:
            from services.formats.thermal import decode_thermal_frame

            decode_thermal_frame(content, suffix=suffix, source=source, size=size)
        else:  # decoded, then converted to grey when in colour: two copies at most
            decode_image(content, source, max_pixels=max_pixels, size=size, max_bytes=max_bytes // 2)


def _require_thermal_device(rig: Rig, calibration: CalibrationSet, device: str) -> None:
    if device not in rig.devices or rig.devices[device].kind != "thermal":
        raise Problem(422, "invalid-input", f"device: calibration set {calibration.id} has no thermal device "
                                            f"{device!r} to place (it has {sorted(rig.devices)}).")


@router.get("", name="list_calibration_sets")
def list_calibration_sets(session: SessionDep, runtime: RuntimeDep, _: ReaderKey) -> list[CalibrationSetOut]:
    """This station's calibration sets, newest first."""
    return [calibration_out(calibration) for calibration in station_calibration_sets(session, runtime.settings.station)]


@router.get("/{calibration_set_id}", name="get_calibration_set", responses=problem_responses(404))
def get_calibration_set(calibration: ExistingCalibration) -> CalibrationSetOut:
    return calibration_out(calibration)


@router.get("/{calibration_set_id}/rig.json", name="download_calibration_set",
            responses={200: {"content": {"application/json": {}}}, **problem_responses(404)})
def download_calibration_set(calibration: ExistingCalibration, runtime: RuntimeDep) -> Response:
    """The calibration set as a rig file."""
    if calibration.rig_sha256 is None:
        raise Problem(404, "not-ready", f"Calibration set {calibration.id} has no rig yet.")
    return Response(stored_bytes(runtime.store, calibration.rig_sha256, f"calibration set {calibration.id}"),
                    media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{calibration.id}-rig.json"'})


@router.post("/{calibration_set_id}/activate", name="activate_calibration_set", responses=problem_responses(404, 409))
def activate_calibration_set(_: AdminKey, calibration: ExistingCalibration, session: SessionDep) -> CalibrationSetOut:
    """Make this the station's active calibration set (new scans use it)."""
    if calibration.rig_sha256 is None:
        raise Problem(409, "not-ready", f"Calibration set {calibration.id} has no rig yet and cannot be active.")
    activate_calibration(session, calibration)
    session.commit()
    return calibration_out(calibration)

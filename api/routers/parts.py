"""Part types (recipes): upload a part file with its nominal mesh, list, get, download, select one per station."""

from __future__ import annotations

import hashlib
import json
from pathlib import PurePath
from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from api.deps import AdminKey, ReaderKey, RuntimeDep, SessionDep
from api.idempotency import IdempotencyKeyHeader, Outcome, request_digest, respond_once
from api.artifacts import stored_bytes
from api.problems import Problem, problem_responses
from api.schemas import PartTypeOut
from api.uploads import read_limited
from services.db.models import PartType
from services.db import parts
from services.errors import InputError
from services.formats.part import MESH_SUFFIXES, parse_part_with_mesh

router = APIRouter(prefix="/part-types", tags=["part types"])
_MAX_PART_BYTES = 1 << 20
_MAX_MESH_BYTES = 128 << 20  # a binary STL of 2.6 million triangles
_MESH_MEDIA_TYPES = {".stl": "model/stl", ".ply": "application/octet-stream", ".obj": "model/obj"}


def part_type_out(part_type: PartType) -> PartTypeOut:
    base = f"/v1/part-types/{part_type.id}"
    return PartTypeOut(part_type_id=part_type.id, name=part_type.name, station=part_type.station,
                       material=part_type.material, selected=part_type.selected, created_at=part_type.created_at,
                       links={"self": base, "part": f"{base}/part.json", "mesh": f"{base}/mesh"})


def _existing_part_type(part_type_id: str, session: SessionDep, _: ReaderKey) -> PartType:
    part_type = parts.part_type(session, part_type_id)
    if part_type is None:
        raise Problem(404, "not-found", f"There is no part type {part_type_id!r}.")
    return part_type


ExistingPartType = Annotated[PartType, Depends(_existing_part_type)]


def validate_part(text: bytes, part_name: str | None, mesh: bytes, mesh_name: str | None, max_triangles: int,
                  max_bytes: int) -> tuple[str, str]:
    """The part file and its mesh as the inspection will load and prepare them (Open3D reads the mesh, each
    feature is fitted to it): the part's name and material, or an ``InputError`` naming the field: ``part``
    (JSON, material, features, a feature whose region misses the nominal) or ``mesh`` (not a triangle mesh
    in the part file's format, or more triangles or memory than the limits; checked before Open3D reads it).
    Run in a decoding process (api/decoding.py)."""
    from services.inspection.inspect import prepare_part

    part = parse_part_with_mesh(text.decode("utf-8", errors="replace"), mesh, f"part ({part_name})",
                                f"mesh ({mesh_name})", max_triangles=max_triangles, max_bytes=max_bytes)
    declared = PurePath(part.definition.nominal).suffix.lower()
    uploaded = PurePath(mesh_name or "").suffix.lower()
    if uploaded in MESH_SUFFIXES and uploaded != declared:
        raise InputError(f"mesh: {mesh_name!r} is a {uploaded} file but the part file's nominal "
                         f"{part.definition.nominal!r} is {declared}.")
    try:
        prepare_part(part)
    except ValueError as error:
        raise InputError(f"part ({part_name}): {error}") from None
    return part.name, part.material.name


@router.post("", name="create_part_type", status_code=201, response_model=PartTypeOut,
             responses=problem_responses(413))
async def create_part_type(request: Request, session: SessionDep, runtime: RuntimeDep, key: AdminKey,
                           part: Annotated[UploadFile, File(description="A part file (docs/part-file.md).")],
                           mesh: Annotated[UploadFile, File(description="Its nominal mesh: STL, PLY or OBJ, "
                                                                        "the format its 'nominal' names.")],
                           select_: Annotated[bool, Form(alias="select", description="Make it the station's "
                                                       "selected part type (scans inspect against it).")] = False,
                           idempotency_key: IdempotencyKeyHeader = None):
    """Store a validated part file and its nominal mesh as a part type of this station."""
    text = await read_limited(part, "part", _MAX_PART_BYTES)
    mesh_bytes = await read_limited(mesh, "mesh", _MAX_MESH_BYTES)
    settings = runtime.settings
    name, material = await request.app.state.decoders.run(
        validate_part, text, part.filename, mesh_bytes, mesh.filename, settings.max_mesh_triangles,
        settings.decode_memory_bytes, source=f"mesh ({mesh.filename})")
    part_digest, mesh_digest = runtime.store.put_bytes(text), runtime.store.put_bytes(mesh_bytes)

    def create() -> Outcome:
        part_type = parts.add_part_type(session, name=name, station=runtime.settings.station, material=material,
                                        part_sha256=part_digest, mesh_sha256=mesh_digest, select_=select_)
        out = part_type_out(part_type)
        return Outcome(201, out.model_dump(mode="json"), out.links["self"])

    body = json.dumps({"select": select_}).encode() + hashlib.sha256(text).digest() + hashlib.sha256(mesh_bytes).digest()
    return await run_in_threadpool(respond_once, session, key, idempotency_key, request_digest(request, body), create,
                                   runtime.settings.idempotency_ttl_s)


@router.get("", name="list_part_types")
def list_part_types(session: SessionDep, runtime: RuntimeDep, _: ReaderKey) -> list[PartTypeOut]:
    """This station's part types, newest first."""
    return [part_type_out(part_type) for part_type in parts.station_part_types(session, runtime.settings.station)]


@router.get("/{part_type_id}", name="get_part_type", responses=problem_responses(404))
def get_part_type(part_type: ExistingPartType) -> PartTypeOut:
    return part_type_out(part_type)


@router.get("/{part_type_id}/part.json", name="download_part_file",
            responses={200: {"content": {"application/json": {}}}, **problem_responses(404)})
def download_part_file(part_type: ExistingPartType, runtime: RuntimeDep) -> Response:
    """The part file as uploaded."""
    return Response(stored_bytes(runtime.store, part_type.part_sha256, f"part type {part_type.id}"),
                    media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{part_type.id}-part.json"'})


@router.get("/{part_type_id}/mesh", name="download_part_mesh",
            responses={200: {"content": dict.fromkeys(_MESH_MEDIA_TYPES.values(), {})}, **problem_responses(404)})
def download_part_mesh(part_type: ExistingPartType, runtime: RuntimeDep) -> Response:
    """The nominal mesh as uploaded, named as the part file's ``nominal``."""
    owner = f"part type {part_type.id}"
    nominal = PurePath(json.loads(stored_bytes(runtime.store, part_type.part_sha256, owner))["nominal"]).name
    return Response(stored_bytes(runtime.store, part_type.mesh_sha256, owner),
                    media_type=_MESH_MEDIA_TYPES.get(PurePath(nominal).suffix.lower(), "application/octet-stream"),
                    headers={"Content-Disposition": f'attachment; filename="{nominal}"'})


@router.post("/{part_type_id}/select", name="select_part_type", responses=problem_responses(404))
def select_station_part_type(_: AdminKey, part_type: ExistingPartType, session: SessionDep) -> PartTypeOut:
    """Make this the station's selected part type: scans that name none are inspected against it."""
    parts.select_part_type(session, part_type)
    session.commit()
    return part_type_out(part_type)

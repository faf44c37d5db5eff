"""Uploads decoded in capped child processes (api/decoding.py), and hostile uploads through the API: every
decoder's lying or malformed file is a 413 or 422 problem naming the upload and the limit, never a 500, and
nothing is stored."""

from __future__ import annotations

import asyncio
import os
import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from api.decoding import DecoderPool
from services.errors import InputError
from services.formats.limits import DeclaredSizeError
from services.simulation.presets import forging_rig

PROBLEM = "application/problem+json"


def _returns(value):
    return value


def _raises(kind: str):
    if kind == "input":
        raise InputError("upload.png: not an image")
    if kind == "declared":
        raise DeclaredSizeError("upload.png: declares 9 pixels, more than the limit of 4")
    if kind == "cv2":
        cv2.imdecode(np.zeros(0, np.uint8), cv2.IMREAD_UNCHANGED)  # empty buffer: cv2.error
    if kind == "memory":
        return np.ones(1 << 31, np.uint8).sum()  # 2 GiB against a 256 MiB cap
    if kind == "abort":
        os.abort()
    if kind == "slow":
        time.sleep(30)  # the test: a decoding that outlasts its time limit
    raise AssertionError(kind)


@pytest.fixture(scope="module")
def pool():
    return DecoderPool(processes=2, memory_bytes=256 << 20, timeout_s=3.0)


def _run(pool, function, *args):
    return asyncio.run(pool.run(function, *args, source="upload.png"))


def test_a_decoding_runs_in_a_child_process_and_answers(pool):
    assert _run(pool, _returns, {"width": 8}) == {"width": 8}
    assert _run(pool, os.getpid) != os.getpid()


@pytest.mark.parametrize(("kind", "error", "message"), [
    ("input", InputError, "^upload.png: not an image$"),
    ("declared", DeclaredSizeError, "more than the limit of 4"),
    ("cv2", InputError, r"^upload.png: cannot be decoded \(error: .*"),
    ("memory", InputError, r"^upload.png: cannot be decoded \(it needs more than the memory limit of 268,435,456 "
                           r"bytes\)$"),
    ("abort", InputError, r"^upload.png: cannot be decoded \(the decoder stopped \(signal SIGABRT\)"),
    ("slow", InputError, r"^upload.png: cannot be decoded \(it took longer than 3 s\)$"),
])
def test_whatever_goes_wrong_in_a_decoding_is_an_input_error_naming_the_upload(pool, kind, error, message):
    with pytest.raises(error, match=message) as raised:
        _run(pool, _raises, kind)
    assert type(raised.value) is error


def test_no_process_to_decode_in_is_503_with_retry_after(pool, monkeypatch):
    from api.problems import Problem

    def refuse(self):
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(type(pool._context.Process(target=print)), "start", refuse)
    with pytest.raises(Problem) as raised:
        _run(pool, _returns, 1)
    assert raised.value.status == 503 and raised.value.kind == "decoding-unavailable"
    assert int(raised.value.headers["Retry-After"]) > 0 and "upload.png" in raised.value.detail


def test_decodings_beyond_the_pool_wait_their_turn():
    pool = DecoderPool(processes=1, memory_bytes=64 << 20, timeout_s=10.0)

    async def three():
        return await asyncio.gather(*(pool.run(_sleep_and_time, 0.3, source="x") for _ in range(3)))

    spans = sorted(asyncio.run(three()))
    assert all(later[0] >= earlier[1] for earlier, later in zip(spans, spans[1:])), spans  # never overlapping


def _sleep_and_time(seconds: float) -> tuple[float, float]:
    start = time.time()
    time.sleep(seconds)  # the test: a decoding that holds its process this long
    return start, time.time()


def _png_declaring(width: int, height: int) -> bytes:
    content = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    content[16:24] = struct.pack(">II", width, height)
    content[29:33] = struct.pack(">I", zlib.crc32(bytes(content[12:29])))
    return bytes(content)


def _bmp_declaring(width: int, height: int) -> bytes:
    content = bytearray(cv2.imencode(".bmp", np.zeros((8, 8), np.uint8))[1].tobytes())
    content[18:26] = struct.pack("<ii", width, height)
    return bytes(content)


def _tiff_declaring(width: int, height: int) -> bytes:
    import io

    import tifffile

    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.zeros((8, 8), np.uint16))
    content = bytearray(buffer.getvalue())
    with tifffile.TiffFile(io.BytesIO(buffer.getvalue())) as tiff:
        tags = tiff.pages.first.tags
        for tag, value in (("ImageWidth", width), ("ImageLength", height)):
            content[tags[tag].valueoffset:tags[tag].valueoffset + 2] = struct.pack("<H", value)
    return bytes(content)


THERMAL = forging_rig().devices["thermal"]
HOSTILE_IMAGES = {
    "30000x30000 PNG (IHDR)": ("bomb.png", _png_declaring(30000, 30000), 413, "more than the limit of"),
    "PNG of another size": ("small.png", _png_declaring(64, 48), 422, "but the device filming it is"),
    "PNG cut after its header": ("cut.png", _png_declaring(THERMAL.width, THERMAL.height)[:60], 422, "cut.png"),
    "BMP whose rows are not there": ("lying.bmp", _bmp_declaring(4000, 3000), 422, "but holds only"),
    "65535x65535 TIFF": ("giga.tiff", _tiff_declaring(65535, 65535), 422, "but holds only"),
    "TIFF of random bytes": ("noise.tiff", b"II*\0" + bytes(range(256)) * 4, 422, "noise.tiff"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_IMAGES))
def test_hostile_board_images_are_problems_naming_the_file(client, auth, runtime, active_calibration, case):
    name, content, status, message = HOSTILE_IMAGES[case]
    rig = forging_rig()
    camera = cv2.imencode(".png", np.zeros((rig.devices["camera"].height, rig.devices["camera"].width),
                                           np.uint8))[1].tobytes()
    files = [("board", ("board.json", '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25}'))]
    files += [("reference_images", (f"c{i}.png", camera)) for i in range(3)]
    thermal = cv2.imencode(".png", np.zeros((THERMAL.height, THERMAL.width), np.uint16))[1].tobytes()
    files += [("device_images", (name, content) if i == 1 else (f"t{i}.png", thermal)) for i in range(3)]
    stored = sum(1 for _ in runtime.store.blobs())
    response = client.post(f"/v1/calibration-sets/{active_calibration}/stereo", headers=auth["admin"], files=files,
                           data={"name": "hostile"})
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM and message in response.json()["detail"], response.text
    assert name in response.json()["detail"] and response.json()["detail"].startswith("device_images")
    assert sum(1 for _ in runtime.store.blobs()) == stored


@pytest.fixture
def active_calibration(client, auth):
    from services.formats.rig import rig_to_json

    created = client.post("/v1/calibration-sets", headers=auth["admin"],
                          files={"rig": ("rig.json", rig_to_json(forging_rig()))}, data={"name": "rig"})
    return created.json()["calibration_set_id"]


def _ply(vertices: int, faces: int, body: bytes) -> bytes:
    return (f"ply\nformat binary_little_endian 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
            ).encode() + body


HOSTILE_MESHES = {
    "PLY declaring 10^8 vertices in 1.2 kB": (".ply", _ply(10**8, 10**8, bytes(1000)), 422, "but holds only"),
    "PLY declaring 10^9 vertices": (".ply", _ply(10**9, 1, bytes(1000)), 422, "1,000,000,000 vertex"),
    "PLY over the triangle limit": (".ply", _ply(3, 2000, struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
                                                + struct.pack("<B3i", 3, 0, 1, 2) * 2000), 413,
                                    "more than the limit of 1,000"),
    "binary STL lying about its count": (".stl", bytes(80) + struct.pack("<I", 10**9) + bytes(500), 422,
                                         "but holds only 584 bytes"),
    "STL over the triangle limit": (".stl", bytes(80) + struct.pack("<I", 1001) + bytes(50 * 1001), 413,
                                    "1,001 triangles (STL)"),
    "OBJ over the triangle limit": (".obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 1001, 413,
                                    "1,001 triangles (OBJ)"),
    "PLY of random bytes after a good header": (".ply", _ply(3, 1, bytes(range(256)) * 2), 422, "mesh (nominal.ply)"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_MESHES))
def test_hostile_meshes_are_problems_naming_the_file(client, auth, runtime, case):
    import json

    suffix, content, status, message = HOSTILE_MESHES[case]
    runtime.settings = runtime.settings.model_copy(update={"max_mesh_triangles": 1000})
    part = {"version": 1, "name": "hostile", "material": "carbon-steel", "nominal": f"nominal{suffix}",
            "surface_tolerance": [-1, 1]}
    response = client.post("/v1/part-types", headers=auth["admin"],
                           files={"part": ("part.json", json.dumps(part)),
                                  "mesh": (f"nominal{suffix}", content, "application/octet-stream")})
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM and message in response.json()["detail"], response.text
    assert f"nominal{suffix}" in response.json()["detail"]
    assert sum(1 for _ in runtime.store.blobs()) == 0

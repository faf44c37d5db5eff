"""Declared sizes checked before decoding (services/formats/limits.py): for every decoder of user data, files
whose header lies about their size (Hypothesis draws the declared sizes) are refused by the header check,
naming the file, as lying (``InputError``) or too large (``DeclaredSizeError``); malformed ones decode or
raise ``InputError``, never a library's exception."""

from __future__ import annotations

import io
import math
import struct
import tempfile
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device_gateway.transfer import decode_capture
from services.errors import InputError
from services.formats.images import decode_image, read_frame
from services.formats.limits import (DeclaredSizeError, check_declared, check_image, check_mesh, check_npy,
                                     check_npz, image_header)
from services.formats.part import read_mesh
from services.formats.ply import cloud_from_ply, cloud_to_ply

LYING = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
MAX_PIXELS = 1 << 16
DIMENSIONS = st.integers(1, (1 << 31) - 1)
COUNTS = st.integers(0, 10**12)


def _image(suffix: str, shape=(6, 8), dtype=np.uint8) -> bytes:
    return cv2.imencode(suffix, np.arange(np.prod(shape), dtype=dtype).reshape(shape))[1].tobytes()


def _refused_or_decoded(content: bytes, width: int, height: int) -> None:
    """What a decoder must do with a header declaring ``width`` x ``height``: refuse it beyond the budget
    (413-kind, naming the file and the limit) before decoding, else decode it or refuse it as invalid."""
    try:
        image = decode_image(content, "upload.img", max_pixels=MAX_PIXELS)
    except DeclaredSizeError as error:
        assert width * height > MAX_PIXELS and str(error).startswith("upload.img: declares") and \
            f"{MAX_PIXELS:,}" in str(error), str(error)
        return
    except InputError as error:
        assert str(error).startswith("upload.img"), str(error)
        return
    assert width * height <= MAX_PIXELS and image.shape == (height, width)


def _png_declaring(width: int, height: int, depth: int = 8, colour: int = 0) -> bytes:
    """A small PNG whose IHDR declares ``width`` x ``height`` (with a correct CRC: only the size lies)."""
    content = bytearray(_image(".png"))
    fields = struct.pack(">IIBB", width, height, depth, colour) + bytes(content[26:29])
    content[16:29] = fields
    content[29:33] = struct.pack(">I", zlib.crc32(b"IHDR" + fields))
    return bytes(content)


@LYING
@given(width=DIMENSIONS, height=DIMENSIONS, depth=st.sampled_from([1, 8, 16]), colour=st.sampled_from([0, 2, 6]))
def test_png_declaring_any_size(width, height, depth, colour):
    _refused_or_decoded(_png_declaring(width, height, depth, colour), width, height)


def test_a_png_decompression_bomb_is_refused_by_its_header_before_it_is_inflated():
    bomb = cv2.imencode(".png", np.zeros((3000, 3000), np.uint8))[1].tobytes()  # 9 MP of zeros in a few kB
    assert len(bomb) < 20_000
    with pytest.raises(DeclaredSizeError, match=r"bomb.png: declares 9,000,000 pixels \(3000x3000 PNG\), more than "
                                                r"the limit of 65,536"):
        decode_image(bomb, "bomb.png", max_pixels=MAX_PIXELS)
    header = check_image(bomb, "bomb.png", max_pixels=10_000_000)
    assert (header.width, header.height, header.decoded_bytes) == (3000, 3000, 9_000_000)
    with pytest.raises(DeclaredSizeError, match="bytes decoded"):
        check_image(bomb, "bomb.png", max_pixels=10_000_000, max_bytes=1 << 20)
    with pytest.raises(InputError, match="bomb.png: is 3000x3000 but the device filming it is 1280x800"):
        check_image(bomb, "bomb.png", max_pixels=10_000_000, size=(1280, 800))


@LYING
@given(width=st.integers(-(1 << 31), (1 << 31) - 1), height=st.integers(-(1 << 31), (1 << 31) - 1),
       bits=st.sampled_from([1, 8, 24, 32]))
def test_bmp_declaring_any_size(width, height, bits):
    content = bytearray(_image(".bmp"))
    content[18:26] = struct.pack("<ii", width, height)
    content[28:30] = struct.pack("<H", bits)
    _refused_or_decoded(bytes(content), width, abs(height))


def test_an_uncompressed_bmp_shorter_than_its_rows_is_refused_as_lying():
    content = bytearray(_image(".bmp", (60, 80)))
    content[18:26] = struct.pack("<ii", 4000, 3000)
    with pytest.raises(InputError, match=r"cut.bmp: declares a 4000x3000 image of 8 bits per pixel, at least "
                                         r"12,000,000 bytes, but holds only"):
        check_image(bytes(content), "cut.bmp", max_pixels=1 << 30)


def _tiff(compression=None) -> tuple[bytes, int, int]:
    """A small TIFF and the file offsets of its ImageWidth and ImageLength values."""
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.arange(48, dtype=np.uint16).reshape(6, 8), compression=compression)
    with tifffile.TiffFile(io.BytesIO(buffer.getvalue())) as tiff:
        tags = tiff.pages.first.tags
        return buffer.getvalue(), tags["ImageWidth"].valueoffset, tags["ImageLength"].valueoffset


@LYING
@given(width=st.integers(1, 65535), height=st.integers(1, 65535), compression=st.sampled_from([None, "zlib"]))
def test_tiff_declaring_any_size(width, height, compression):
    content, width_at, height_at = _tiff(compression)
    content = bytearray(content)
    content[width_at:width_at + 2] = struct.pack("<H", width)
    content[height_at:height_at + 2] = struct.pack("<H", height)
    _refused_or_decoded(bytes(content), width, height)


def test_a_tiff_claiming_ten_gigapixels_is_refused_before_opencv_sees_it():
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.zeros((4, 4), np.uint8))
    content, width_at, height_at = bytearray(buffer.getvalue()), *_offsets(buffer.getvalue())
    content[width_at:width_at + 2] = struct.pack("<H", 65535)
    content[height_at:height_at + 2] = struct.pack("<H", 65535)
    with pytest.raises(InputError, match=r"giga.tiff: declares a 65535x65535 image of 1 uint8 samples per pixel, "
                                         r"at least 4,294,836,225 bytes, but holds only 16 bytes"):
        decode_image(bytes(content), "giga.tiff")
    compressed = io.BytesIO()  # compressed: its length says nothing, its pixels are over the budget
    tifffile.imwrite(compressed, np.zeros((6000, 6000), np.uint8), compression="zlib")
    with pytest.raises(DeclaredSizeError, match=r"giga.tiff: declares 36,000,000 pixels \(6000x6000 TIFF\)"):
        decode_image(compressed.getvalue(), "giga.tiff")


def _offsets(content: bytes) -> tuple[int, int]:
    with tifffile.TiffFile(io.BytesIO(content)) as tiff:
        tags = tiff.pages.first.tags
        return tags["ImageWidth"].valueoffset, tags["ImageLength"].valueoffset


@LYING
@given(width=st.integers(1, 65535), height=st.integers(1, 65535))
def test_jpeg_declaring_any_size(width, height):
    content = bytearray(_image(".jpg", (16, 16)))
    sof = next(i for i in range(2, len(content) - 1) if content[i] == 0xFF and content[i + 1] == 0xC0)
    content[sof + 5:sof + 9] = struct.pack(">HH", height, width)
    _refused_or_decoded(bytes(content), width, height)


@settings(max_examples=100, deadline=None)
@given(content=st.binary(max_size=200))
def test_any_bytes_are_an_image_or_an_input_error(content):
    for prefix in (b"", b"\x89PNG\r\n\x1a\n", b"BM", b"II*\0", b"\xff\xd8"):
        try:
            image_header(prefix + content, "upload")
        except InputError as error:
            assert str(error).startswith("upload"), str(error)


def test_read_frame_checks_the_header_too(tmp_path):
    (tmp_path / "bomb.png").write_bytes(cv2.imencode(".png", np.zeros((300, 300), np.uint8))[1].tobytes())
    with pytest.raises(DeclaredSizeError, match="bomb.png: declares 90,000 pixels"):
        read_frame(tmp_path / "bomb.png", max_pixels=10_000)
    assert read_frame(tmp_path / "bomb.png").shape == (300, 300)


def _ply_declaring(vertices: int, faces: int, body: bytes, format_: str = "binary_little_endian") -> bytes:
    return (f"ply\nformat {format_} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
            ).encode() + body


@LYING
@given(vertices=COUNTS, faces=COUNTS, body=st.binary(max_size=200),
       format_=st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
def test_ply_declaring_any_counts(vertices, faces, body, format_):
    content = _ply_declaring(vertices, faces, body, format_)
    per_vertex, per_face = (6, 2) if format_ == "ascii" else (12, 1)
    for read in (lambda: check_mesh(content, ".ply", "mesh.ply", max_triangles=1000),
                 lambda: cloud_from_ply(content, "mesh.ply")):
        try:
            read()
        except DeclaredSizeError as error:
            assert faces > 1000 and "more than the limit of 1,000" in str(error), str(error)
        except InputError as error:
            assert str(error).startswith("mesh.ply"), str(error)
            if vertices * per_vertex + faces * per_face > len(body):
                assert "but holds only" in str(error), str(error)


def test_a_ply_declaring_a_hundred_million_vertices_in_a_kilobyte_is_refused_before_open3d_reads_it(tmp_path):
    path = tmp_path / "lying.ply"
    path.write_bytes(_ply_declaring(10**8, 1, bytes(1000)))
    with pytest.raises(InputError, match=r"mesh: lying.ply: declares 100,000,000 vertex, 1 face, at least "
                                         r"1,200,000,001 bytes, but holds only 1,000 bytes"):
        read_mesh(path, "mesh", "lying.ply")


@LYING
@given(count=st.integers(0, (1 << 32) - 1), extra=st.integers(-84, 200))
def test_binary_stl_declaring_any_count(count, extra, tmp_path_factory):
    length = max(0, min(84 + 50 * min(count, 4) + extra, 10_000))
    content = bytearray(length)
    if length >= 84:
        content[80:84] = struct.pack("<I", count)
    path = tmp_path_factory.mktemp("stl") / "mesh.stl"
    path.write_bytes(bytes(content))
    try:
        read_mesh(path, "mesh", "mesh.stl", max_triangles=1000)
    except DeclaredSizeError as error:
        assert count > 1000 and 84 + 50 * count == length, str(error)
    except InputError as error:
        assert str(error).startswith("mesh: mesh.stl"), str(error)


def test_mesh_triangles_over_the_limit_are_refused_413_kind(tmp_path):
    triangle = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 11
    with pytest.raises(DeclaredSizeError, match=r"mesh.obj: declares 11 triangles \(OBJ\), more than the limit of 10"):
        check_mesh(triangle, ".obj", "mesh.obj", max_triangles=10)
    stl = bytes(80) + struct.pack("<I", 20) + bytes(50 * 20)
    with pytest.raises(DeclaredSizeError, match=r"mesh.stl: declares 20 triangles \(STL\)"):
        check_mesh(stl, ".stl", "mesh.stl", max_triangles=10)
    with pytest.raises(DeclaredSizeError, match="bytes to read the mesh into"):
        check_mesh(stl, ".stl", "mesh.stl", max_bytes=1000)
    assert check_mesh(stl, ".stl", "mesh.stl").triangles == 20


def _npy(shape, dtype) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                  "fortran_order": False, "shape": shape})
    return buffer.getvalue()


@LYING
@given(shape=st.lists(st.integers(0, 10**6), max_size=4).map(tuple),
       dtype=st.sampled_from(["uint8", "uint16", "float32", "float64", "complex128"]), body=st.binary(max_size=300))
def test_npy_declaring_any_shape(shape, dtype, body):
    content = _npy(shape, dtype) + body
    needed = math.prod(shape) * np.dtype(dtype).itemsize
    try:
        check_npy(io.BytesIO(content), len(content), "frames.npy", max_bytes=1 << 20)
    except DeclaredSizeError as error:
        assert needed > 1 << 20 and "frames.npy: declares" in str(error), str(error)
        return
    except InputError as error:
        assert needed > len(body) and "frames.npy: declares" in str(error) and "holds only" in str(error), str(error)
        return
    assert needed <= len(body)
    assert np.load(io.BytesIO(content)).shape == shape  # what passed the check loads


def test_object_arrays_are_refused():
    content = _npy((2,), object) + b"\0" * 16
    with pytest.raises(InputError, match="a.npy: a NumPy array of Python objects"):
        check_npy(io.BytesIO(content), len(content), "a.npy")


def _npz(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return buffer.getvalue()


def test_a_capture_archive_with_a_lying_member_is_refused_before_numpy_reads_it():
    frames = _npy((1000, 4000, 3000), "uint16") + bytes(64)  # declares 24 GB in 64 bytes
    archive = _npz({"frames.npy": frames, "metadata.npy": _npy((2,), "uint8") + b"{}"})
    with pytest.raises(InputError, match=r"frames.npy: declares a 1000x4000x3000 uint16 array"):
        check_npz(archive, "capture.npz", max_bytes=1 << 40)
    with pytest.raises(ValueError, match=r"not a capture archive: .*frames.npy: declares 24,000,000,000 bytes"):
        decode_capture(archive)
    deflated = io.BytesIO()  # a zip bomb: 100 MB of zeros deflated to 100 kB, beyond an archive's own length
    with zipfile.ZipFile(deflated, "w", zipfile.ZIP_DEFLATED) as bomb:
        bomb.writestr("frames.npy", _npy((100_000_000,), "uint8") + bytes(100_000_000))
    with pytest.raises(DeclaredSizeError, match="capture.npz: declares 100,000,128 bytes in its members"):
        check_npz(deflated.getvalue(), "capture.npz", max_bytes=len(deflated.getvalue()))
    with pytest.raises(InputError, match="capture.npz: not an .npz"):
        check_npz(b"PK junk", "capture.npz")


def test_check_declared_names_the_file_and_the_limit():
    check_declared(10, 10, "f", "things")
    with pytest.raises(DeclaredSizeError, match=r"^f: declares 11 things, more than the limit of 10$"):
        check_declared(11, 10, "f", "things")


def test_valid_files_pass_their_checks(tmp_path):
    for suffix in (".png", ".bmp", ".tiff", ".jpg"):
        header = check_image(_image(suffix), f"a{suffix}", size=(8, 6))
        assert (header.width, header.height) == (8, 6), suffix
    ply = cloud_to_ply({"x": np.arange(5, dtype=np.float32)})
    assert len(cloud_from_ply(ply, "a.ply")) == 5
    with tempfile.TemporaryDirectory() as directory:
        array = Path(directory) / "a.npy"
        np.save(array, np.zeros((3, 4), np.float32))
        with open(array, "rb") as stream:
            assert check_npy(stream, array.stat().st_size, "a.npy") == ((3, 4), np.dtype(np.float32))

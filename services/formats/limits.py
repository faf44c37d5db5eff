"""What a file declares, read from its header before anything is decoded, checked against its length and
the configured limits.

A file of a few kilobytes can declare a 30000 x 30000 image or 10^9 vertices, and a decoder allocates what
the header says before it finds out the data are not there. Every decoder of user data calls one of these
first: a file whose declared content cannot fit in its own length is refused as lying (``InputError``, a
422), one whose declared content exceeds a limit as too large (:class:`DeclaredSizeError`, a 413). Both
messages name the file and the limit.

The headers are parsed here by hand (a few struct fields each) rather than by the decoding libraries,
because those allocate the declared size as they open the file; tifffile is the exception: it reads a
TIFF's directories without reading its pixels, and is used for TIFF.
"""

from __future__ import annotations

import io
import logging
import math
import struct
import zipfile
from dataclasses import dataclass

import numpy as np

from services.errors import InputError

DEFAULT_MAX_PIXELS = 1 << 25  # 33.5 megapixels: the largest frame a station camera gives, with room
DEFAULT_MAX_TRIANGLES = 10_000_000
DEFAULT_MAX_ARRAY_BYTES = 1 << 30

_PLY_TYPE_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2,
                   "uint16": 2, "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4,
                   "double": 8, "float64": 8}
_PLY_MAX_HEADER_BYTES = 1 << 16


class DeclaredSizeError(InputError):
    """A file declares more than a configured limit allows (the API answers 413 payload-too-large)."""


def check_declared(amount: int, limit: int, source: str, what: str, unit: str = "") -> None:
    """Refuse ``amount`` of ``what`` beyond ``limit`` with a :class:`DeclaredSizeError` naming ``source``.

    The one place a declared size meets its limit; a decoder that reads its own header (e.g. a radiometric
    JPEG's raw thermal block) calls it with what the header says before allocating.
    """
    if amount > limit:
        raise DeclaredSizeError(f"{source}: declares {amount:,} {what}{unit}, more than the limit of "
                                f"{limit:,}{unit}")


def check_fits(needed: int, available: int, source: str, declared: str) -> None:
    """Refuse a file whose declared content needs ``needed`` bytes but which holds only ``available``."""
    if needed > available:
        raise InputError(f"{source}: declares {declared}, at least {needed:,} bytes, but holds only "
                         f"{available:,} bytes (a cut or lying file)")


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header declares: its size, channels as decoded and bytes per sample."""

    format: str
    width: int
    height: int
    channels: int
    bytes_per_sample: int

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoded image (OpenCV, ``IMREAD_UNCHANGED``)."""
        return self.width * self.height * self.channels * self.bytes_per_sample


def image_header(content: bytes, source: str) -> ImageHeader:
    """The header of a PNG, BMP or TIFF image; ``InputError`` naming ``source`` for any other bytes, or a
    header that cannot be true of the file (data shorter than the pixels need, for uncompressed data)."""
    if content.startswith(b"\x89PNG\r\n\x1a\n"):
        return _png_header(content, source)
    if content.startswith(b"BM"):
        return _bmp_header(content, source)
    if content[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
        return _tiff_header(content, source)
    if content.startswith(b"\xff\xd8"):
        return _jpeg_header(content, source)
    raise InputError(f"{source}: cannot read the frame (not a readable PNG, BMP, TIFF or JPEG image; it begins "
                     f"{content[:8]!r})")


def check_image(content: bytes, source: str, *, max_pixels: int = DEFAULT_MAX_PIXELS,
                size: tuple[int, int] | None = None, max_bytes: int | None = None) -> ImageHeader:
    """Check an image's header before it is decoded: its width x height against ``max_pixels``, against the
    device's ``size`` (width, height) when given, and its decoded bytes against ``max_bytes`` (a memory
    budget) when given.

    Raises
    ------
    InputError
        Naming ``source``: not an image, a lying header, or another size than ``size``.
    DeclaredSizeError
        Naming ``source`` and the limit: more pixels than ``max_pixels`` or more bytes than ``max_bytes``.
    """
    header = image_header(content, source)
    if header.width <= 0 or header.height <= 0:
        raise InputError(f"{source}: declares an empty {header.width}x{header.height} image")
    check_declared(header.width * header.height, max_pixels, source,
                   f"pixels ({header.width}x{header.height} {header.format})")
    if size is not None and (header.width, header.height) != tuple(size):
        raise InputError(f"{source}: is {header.width}x{header.height} but the device filming it is "
                         f"{size[0]}x{size[1]}")
    if max_bytes is not None:
        check_declared(header.decoded_bytes, max_bytes, source, "bytes decoded", "")
    return header


def _png_header(content: bytes, source: str) -> ImageHeader:
    if len(content) < 33 or content[12:16] != b"IHDR":
        raise InputError(f"{source}: a PNG whose first chunk is not IHDR (cut or corrupt)")
    width, height, depth, colour = struct.unpack(">IIBB", content[16:26])
    channels = {0: 1, 2: 3, 3: 3, 4: 4, 6: 4}.get(colour)  # as OpenCV decodes: palette to BGR, grey+alpha to BGRA
    if channels is None or depth not in (1, 2, 4, 8, 16):
        raise InputError(f"{source}: a PNG with colour type {colour} and bit depth {depth}, which PNG does not have")
    return ImageHeader("PNG", width, height, channels, 2 if depth == 16 else 1)


_JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # SOF0..SOF15 but DHT, JPG, DAC


def _jpeg_header(content: bytes, source: str) -> ImageHeader:
    """The frame header (SOF) of a JPEG: the segments before it are skipped by their lengths."""
    position = 2
    while position + 4 <= len(content):
        if content[position] != 0xFF:
            break
        marker = content[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        (length,) = struct.unpack(">H", content[position + 2:position + 4])
        if marker in _JPEG_FRAME_MARKERS and position + 10 <= len(content):
            precision, height, width, components = struct.unpack(">BHHB", content[position + 4:position + 10])
            return ImageHeader("JPEG", width, height, 1 if components == 1 else 3, 2 if precision > 8 else 1)
        position += 2 + length
    raise InputError(f"{source}: a JPEG without a frame header (cut or corrupt)")


def _bmp_header(content: bytes, source: str) -> ImageHeader:
    if len(content) < 26:
        raise InputError(f"{source}: a BMP cut within its header")
    (offset,) = struct.unpack("<I", content[10:14])
    (dib_size,) = struct.unpack("<I", content[14:18])
    if dib_size == 12:  # BITMAPCOREHEADER
        width, height, _, bits = struct.unpack("<hhHH", content[18:26])
        compression = 0
    elif dib_size >= 40 and len(content) >= 34:
        width, height, _, bits, compression = struct.unpack("<iiHHI", content[18:34])
    else:
        raise InputError(f"{source}: a BMP with an unknown header of {dib_size} bytes")
    height = abs(height)  # negative: rows stored top-down
    if bits not in (1, 2, 4, 8, 16, 24, 32):
        raise InputError(f"{source}: a BMP of {bits} bits per pixel, which BMP does not have")
    if compression in (0, 3) and width > 0:  # uncompressed (or bit fields): the rows must be in the file
        stride = (width * bits + 31) // 32 * 4
        check_fits(stride * height, len(content) - min(offset, len(content)), source,
                   f"a {width}x{height} image of {bits} bits per pixel")
    return ImageHeader("BMP", width, height, 4 if bits == 32 else 3, 1)


def _tiff_header(content: bytes, source: str) -> ImageHeader:
    import tifffile

    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # it logs what it finds wrong; the error below says it once
    try:
        with tifffile.TiffFile(io.BytesIO(content)) as tiff:  # reads the first directory, not the pixels
            page = tiff.pages.first
            shape, dtype = tuple(int(n) for n in page.shape), page.dtype
            compression, byte_counts = int(page.compression), page.databytecounts
    except Exception as error:  # tifffile raises several types for a malformed directory
        raise InputError(f"{source}: not a readable TIFF ({type(error).__name__}: {error})") from None
    finally:
        logger.setLevel(level)
    if dtype is None or len(shape) < 2:
        raise InputError(f"{source}: a TIFF whose first page has no image data (shape {shape})")
    samples = int(np.prod(shape[2:])) if len(shape) > 2 else 1
    if len(shape) > 2 and shape[-1] > 4 and shape[0] <= 4:  # planar samples first
        height, width, samples = shape[1], shape[2], shape[0]
    else:
        height, width = shape[0], shape[1]
    header = ImageHeader("TIFF", width, height, samples, dtype.itemsize)
    if compression == 1:  # uncompressed: the strips must hold every pixel
        check_fits(header.decoded_bytes, min(sum(byte_counts), len(content)), source,
                   f"a {width}x{height} image of {samples} {dtype} samples per pixel")
    return header


@dataclass(frozen=True)
class MeshHeader:
    """What a mesh file declares: its vertex and triangle counts (``None`` where the format does not say)."""

    format: str
    vertices: int | None
    triangles: int

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the mesh as read: Open3D's double vertices and int triangles, the float64/int32 copies
        made of them, and Open3D's vectors growing by doubling while it reads (hence 2 x 2)."""
        vertices = self.vertices if self.vertices is not None else 3 * self.triangles
        return 4 * (24 * vertices + 12 * self.triangles)


def check_mesh(content: bytes, suffix: str, source: str, *, max_triangles: int = DEFAULT_MAX_TRIANGLES,
               max_bytes: int | None = None) -> MeshHeader:
    """Check a triangle mesh (``suffix`` ``.stl``, ``.ply`` or ``.obj``) before it is read: the counts its
    header declares against the file's length, its triangles against ``max_triangles`` and, when given, the
    memory reading it takes against ``max_bytes``.

    Raises
    ------
    InputError
        Naming ``source``: a header that cannot be parsed or declares more than the file holds.
    DeclaredSizeError
        Naming ``source`` and the limit: too many triangles, or more memory than ``max_bytes``.
    """
    suffix = suffix.lower()
    if suffix == ".ply":
        header = ply_header(content, source)
        faces = header.counts.get("face", 0)
        mesh = MeshHeader("PLY", header.counts.get("vertex", 0), faces)
    elif suffix == ".stl":
        mesh = _stl_header(content, source)
    elif suffix == ".obj":
        # a text format: what it declares is what it holds, so only the faces are counted, one triangle a
        # face line (a polygon of n corners makes n - 2: a lower bound, counted without parsing)
        faces = content.count(b"\nf ") + content.startswith(b"f ")
        mesh = MeshHeader("OBJ", content.count(b"\nv ") + content.startswith(b"v "), faces)
    else:
        raise InputError(f"{source}: a mesh must be STL, PLY or OBJ, not {suffix or 'a file without a suffix'}")
    check_declared(mesh.triangles, max_triangles, source, f"triangles ({mesh.format})")
    if max_bytes is not None:
        check_declared(mesh.decoded_bytes, max_bytes, source, "bytes to read the mesh into")
    return mesh


def _stl_header(content: bytes, source: str) -> MeshHeader:
    if len(content) >= 84:
        (count,) = struct.unpack("<I", content[80:84])
        if 84 + 50 * count == len(content):
            return MeshHeader("STL", None, count)
    if content[:1024].lstrip()[:5].lower() == b"solid":  # ASCII: each triangle closes with "endfacet"
        return MeshHeader("STL", None, content.count(b"endfacet"))
    if len(content) < 84:
        raise InputError(f"{source}: an STL cut within its 84-byte header ({len(content)} bytes)")
    check_fits(84 + 50 * count, len(content), source, f"{count:,} triangles")
    raise InputError(f"{source}: declares {count:,} triangles, {84 + 50 * count:,} bytes, but holds "
                     f"{len(content):,} bytes (a binary STL is exactly 84 + 50 bytes per triangle)")


@dataclass(frozen=True)
class PlyHeader:
    """A PLY header: its format, each element's declared count, and the header's length in bytes."""

    format: str
    counts: dict[str, int]
    length: int


def ply_header(content: bytes, source: str) -> PlyHeader:
    """Parse a PLY header and check that the body can hold what it declares: in a binary PLY each element
    takes at least its scalar properties' bytes and each list's count, in an ASCII PLY at least two
    characters a property (a digit and a separator).

    Raises
    ------
    InputError
        Naming ``source``: no PLY header, a malformed one, or one declaring more than the file holds.
    """
    end = content.find(b"end_header", 0, _PLY_MAX_HEADER_BYTES)
    if not content.startswith(b"ply") or end < 0:
        raise InputError(f"{source}: not a readable PLY file (no 'ply' ... 'end_header' header within "
                         f"{_PLY_MAX_HEADER_BYTES} bytes)")
    newline = content.find(b"\n", end)
    length = len(content) if newline < 0 else newline + 1
    format_, elements = None, []  # [name, count, minimum bytes or characters of one]
    for line in content[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            format_ = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append([words[1], int(words[2]), 0])
        elif words[0] == "property" and elements and len(words) in (3, 5):
            sizes = [_PLY_TYPE_SIZES.get(word) for word in (words[1:2] if len(words) == 3 else words[2:4])]
            if None in sizes or (len(words) == 5 and words[1] != "list"):
                raise InputError(f"{source}: PLY property line {line.strip()!r} has an unknown type")
            elements[-1][2] += sizes[0] if format_ != "ascii" else 2
        else:
            raise InputError(f"{source}: PLY header line {line.strip()!r} is malformed")
    if format_ not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{source}: PLY format {format_!r} is not ascii or binary")
    needed = sum(count * size for _, count, size in elements)
    declared = ", ".join(f"{count:,} {name}" for name, count, _ in elements)
    check_fits(needed, len(content) - length, source, declared or "no elements")
    return PlyHeader(format_, {name: count for name, count, _ in elements}, length)


def check_npy(stream: io.IOBase, available: int, source: str, *,
              max_bytes: int = DEFAULT_MAX_ARRAY_BYTES) -> tuple[tuple[int, ...], np.dtype]:
    """Check the header of a ``.npy`` array at ``stream``'s position, of which ``available`` bytes remain:
    no Python objects, the data it declares within the bytes left and within ``max_bytes``. The stream is
    left after the header; returns the array's (shape, dtype).

    Raises
    ------
    InputError
        Naming ``source``: not an ``.npy`` header, an object array, or declared data longer than the file.
    DeclaredSizeError
        Naming ``source`` and the limit: declared data beyond ``max_bytes``.
    """
    start = stream.tell()
    try:
        version = np.lib.format.read_magic(stream)
        reader = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in reader:
            raise ValueError(f"version {version} is not 1.0 or 2.0")
        shape, _, dtype = reader[version](stream)
    except (ValueError, OSError, SyntaxError, TypeError) as error:
        raise InputError(f"{source}: not a NumPy .npy array ({error})") from None
    if dtype.hasobject:
        raise InputError(f"{source}: a NumPy array of Python objects, which is not read")
    nbytes = math.prod(shape) * dtype.itemsize
    declared = f"a {'x'.join(map(str, shape)) or 'scalar'} {dtype} array"
    check_declared(nbytes, max_bytes, source, f"bytes ({declared})")
    check_fits(nbytes, available - (stream.tell() - start), source, declared)
    return shape, dtype


def check_npz(content: bytes, source: str, *, max_bytes: int = DEFAULT_MAX_ARRAY_BYTES) -> None:
    """Check an ``.npz`` archive before ``np.load`` reads it: every member's declared size and, for each
    ``.npy`` member, its header (:func:`check_npy`); the members together within ``max_bytes``.

    Raises
    ------
    InputError
        Naming ``source`` (and the member): not a zip archive, or a member whose header lies.
    DeclaredSizeError
        Naming ``source`` and the limit: members declaring more than ``max_bytes`` in all.
    """
    try:
        archive = zipfile.ZipFile(io.BytesIO(content))
    except (zipfile.BadZipFile, OSError, ValueError) as error:
        raise InputError(f"{source}: not an .npz (zip) archive ({error})") from None
    with archive:
        members = archive.infolist()
        check_declared(sum(member.file_size for member in members), max_bytes, source, "bytes in its members")
        for member in members:
            name = f"{source}: {member.filename}"
            if member.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise InputError(f"{name}: compressed with method {member.compress_type}, not stored or deflated")
            if member.filename.endswith(".npy"):
                try:
                    with archive.open(member) as stream:
                        check_npy(_Counted(stream), member.file_size, name, max_bytes=max_bytes)
                except (zipfile.BadZipFile, OSError, EOFError) as error:
                    raise InputError(f"{name}: cannot be read ({error})") from None


class _Counted(io.RawIOBase):
    """A read-only stream that knows its position (a zip member's stream reports none)."""

    def __init__(self, stream) -> None:
        self._stream, self._position = stream, 0

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        self._position += len(data)
        return data

    def tell(self) -> int:
        return self._position

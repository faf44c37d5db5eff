"""Point clouds and temperature fields as binary little-endian PLY (via plyfile), as bytes or files.

Each property's unit is a header comment ``unit <property> <unit>`` (``unit x mm``,
``unit temperature degC``); other comments are the cloud's own.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from services.errors import InputError
from services.formats.files import atomic_output
from services.formats.limits import ply_header
from services.geometry.cloud import PointCloud

_UNIT_COMMENT = "unit "


def as_cloud(cloud: PointCloud | Mapping[str, np.ndarray]) -> PointCloud:
    """``cloud`` itself, or a mapping of per-point arrays as a :class:`PointCloud`."""
    return cloud if isinstance(cloud, PointCloud) else PointCloud(dict(cloud))


def _ply_data(cloud: PointCloud) -> PlyData:
    """The binary little-endian PLY of a cloud's per-vertex properties, units and comments."""
    vertices = np.empty(len(cloud), dtype=[(name, values.dtype.newbyteorder("<").str)
                                           for name, values in cloud.items()])
    for name, values in cloud.items():
        vertices[name] = values
    comments = [*cloud.comments, *(f"{_UNIT_COMMENT}{name} {unit}" for name, unit in cloud.units.items())]
    return PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<", comments=comments)


def cloud_to_ply(cloud: PointCloud | Mapping[str, np.ndarray]) -> bytes:
    """The binary little-endian PLY of a cloud's per-vertex properties, units and comments."""
    buffer = io.BytesIO()
    _ply_data(as_cloud(cloud)).write(buffer)
    return buffer.getvalue()


_SCALAR_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
                 "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
                 "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _binary_vertices(data: bytes, length: int) -> tuple[np.ndarray, list[str]] | None:
    """The vertices and comments of a binary PLY whose one element is ``vertex`` of scalar properties (the clouds
    this project writes), read straight from the bytes; None for any other PLY. plyfile reads an in-memory
    stream element by element (2.4 s for 111,000 points of ten properties), a file it maps at once."""
    header = data[:length].decode("ascii", errors="replace").splitlines()
    order, fields, comments, count = None, [], [], None
    for line in header[1:]:
        words = line.split()
        if not words or words[0] == "end_header":
            continue
        if words[0] == "format":
            order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(words[1])
        elif words[0] == "comment":
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif words[0] == "element" and count is None and words[1] == "vertex":
            count = int(words[2])
        elif words[0] == "property" and len(words) == 3 and words[1] in _SCALAR_TYPES and count is not None:
            fields.append((words[2], order + _SCALAR_TYPES[words[1]] if order else ""))
        elif words[0] != "obj_info":
            return None  # another element, a list property: plyfile reads it
    if order is None or count is None or not fields or len({name for name, _ in fields}) != len(fields):
        return None
    vertices = np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=length)
    return vertices, comments


def cloud_from_ply(data: bytes, source: str = "PLY") -> PointCloud:
    """Parse PLY bytes (binary or ASCII) into a cloud; an ``InputError`` names ``source``, also for a header
    declaring more than the file holds (checked before plyfile allocates it)."""
    header = ply_header(data, source)
    fast = _binary_vertices(data, header.length)
    if fast is not None:
        vertex, ply_comments = fast
    else:
        try:
            ply = PlyData.read(io.BytesIO(data))
        except Exception as error:  # plyfile raises several types for malformed headers and bodies
            raise InputError(f"{source}: not a readable PLY file ({error})") from None
        if "vertex" not in ply:
            raise InputError(f"{source}: PLY file has no 'vertex' element")
        vertex, ply_comments = ply["vertex"].data, ply.comments
    units, comments = {}, []
    for comment in ply_comments:
        parts = comment.split()
        if comment.startswith(_UNIT_COMMENT) and len(parts) == 3:
            units[parts[1]] = parts[2]
        else:
            comments.append(comment)
    return PointCloud({name: np.ascontiguousarray(vertex[name]).astype(vertex.dtype[name].newbyteorder("="),
                                                                        copy=False)
                       for name in vertex.dtype.names}, units, tuple(comments))


def write_cloud(path: str | Path, cloud: PointCloud | Mapping[str, np.ndarray],
                comments: list[str] | None = None) -> None:
    """Write a cloud as a binary PLY (as :func:`cloud_to_ply`); the file appears atomically (written beside the
    target and renamed).

    ``comments`` replace the cloud's own when given.
    """
    cloud = as_cloud(cloud)
    if comments is not None:
        cloud = cloud.with_properties(comments=tuple(comments))
    ply = _ply_data(cloud)
    with atomic_output(path) as temporary, temporary.open("wb") as file:
        ply.write(file)  # straight from the vertex array, without the bytes of cloud_to_ply


def read_cloud(path: str | Path) -> PointCloud:
    """Read a PLY file's vertex properties; errors name the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: point cloud file is missing") from None
    except OSError as error:
        raise InputError(f"{path}: cannot read the point cloud ({error.strerror or error})") from None
    return cloud_from_ply(data, str(path))

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


def cloud_from_ply(data: bytes, source: str = "PLY") -> PointCloud:
    """Parse PLY bytes (binary or ASCII) into a cloud; an ``InputError`` names ``source``, also for a header
    declaring more than the file holds (checked before plyfile allocates it)."""
    ply_header(data, source)
    try:
        ply = PlyData.read(io.BytesIO(data))
    except Exception as error:  # plyfile raises several types for malformed headers and bodies
        raise InputError(f"{source}: not a readable PLY file ({error})") from None
    if "vertex" not in ply:
        raise InputError(f"{source}: PLY file has no 'vertex' element")
    vertex = ply["vertex"].data
    units, comments = {}, []
    for comment in ply.comments:
        parts = comment.split()
        if comment.startswith(_UNIT_COMMENT) and len(parts) == 3:
            units[parts[1]] = parts[2]
        else:
            comments.append(comment)
    return PointCloud({name: np.asarray(vertex[name]) for name in vertex.dtype.names}, units, tuple(comments))


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

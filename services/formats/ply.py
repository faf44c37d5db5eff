"""Point clouds and temperature fields as binary little-endian PLY (via plyfile)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from services.errors import InputError
from services.formats.files import atomic_output


def write_cloud(path: str | Path, properties: dict[str, np.ndarray], comments: list[str] | None = None) -> None:
    """Write per-vertex properties (1-D arrays of equal length) as a binary little-endian PLY.

    The file appears atomically: it is written beside the target and renamed.
    """
    path = Path(path)
    lengths = {name: len(values) for name, values in properties.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"All PLY properties must have the same length; got {lengths}.")
    count = next(iter(lengths.values()), 0)
    vertices = np.empty(count, dtype=[(name, np.asarray(values).dtype.str) for name, values in properties.items()])
    for name, values in properties.items():
        vertices[name] = values
    data = PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<", comments=comments or [])
    with atomic_output(path) as temporary:
        data.write(str(temporary))


def read_cloud(path: str | Path) -> dict[str, np.ndarray]:
    """Read the vertex properties of a PLY file into a dict of 1-D arrays."""
    path = Path(path)
    try:
        data = PlyData.read(str(path))
    except FileNotFoundError:
        raise InputError(f"{path}: point cloud file is missing") from None
    except Exception as error:  # plyfile raises several types for malformed headers and bodies
        raise InputError(f"{path}: not a readable PLY file ({error})") from None
    if "vertex" not in data:
        raise InputError(f"{path}: PLY file has no 'vertex' element")
    vertex = data["vertex"].data
    return {name: np.asarray(vertex[name]) for name in vertex.dtype.names}

"""The per-calibration precomputation of reconstruction: triangulation tables, kept in memory and on disk.

A table depends only on the camera, the projector and the coded axis, and takes longer to build than a
scan takes to reconstruct, so it is built once per calibration: a table is named by the SHA-256 of
what it depends on, kept in memory for the process, and (when a directory is given) as an ``.npz``
file that the next process loads instead of rebuilding it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import threading
from pathlib import Path

import numpy as np

from services.geometry.camera_model import CameraModel
from services.structured_light.triangulate import TriangulationTable, triangulation_table

# Bump when TriangulationTable or its algorithm changes: older files are then ignored.
TABLE_FORMAT = "triangulation-table-1"
_ARRAY_FIELDS = tuple(f.name for f in dataclasses.fields(TriangulationTable) if f.name != "axis")


def table_key(camera: CameraModel, projector: CameraModel, axis: str) -> str:
    """SHA-256 (hex) of everything a triangulation table depends on."""
    hasher = hashlib.sha256(f"{TABLE_FORMAT} {axis} {camera.size} {projector.size}".encode())
    for device in (camera, projector):
        for array in (device.K, device.dist, device.R, device.t):
            hasher.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
    return hasher.hexdigest()


def default_table_directory() -> Path:
    """Where the command line keeps its tables: ``$XDG_CACHE_HOME/thermofield/tables`` (``~/.cache``)."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "thermofield" / "tables"


class TriangulationTables:
    """Triangulation tables by content hash, built on first use; thread-safe.

    Parameters
    ----------
    directory : path, optional
        Keep the tables there as ``<key>.npz`` too, so that another process with the same calibration
        loads instead of building them. None keeps them in memory only.
    max_tables : int
        Tables kept in memory (about 12 MB each at 1280x800); the oldest goes first.
    """

    def __init__(self, directory: str | Path | None = None, max_tables: int = 4) -> None:
        self.directory = None if directory is None else Path(directory)
        self.max_tables = max_tables
        self._tables: dict[str, TriangulationTable] = {}
        self._lock = threading.Lock()
        self.built = 0  # tables built (not loaded) by this object, for tests and benchmarks

    def get(self, camera: CameraModel, projector: CameraModel, axis: str) -> TriangulationTable:
        """The table of ``camera`` and ``projector`` against coded ``axis``, built or loaded once."""
        key = table_key(camera, projector, axis)
        with self._lock:
            table = self._tables.get(key)
            if table is None:
                table = self._load(key, axis)
                if table is None:
                    table = triangulation_table(camera, projector, axis)
                    self.built += 1
                    self._save(key, table)
                if len(self._tables) >= self.max_tables:
                    self._tables.pop(next(iter(self._tables)))
                self._tables[key] = table
            return table

    def _path(self, key: str) -> Path | None:
        return None if self.directory is None else self.directory / f"{key}.npz"

    def _load(self, key: str, axis: str) -> TriangulationTable | None:
        path = self._path(key)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as arrays:
                return TriangulationTable(axis=axis, **{name: arrays[name] for name in _ARRAY_FIELDS})
        except (OSError, ValueError, KeyError):
            return None  # a damaged or foreign file: build the table again and replace it

    def _save(self, key: str, table: TriangulationTable) -> None:
        path = self._path(key)
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".part", delete=False) as file:
                np.savez(file, **{name: getattr(table, name) for name in _ARRAY_FIELDS})
            Path(file.name).replace(path)
        except OSError:
            pass  # an unwritable cache only costs the next process a rebuild

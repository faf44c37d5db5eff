"""The rig file: named, calibrated devices sharing one world frame (a public format).

```json
{"version": 2, "units": "mm",
 "devices": {"<name>": {"kind": "camera" | "projector" | "thermal",
                        "width": 1280, "height": 800,
                        "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],
                        "dist": [k1, k2, p1, p2, k3, ...],
                        "R": [[...], [...], [...]], "t": [tx, ty, tz]}},
 "heads": [{"name": "north", "camera": "<camera device>", "projector": "<projector device>"}]}
```

Version 2 adds the station's sensor heads, each a camera and a projector of ``devices``; thermal
cameras belong to the station, not to a head. A file without ``version`` is version 1: no ``heads``,
and a rig with exactly one camera and one projector is one head (:data:`SINGLE_HEAD`).

(R, t) maps world to device coordinates, x_dev = R x_world + t, in millimetres
with OpenCV axes (x right, y down, z forward). ``dist`` has 0, 4, 5, 8, 12 or 14
coefficients in OpenCV order. Unknown fields are refused so that a typo is not
silently ignored. See docs/rig-file.md.

A parsed rig holds :class:`~services.geometry.camera.CameraModel` objects (read-only arrays); the
pydantic models here are only the file's schema.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.errors import InputError
from services.formats.files import write_text_atomically
from services.formats.json_files import read_text, validate_json
from services.geometry.camera_model import VALID_DISTORTION_LENGTHS, CameraModel, DeviceKind

_ROTATION_TOLERANCE = 1e-6
RIG_FILE_VERSION = 2
SINGLE_HEAD = "head"
"""The name of a version-1 rig's one head (its only camera and projector)."""
HEAD_NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"
"""A head's name is also its capture sub-directory's name: letters, digits, ``_``, ``.``, ``-``."""
Matrix3 = Annotated[list[Annotated[list[float], Field(min_length=3, max_length=3)]], Field(min_length=3, max_length=3)]


class DeviceEntry(BaseModel):
    """The schema of one device of the rig file: intrinsics, distortion and pose, checked to be physical."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: DeviceKind
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    K: Matrix3
    dist: list[float] = Field(default_factory=list)
    R: Matrix3 = Field(default_factory=lambda: np.eye(3).tolist())
    t: Annotated[list[float], Field(min_length=3, max_length=3)] = Field(default_factory=lambda: [0.0, 0.0, 0.0])

    @field_validator("K")
    @classmethod
    def _intrinsics_are_physical(cls, K: list[list[float]]) -> list[list[float]]:
        k = np.asarray(K, dtype=float)
        if not np.all(np.isfinite(k)):
            raise ValueError("K contains a non-finite value")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f"focal lengths must be positive; got fx={k[0, 0]}, fy={k[1, 1]}")
        if not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
            raise ValueError("K must be upper triangular with last row [0, 0, 1]")
        if k[0, 1] != 0:
            raise ValueError("K[0][1] (skew) must be 0: OpenCV's camera model has no skew")
        return K

    @field_validator("dist")
    @classmethod
    def _distortion_length_is_opencv(cls, dist: list[float]) -> list[float]:
        if len(dist) not in VALID_DISTORTION_LENGTHS:
            raise ValueError(f"must have one of {VALID_DISTORTION_LENGTHS} coefficients; got {len(dist)}")
        if not np.all(np.isfinite(dist)):
            raise ValueError("contains a non-finite value")
        return dist

    @field_validator("R")
    @classmethod
    def _is_rotation(cls, R: list[list[float]]) -> list[list[float]]:
        r = np.asarray(R, dtype=float)
        orthogonality = np.abs(r @ r.T - np.eye(3)).max()
        if not np.isfinite(orthogonality) or orthogonality > _ROTATION_TOLERANCE or np.linalg.det(r) < 0:
            raise ValueError(
                f"R is not a rotation matrix (max |R R^T - I| = {orthogonality:.2g}, det = {np.linalg.det(r):.4g})"
            )
        return R

    @field_validator("t")
    @classmethod
    def _translation_is_finite(cls, t: list[float]) -> list[float]:
        if not np.all(np.isfinite(t)):
            raise ValueError("contains a non-finite value")
        return t

    def camera_model(self) -> CameraModel:
        return CameraModel(kind=self.kind, width=self.width, height=self.height, K=self.K, dist=self.dist,
                           R=self.R, t=self.t)

    @classmethod
    def of(cls, device: CameraModel) -> DeviceEntry:
        return cls(kind=device.kind, width=device.width, height=device.height, K=device.K.tolist(),
                   dist=device.dist.tolist(), R=device.R.tolist(), t=device.t.tolist())


class HeadEntry(BaseModel):
    """The schema of one sensor head of a version-2 rig: the names of its camera and projector."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    camera: str
    projector: str

    @field_validator("name")
    @classmethod
    def _name_is_a_directory_name(cls, name: str) -> str:
        if not re.fullmatch(HEAD_NAME_PATTERN, name):
            raise ValueError("a head's name is also its capture directory's: 1 to 64 letters, digits, '_', '.' "
                             f"or '-', starting with a letter or digit; got {name!r}")
        return name


class RigFile(BaseModel):
    """The schema of the rig file (version 1 without ``version`` and ``heads``, version 2 with them)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1, 2] = 1
    units: Literal["mm"] = "mm"
    devices: dict[str, DeviceEntry]
    heads: list[HeadEntry] | None = None

    @model_validator(mode="after")
    def _heads_name_their_devices(self) -> RigFile:
        if self.version == 1:
            if self.heads is not None:
                raise ValueError('"heads" needs "version": 2')
            return self
        if not self.heads:
            raise ValueError("a version-2 rig lists at least one head")
        _check_heads([(h.name, h.camera, h.projector) for h in self.heads],
                     {name: entry.kind for name, entry in self.devices.items()})
        return self


def _check_heads(heads: list[tuple[str, str, str]], kinds: Mapping[str, str]) -> None:
    """Raise ValueError unless head names are unique and each names its own camera and projector."""
    names = [name for name, _, _ in heads]
    if len(set(names)) != len(names):
        raise ValueError(f"head names must be unique; got {names}")
    used: dict[str, str] = {}
    for name, *devices in heads:
        for device, kind in zip(devices, ("camera", "projector")):
            if device not in kinds:
                raise ValueError(f"head {name!r}: no device named {device!r} (the rig has {sorted(kinds)})")
            if kinds[device] != kind:
                raise ValueError(f"head {name!r}: {device!r} is a {kinds[device]}, not a {kind}")
            if device in used:
                raise ValueError(f"head {name!r}: {device!r} already belongs to head {used[device]!r}")
            used[device] = name


@dataclass(frozen=True)
class Head:
    """One sensor head of a station: a camera and the projector whose patterns it films."""

    name: str
    camera: str
    projector: str


@dataclass(frozen=True)
class Rig:
    """Named devices in one world frame, lengths in millimetres."""

    devices: Mapping[str, CameraModel]
    units: Literal["mm"] = "mm"
    station_heads: tuple[Head, ...] = ()
    """The heads a version-2 file lists; empty for a version-1 rig (see :attr:`heads`)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "devices", MappingProxyType(dict(self.devices)))
        object.__setattr__(self, "station_heads", tuple(self.station_heads))
        if self.station_heads:
            try:
                _check_heads([(h.name, h.camera, h.projector) for h in self.station_heads],
                             {name: device.kind for name, device in self.devices.items()})
            except ValueError as error:
                raise InputError(f"rig: {error}") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Rig):
            return NotImplemented
        return (self.units == other.units and dict(self.devices) == dict(other.devices)
                and self.station_heads == other.station_heads)

    def __hash__(self) -> int:
        return hash((tuple(sorted((name, hash(device)) for name, device in self.devices.items())),
                     self.station_heads))

    @property
    def heads(self) -> tuple[Head, ...]:
        """The station's heads: those of a version-2 file; for a version-1 rig with exactly one camera and one
        projector, that pair as one head named :data:`SINGLE_HEAD`; otherwise none."""
        if self.station_heads:
            return self.station_heads
        cameras = [n for n, d in self.devices.items() if d.kind == "camera"]
        projectors = [n for n, d in self.devices.items() if d.kind == "projector"]
        if len(cameras) == 1 and len(projectors) == 1:
            return (Head(SINGLE_HEAD, cameras[0], projectors[0]),)
        return ()

    def head(self, name: str) -> Head:
        """The head called ``name``; InputError naming the heads there are when it is missing."""
        for head in self.heads:
            if head.name == name:
                return head
        raise InputError(f"the rig has no head named {name!r} (it has {[h.name for h in self.heads]})")

    def with_device(self, name: str, device: CameraModel) -> Rig:
        """This rig with ``name`` added or replaced."""
        return Rig({**self.devices, name: device}, self.units, self.station_heads)

    def without_kind(self, kind: DeviceKind) -> Rig:
        """This rig without its devices of ``kind`` (and without its heads, when those were cameras or
        projectors)."""
        heads = self.station_heads if kind == "thermal" else ()
        return Rig({n: d for n, d in self.devices.items() if d.kind != kind}, self.units, heads)

    def device(self, name: str | None, kind: DeviceKind) -> tuple[str, CameraModel]:
        """The device called ``name``, or the only device of ``kind`` when ``name`` is None.

        Raises
        ------
        InputError
            When the device is missing, of another kind, or ambiguous.
        """
        if name is not None:
            if name not in self.devices:
                raise InputError(f"the rig has no device named {name!r} (it has {sorted(self.devices)})")
            if self.devices[name].kind != kind:
                raise InputError(f"rig device {name!r} is a {self.devices[name].kind}, not a {kind}")
            return name, self.devices[name]
        matching = [n for n, d in self.devices.items() if d.kind == kind]
        if len(matching) != 1:
            found = f"several ({', '.join(matching)}); name one" if matching else "none"
            raise InputError(f"the rig must have exactly one {kind} device to pick by default; it has {found}")
        return matching[0], self.devices[matching[0]]


def parse_rig(text: str, source: str = "rig") -> Rig:
    """Validate rig JSON text; errors name ``source``, the device and the field."""
    parsed = validate_json(RigFile, text, source)
    heads = tuple(Head(h.name, h.camera, h.projector) for h in parsed.heads or ())
    return Rig({name: entry.camera_model() for name, entry in parsed.devices.items()}, parsed.units, heads)


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file."""
    return parse_rig(read_text(path, "rig file"), str(path))


def rig_to_json(rig: Rig) -> str:
    """The rig file's text (the inverse of :func:`parse_rig`): version 2 when the rig lists heads, else
    version 1 (no ``version`` key), so that a one-head rig's file reads as it always did."""
    devices = {name: DeviceEntry.of(d) for name, d in rig.devices.items()}
    if not rig.station_heads:
        return json.dumps(RigFile(units=rig.units, devices=devices).model_dump(exclude={"version", "heads"}),
                          indent=2)
    heads = [HeadEntry(name=h.name, camera=h.camera, projector=h.projector) for h in rig.station_heads]
    document = RigFile(version=RIG_FILE_VERSION, units=rig.units, devices=devices, heads=heads)
    return json.dumps(document.model_dump(), indent=2)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write a rig file atomically (a reader never sees half a file)."""
    write_text_atomically(path, rig_to_json(rig) + "\n")

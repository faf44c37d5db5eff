"""A station's capture on disk: one capture directory per head, and the thermal frames once for all (a public
layout, docs/station.md).

```
<dir>/<head>/sequence.json     each head's capture, as `thermofield reconstruct --captures` reads one:
<dir>/<head>/<frames>          the manifest and the frames it names (services/formats/sequence.py)
<dir>/thermal/<device>.tiff    one frame per thermal camera of the rig, float32 degrees C, named as the device
```

A head's sub-directory is named as the head in the rig file (version 2, ``heads``); a version-1 rig's one
head is ``head``. The heads run one after another (each lit by its own projector only); the thermal
frames are taken once, for every head.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.errors import InputError
from services.formats.files import output_directory
from services.formats.images import write_image
from services.formats.rig import Rig
from services.formats.sequence import MANIFEST_NAME, Sequence, read_capture, save_sequence
from services.formats.thermal import write_thermal_frame

THERMAL_DIRECTORY = "thermal"
THERMAL_SUFFIX = ".tiff"


@dataclass(frozen=True)
class HeadFrames:
    """One head's capture: its manifest and camera frames (F, H, W) in the manifest's order."""

    head: str
    sequence: Sequence
    frames: np.ndarray


def is_station_capture(directory: str | Path, rig: Rig) -> bool:
    """Whether ``directory`` holds one sub-directory per head of ``rig`` rather than one capture itself: it has
    no ``sequence.json`` and the rig's first head's sub-directory has one."""
    directory = Path(directory)
    heads = rig.heads
    return (bool(heads) and not (directory / MANIFEST_NAME).is_file()
            and (directory / heads[0].name / MANIFEST_NAME).is_file())


def head_directory(directory: str | Path, head: str) -> Path:
    """Where head ``head``'s capture lies in the station capture ``directory``."""
    return Path(directory) / head


def read_head_capture(directory: str | Path, head: str) -> HeadFrames:
    """Read head ``head``'s capture from the station capture ``directory``.

    Raises
    ------
    InputError
        Naming the head and its directory when it is missing, and the file when a frame or the manifest is
        missing or wrong (see :func:`services.formats.sequence.read_capture`).
    """
    path = head_directory(directory, head)
    if not path.is_dir():
        present = sorted(p.name for p in Path(directory).iterdir() if p.is_dir()) if Path(directory).is_dir() else []
        raise InputError(f"{path}: no capture of head {head!r} (the station capture has sub-directories {present}; "
                         "each head's capture lies in a sub-directory named as the head in the rig)")
    sequence, frames = read_capture(path)
    return HeadFrames(head, sequence, frames)


def read_station_capture(directory: str | Path, rig: Rig) -> tuple[HeadFrames, ...]:
    """Every head's capture of ``rig`` from the station capture ``directory``, in the rig's head order."""
    if not rig.heads:
        raise InputError("the rig names no head (a version-2 rig lists its heads; a version-1 rig has exactly "
                         "one camera and one projector)")
    return tuple(read_head_capture(directory, head.name) for head in rig.heads)


def thermal_path(directory: str | Path, device: str) -> Path:
    """Where thermal camera ``device``'s frame lies in the station capture ``directory``."""
    return Path(directory) / THERMAL_DIRECTORY / f"{device}{THERMAL_SUFFIX}"


def save_station_capture(directory: str | Path, heads: tuple[HeadFrames, ...],
                         thermal: Mapping[str, np.ndarray]) -> Path:
    """Write a station capture (the layout of the module docstring); every file appears whole or not at all.

    ``heads`` are the heads' captures, ``thermal`` one frame in degrees C per thermal device name.
    """
    directory = output_directory(directory)
    for head in heads:
        if len(head.frames) != len(head.sequence.frames):
            raise ValueError(f"head {head.head!r}: {len(head.frames)} frames for a manifest of "
                             f"{len(head.sequence.frames)}")
        target = output_directory(head_directory(directory, head.head))
        for frame, image in zip(head.sequence.frames, head.frames):
            write_image(target / frame.file, image)
        save_sequence(head.sequence, target)
    if thermal:
        output_directory(directory / THERMAL_DIRECTORY)
    for device, frame in thermal.items():
        write_thermal_frame(thermal_path(directory, device), frame)
    return directory

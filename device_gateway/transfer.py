"""The capture as it travels over HTTP: one uncompressed NumPy ``.npz`` archive.

Arrays ``frames`` (F, H, W), ``frame_timestamps`` (F,), ``thermal`` (T, h, w)
float32 degrees Celsius and ``thermal_timestamps`` (T,), plus ``metadata``: UTF-8
JSON bytes holding the sequence manifest, the devices, the per-frame metadata and the
capture's exposure (mode, exposure times, glow level, saturation level).
Uncompressed because frames are noisy (compression gains little) and the scan has
a 2 s budget; loaded without pickle, so a capture cannot carry code.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile

import numpy as np

from device_gateway.devices import DeviceInfo
from device_gateway.station import BoardViews, Capture
from services.errors import InputError
from services.formats.limits import check_npz
from services.formats.sequence import Sequence

MEDIA_TYPE = "application/vnd.thermofield.capture+npz"
BOARD_VIEWS_MEDIA_TYPE = "application/vnd.thermofield.board-views+npz"
_ARRAYS = ("frames", "frame_timestamps", "thermal", "thermal_timestamps")
_BOARD_ARRAYS = ("camera", "thermal", "timestamps")


def encode_capture(capture: Capture) -> bytes:
    """Serialise a capture to ``.npz`` bytes."""
    metadata = {
        "sequence": capture.sequence.model_dump(mode="json"),
        "devices": [dataclasses.asdict(info) for info in capture.devices],
        "frame_metadata": capture.frame_metadata,
        "thermal_metadata": capture.thermal_metadata,
        "exposure": capture.exposure,
    }
    buffer = io.BytesIO()
    np.savez(buffer, metadata=np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8),
             **{name: getattr(capture, name) for name in _ARRAYS})
    return buffer.getvalue()


def decode_capture(data: bytes) -> Capture:
    """Read ``.npz`` bytes written by :func:`encode_capture`.

    Raises
    ------
    ValueError
        When the bytes are not such an archive.
    """
    arrays, metadata = _load_archive(data, _ARRAYS, "a capture archive")
    return Capture(
        sequence=Sequence.model_validate(metadata["sequence"]),
        frame_metadata=metadata["frame_metadata"],
        thermal_metadata=metadata["thermal_metadata"],
        devices=[DeviceInfo(**info) for info in metadata["devices"]],
        exposure=metadata.get("exposure", {}),
        **arrays,
    )


def encode_board_views(views: BoardViews) -> bytes:
    """Serialise calibration board views to ``.npz`` bytes (arrays plus the devices as JSON metadata)."""
    metadata = {"devices": [dataclasses.asdict(info) for info in views.devices]}
    buffer = io.BytesIO()
    np.savez(buffer, metadata=np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8),
             **{name: getattr(views, name) for name in _BOARD_ARRAYS})
    return buffer.getvalue()


def decode_board_views(data: bytes) -> BoardViews:
    """Read ``.npz`` bytes written by :func:`encode_board_views`; ``ValueError`` when they are not such an archive."""
    arrays, metadata = _load_archive(data, _BOARD_ARRAYS, "a board-views archive")
    return BoardViews(devices=[DeviceInfo(**info) for info in metadata["devices"]], **arrays)


def _load_archive(data: bytes, names: tuple[str, ...], what: str) -> tuple[dict[str, np.ndarray], dict]:
    """The named arrays and the JSON metadata of an ``.npz`` archive, read without pickle, after every
    member's declared size was checked against the archive's length (:func:`check_npz`)."""
    try:
        check_npz(data, f"the gateway's answer ({what})", max_bytes=max(len(data), 1))
    except InputError as error:
        raise ValueError(f"The gateway's answer is not {what}: {error}.") from None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            return {name: archive[name] for name in names}, json.loads(archive["metadata"].tobytes())
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as error:
        raise ValueError(f"The gateway's answer is not {what}: {error}.") from None

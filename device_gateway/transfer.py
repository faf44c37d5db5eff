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
from device_gateway.station import BoardViews, Capture, HeadCapture, StationCapture
from services.errors import InputError
from services.formats.limits import check_npz
from services.formats.sequence import Sequence

MEDIA_TYPE = "application/vnd.thermofield.capture+npz"
BOARD_VIEWS_MEDIA_TYPE = "application/vnd.thermofield.board-views+npz"
STATION_MEDIA_TYPE = "application/vnd.thermofield.station-capture+npz"
STATION_FORMAT, STATION_VERSION = "thermofield-station-capture", 1
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


def encode_station_capture(capture: StationCapture) -> bytes:
    """Serialise a station capture to ``.npz`` bytes (docs/station.md, "The station capture archive"): head k's
    frames as ``frames-k`` and ``frame_timestamps-k``, thermal camera j's as ``thermal-j`` and
    ``thermal_timestamps-j``, and ``metadata`` naming the format, its version, the sequence, each head (name,
    arrays, exposure, per-frame metadata with ``head``, error) and each thermal camera (device, arrays)."""
    arrays: dict[str, np.ndarray] = {}
    heads = []
    for index, head in enumerate(capture.heads):
        arrays[f"frames-{index}"], arrays[f"frame_timestamps-{index}"] = head.frames, head.frame_timestamps
        heads.append({"head": head.head, "frames": f"frames-{index}", "frame_timestamps": f"frame_timestamps-{index}",
                      "frame_metadata": head.frame_metadata, "exposure": head.exposure, "error": head.error})
    thermal = []
    for index, (device, frames) in enumerate(capture.thermal.items()):
        arrays[f"thermal-{index}"] = frames
        arrays[f"thermal_timestamps-{index}"] = capture.thermal_timestamps[device]
        thermal.append({"device": device, "frames": f"thermal-{index}", "timestamps": f"thermal_timestamps-{index}"})
    metadata = {"format": STATION_FORMAT, "version": STATION_VERSION,
                "sequence": capture.sequence.model_dump(mode="json"), "heads": heads, "thermal": thermal,
                "devices": [dataclasses.asdict(info) for info in capture.devices]}
    buffer = io.BytesIO()
    np.savez(buffer, metadata=np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8), **arrays)
    return buffer.getvalue()


def decode_station_capture(data: bytes) -> StationCapture:
    """Read ``.npz`` bytes written by :func:`encode_station_capture`; ``ValueError`` when they are not such an
    archive or of another version."""
    _, metadata = _load_archive(data, (), "a station capture archive")
    if metadata.get("format") != STATION_FORMAT or metadata.get("version") != STATION_VERSION:
        raise ValueError(f"The gateway's answer is not a station capture archive of version {STATION_VERSION}: "
                         f"format {metadata.get('format')!r}, version {metadata.get('version')!r}.")
    names = tuple(entry[key] for entry in metadata["heads"] for key in ("frames", "frame_timestamps")) + tuple(
        entry[key] for entry in metadata["thermal"] for key in ("frames", "timestamps"))
    arrays, _ = _load_archive(data, names, "a station capture archive")
    heads = tuple(HeadCapture(head=entry["head"], frames=arrays[entry["frames"]],
                              frame_timestamps=arrays[entry["frame_timestamps"]],
                              frame_metadata=entry["frame_metadata"], exposure=entry["exposure"], error=entry["error"])
                  for entry in metadata["heads"])
    return StationCapture(sequence=Sequence.model_validate(metadata["sequence"]), heads=heads,
                          thermal={entry["device"]: arrays[entry["frames"]] for entry in metadata["thermal"]},
                          thermal_timestamps={entry["device"]: arrays[entry["timestamps"]]
                                              for entry in metadata["thermal"]},
                          devices=[DeviceInfo(**info) for info in metadata["devices"]])

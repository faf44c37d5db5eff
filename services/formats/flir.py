"""FLIR radiometric JPEG (R-JPEG): the raw thermal counts and the camera's radiometric constants.

An R-JPEG is a visible JPEG whose APP1 segments carry FLIR's "FFF" records: the raw
16-bit thermal image (PNG-coded or plain little-endian) and the camera information
(Planck R1, R2, B, F, O; emissivity, object distance, reflected, atmospheric and window
temperatures, relative humidity, the atmospheric transmission fit). `flyr` parses the
records and decodes the raw image; temperatures follow by FLIR's model in
:func:`services.fusion.radiometry.counts_to_temperature`. See docs/thermal-formats.md.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, replace

import numpy as np

from services.errors import InputError
from services.formats.limits import check_declared
from services.fusion.radiometry import KELVIN_OFFSET, AtmosphereConstants, PlanckConstants, counts_to_temperature

JPEG_SUFFIXES = (".jpg", ".jpeg")

# The largest radiometric cameras are 1280x1024 (1.3 Mpx); a declared size beyond this budget is a corrupt
# or hostile header, refused before anything is decoded.
MAX_THERMAL_PIXELS = 4 * 1024 * 1024


def check_declared_size(width: int, height: int, source: str) -> None:
    """Refuse a thermal image whose header declares a nonsense size, before decoding it (the limit itself is
    checked where every decoder's is: :func:`services.formats.limits.check_declared`)."""
    if width < 1 or height < 1:
        raise InputError(f"{source}: FLIR raw thermal image declares a {width}x{height} size (corrupt file)")
    check_declared(width * height, MAX_THERMAL_PIXELS, f"{source}: FLIR raw thermal image", "pixels")


@dataclass(frozen=True)
class FlirConditions:
    """The measurement conditions of FLIR's model (temperatures in degrees C, humidity a fraction)."""

    emissivity: float
    distance_m: float
    reflected_c: float
    atmosphere_c: float
    relative_humidity: float
    window_c: float = 20.0
    window_transmission: float = 1.0

    def problem(self) -> str | None:
        """What is wrong with these conditions, in a few words, or None."""
        checks = (
            (0.0 < self.emissivity <= 1.0, f"emissivity {self.emissivity:g} is not in (0, 1]"),
            (math.isfinite(self.distance_m) and 0.0 <= self.distance_m <= 1e5,
             f"object distance {self.distance_m:g} m is not in 0..100000 m"),
            (0.0 <= self.relative_humidity <= 1.0,
             f"relative humidity {self.relative_humidity:g} is not a fraction in [0, 1]"),
            (0.0 < self.window_transmission <= 1.0,
             f"IR window transmission {self.window_transmission:g} is not in (0, 1]"),
        )
        for name, value in (("reflected", self.reflected_c), ("atmospheric", self.atmosphere_c),
                            ("IR window", self.window_c)):
            checks += ((math.isfinite(value) and -KELVIN_OFFSET < value < 5000.0,
                        f"{name} temperature {value:g} C is not a temperature"),)
        return next((message for ok, message in checks if not ok), None)


@dataclass(frozen=True)
class FlirImage:
    """What an R-JPEG holds for radiometry."""

    counts: np.ndarray  # (height, width) uint16 raw counts
    planck: PlanckConstants
    atmosphere: AtmosphereConstants
    conditions: FlirConditions  # as the camera stored them
    camera: str  # make and model from the EXIF, or "unknown camera"


def read_flir_jpeg(content: bytes, source: str) -> FlirImage:
    """Parse an R-JPEG's bytes; errors are one-line :class:`InputError` naming ``source``.

    Raises
    ------
    InputError
        Not a JPEG, a JPEG without FLIR records (a plain JPEG), truncated records, an absurd
        declared size, or missing or nonsense constants.
    """
    from flyr.records import RecordIndex, extract_flir_app1, parse_flir_records
    from flyr.thermal import parse_camera_info, parse_raw_data

    if content[:2] != b"\xff\xd8":
        raise InputError(f"{source}: not a FLIR radiometric JPEG (not a JPEG file)")
    complete = content.rstrip(b"\x00").endswith(b"\xff\xd9")  # the JPEG end-of-image marker
    try:
        flir = extract_flir_app1(io.BytesIO(content))
    except KeyError as error:  # flyr joins the chunks it found; a missing one is a KeyError
        raise InputError(f"{source}: FLIR radiometric JPEG is truncated (FLIR data chunk {error} is missing)") \
            from None
    except ValueError as error:
        reason = str(error)
        if "no metadata" in reason:
            reason = "no FLIR radiometric data; a plain JPEG?" if complete else \
                "no FLIR radiometric data, and the file is truncated"
        raise InputError(f"{source}: not a FLIR radiometric JPEG ({reason})") from None
    if not complete:
        raise InputError(f"{source}: FLIR radiometric JPEG is truncated (it does not end with the JPEG end-of-image "
                         "marker)")
    try:
        records = parse_flir_records(flir)
    except Exception:  # flyr reads offsets without checks; any failure means corrupt records
        raise InputError(f"{source}: FLIR radiometric JPEG with an unreadable record directory (corrupt)") from None
    missing = [name for name, index in (("raw thermal image", RecordIndex.RAW_DATA),
                                        ("camera information", RecordIndex.CAMERA_INFO))
               if index.value not in records]
    if missing:
        raise InputError(f"{source}: FLIR radiometric JPEG without its {' and '.join(missing)} (truncated?)")
    flir_bytes = flir.getbuffer().nbytes
    for index in (RecordIndex.RAW_DATA, RecordIndex.CAMERA_INFO):
        _, _, offset, length = records[index.value]
        if offset + length > flir_bytes:
            raise InputError(f"{source}: FLIR radiometric JPEG is truncated (its {index.name.lower()} record ends "
                             f"at byte {offset + length} of {flir_bytes})")
    raw_offset = records[RecordIndex.RAW_DATA.value][2]
    flir.seek(raw_offset + 2)
    width, height = (int.from_bytes(flir.read(2), "little") for _ in range(2))
    check_declared_size(width, height, source)
    try:
        _, _, counts = parse_raw_data(flir, records[RecordIndex.RAW_DATA.value])
        info = parse_camera_info(flir, records[RecordIndex.CAMERA_INFO.value])
    except Exception as error:  # PIL, numpy and struct raise many types for a corrupt record
        raise InputError(f"{source}: FLIR radiometric JPEG with a corrupt raw thermal image or camera information "
                         f"({type(error).__name__}: {error})") from None
    if counts.shape != (height, width) or counts.min() < 0 or counts.max() > 65535:
        raise InputError(f"{source}: FLIR raw thermal image is not {width}x{height} 16-bit counts (corrupt)")
    try:
        planck = PlanckConstants(info["planck_r1"], info["planck_r2"], info["planck_b"], info["planck_f"],
                                 float(info["planck_o"]))
        atmosphere = AtmosphereConstants(info["atmospheric_trans_alpha1"], info["atmospheric_trans_alpha2"],
                                         info["atmospheric_trans_beta1"], info["atmospheric_trans_beta2"],
                                         info["atmospheric_trans_x"])
    except ValueError as error:
        raise InputError(f"{source}: FLIR radiometric JPEG without usable camera constants ({error})") from None
    conditions = FlirConditions(
        emissivity=info["emissivity"], distance_m=info["object_distance"],
        reflected_c=info["reflected_apparent_temperature"] - KELVIN_OFFSET,
        atmosphere_c=info["atmospheric_temperature"] - KELVIN_OFFSET,
        relative_humidity=info["relative_humidity"],
        window_c=info["ir_window_temperature"] - KELVIN_OFFSET,
        window_transmission=info["ir_window_transmission"],
    )
    problem = conditions.problem()
    if problem:
        raise InputError(f"{source}: FLIR radiometric JPEG with inconsistent parameters: {problem}")
    return FlirImage(counts=counts.astype(np.uint16), planck=planck, atmosphere=atmosphere,
                     conditions=conditions, camera=_camera_name(content))


def _camera_name(content: bytes) -> str:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(content)) as image:
            exif = image.getexif()
    except Exception:  # the camera's name is only informative
        return "unknown camera"
    name = " ".join(str(exif.get(tag, "")).strip("\x00 ") for tag in (0x010F, 0x0110)).strip()  # Make, Model
    return name or "unknown camera"


def flir_temperature(image: FlirImage, conditions: FlirConditions | None = None) -> np.ndarray:
    """Object temperature (degrees C, float64) of an R-JPEG by FLIR's model, with the file's conditions or
    ``conditions`` (see :func:`with_overrides`)."""
    # Not flyr's own conversion: it is private to its thermogram object (no function on arrays), and one model
    # (services/fusion/radiometry.py) serves R-JPEGs, sidecar counts and apparent frames alike.
    c = image.conditions if conditions is None else conditions
    problem = c.problem()
    if problem:
        raise ValueError(f"The measurement conditions are inconsistent: {problem}.")
    return counts_to_temperature(image.counts, image.planck, c.emissivity, c.reflected_c,
                                 atmosphere_c=c.atmosphere_c, relative_humidity=c.relative_humidity,
                                 distance_m=c.distance_m, atmosphere=image.atmosphere,
                                 window_temperature_c=c.window_c, window_transmission=c.window_transmission)


def with_overrides(conditions: FlirConditions, **overrides: float | None) -> FlirConditions:
    """The conditions with the given fields replaced (None keeps the file's value)."""
    return replace(conditions, **{name: value for name, value in overrides.items() if value is not None})

"""Thermal frames: temperature images in degrees Celsius, centikelvin, raw counts with Planck constants, or
FLIR radiometric JPEGs.

Formats, chosen by the file and an optional sidecar JSON of the same stem
(``frame.png`` -> ``frame.json``):

- FLIR radiometric JPEG (``.jpg``/``.jpeg``, R-JPEG): raw counts and the camera's constants in
  the file (:mod:`services.formats.flir`), temperatures by FLIR's model; no sidecar;
- float32/float64 TIFF or ``.npy``: degrees Celsius (NaN for no data);
- 16-bit PNG or TIFF (or uint16 ``.npy``): centikelvin, T = v / 100 - 273.15 degrees
  Celsius; 0 (no data) and 65535 (saturated) read as NaN. 16 bits reach only
  382 degrees C: store hot parts as float TIFF or raw counts;
- 16-bit frames on a stated linear scale (the high-range "temperature linear" modes of
  radiometric cameras, e.g. 0.1 K per count): sidecar ``{"unit": "linear", "scale": 0.1,
  "offset": 0.0}``, T = offset + scale v kelvin; 0 and 65535 read as NaN;
- raw sensor counts (any numeric type) when the sidecar says so:

```json
{"unit": "counts", "planck": {"R1": 21106.77, "R2": 0.012545258, "B": 1501, "F": 1, "O": -7340},
 "emissivity": 0.9, "reflected_temperature": 20.0}
```

``unit`` is one of ``celsius``, ``kelvin``, ``centikelvin``, ``linear``, ``counts``. Temperature
frames are apparent (black-body) temperatures; when an emissivity below 1 or an
object distance is given (sidecar or caller), they are corrected on the sidecar's
Planck curve (or the typical long-wave curve) by FLIR's model. The caller's
:class:`RadiometricOverrides` replace the file's or sidecar's conditions. See
docs/thermal-formats.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import tifffile
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.errors import InputError
from services.formats.files import atomic_output
from services.formats.flir import JPEG_SUFFIXES, flir_temperature, read_flir_jpeg, with_overrides
from services.formats.json_files import read_text, validate_json
from services.fusion.radiometry import KELVIN_OFFSET, PlanckConstants, correct_emissivity, counts_to_temperature

THERMAL_SUFFIXES = (".npy", ".tif", ".tiff", ".png")  # written and read
READ_SUFFIXES = THERMAL_SUFFIXES + JPEG_SUFFIXES  # read only: FLIR radiometric JPEG
_CENTIKELVIN_NO_DATA = (0, 65535)


class PlanckCurve(BaseModel):
    """The camera's Planck constants as its metadata lists them."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    R1: float = Field(gt=0)
    R2: float = Field(gt=0)
    B: float = Field(gt=0)
    F: float
    O: float

    def constants(self) -> PlanckConstants:
        return PlanckConstants(self.R1, self.R2, self.B, self.F, self.O)


class ThermalSidecar(BaseModel):
    """What the numbers of a thermal frame mean."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    unit: Literal["celsius", "kelvin", "centikelvin", "linear", "counts"]
    scale: float | None = Field(None, gt=0.0, description="linear: kelvin per count")
    offset: float | None = Field(None, description="linear: kelvin at count 0")
    planck: PlanckCurve | None = None
    emissivity: float = Field(1.0, gt=0.0, le=1.0)
    reflected_temperature: float = Field(20.0, gt=-KELVIN_OFFSET)

    @model_validator(mode="after")
    def _counts_need_planck(self) -> ThermalSidecar:
        if self.unit == "counts" and self.planck is None:
            raise ValueError("raw counts need the camera's 'planck' constants (R1, R2, B, F, O)")
        if (self.unit == "linear") != (self.scale is not None):
            raise ValueError("'scale' (kelvin per count) and 'offset' (kelvin at 0) go with unit 'linear', and "
                             "only with it")
        return self


@dataclass(frozen=True)
class RadiometricOverrides:
    """The user's measurement conditions, replacing the file's or sidecar's (None keeps them).

    Temperatures in degrees C, humidity a fraction in [0, 1], distance in metres. Oxidised steel at
    1000 degrees C has an emissivity of about 0.8..0.9 (cameras default to 0.95).
    """

    emissivity: float | None = None
    reflected_c: float | None = None
    atmosphere_c: float | None = None
    relative_humidity: float | None = None
    distance_m: float | None = None

    def __post_init__(self) -> None:
        checks = (
            ("emissivity", self.emissivity, lambda v: 0.0 < v <= 1.0, "in (0, 1]"),
            ("reflected temperature", self.reflected_c, lambda v: -KELVIN_OFFSET < v < 5000.0,
             "a temperature in degrees C (above -273.15)"),
            ("atmospheric temperature", self.atmosphere_c, lambda v: -KELVIN_OFFSET < v < 5000.0,
             "a temperature in degrees C (above -273.15)"),
            ("relative humidity", self.relative_humidity, lambda v: 0.0 <= v <= 1.0,
             "a fraction in [0, 1] (0.5 is 50 %)"),
            ("object distance", self.distance_m, lambda v: 0.0 <= v <= 1e5, "in 0..100000 m"),
        )
        for name, value, ok, what in checks:
            if value is not None and not (math.isfinite(value) and ok(value)):
                raise InputError(f"{name} must be {what}; got {value}")


def sidecar_path(frame_path: str | Path) -> Path:
    """The sidecar JSON that describes a frame: same directory and stem, ``.json``."""
    return Path(frame_path).with_suffix(".json")


def _read_sidecar(path: Path) -> ThermalSidecar | None:
    if not path.is_file():
        return None
    return validate_json(ThermalSidecar, read_text(path, "thermal sidecar"), f"{path}: invalid thermal sidecar")


def _check_path(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in READ_SUFFIXES:
        raise InputError(f"{path}: thermal frames must be {', '.join(READ_SUFFIXES)} files")
    if not path.is_file():
        raise InputError(f"{path}: thermal frame file is missing")
    return suffix


def _decode_array(content: bytes, suffix: str, source: str) -> np.ndarray:
    try:
        if suffix == ".npy":
            array = np.load(BytesIO(content), allow_pickle=False)
        elif suffix == ".png":
            array = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
            if array is None:
                raise ValueError("OpenCV cannot decode it")
        else:
            array = tifffile.imread(BytesIO(content))
    except Exception as error:  # numpy, OpenCV and tifffile raise many types for corrupt files
        raise InputError(f"{source}: cannot read the thermal frame ({error})") from None
    if np.asarray(array).size == 0:
        raise InputError(f"{source}: cannot read the thermal frame (no image data; corrupt or empty file)")
    return np.asarray(array)


def _default_unit(source: str, array: np.ndarray) -> str:
    if np.issubdtype(array.dtype, np.floating):
        return "celsius"
    if array.dtype == np.uint16:
        return "centikelvin"
    raise InputError(
        f"{source}: a {array.dtype} thermal frame is not radiometric; give degrees C as float TIFF/.npy, "
        f"centikelvin as 16-bit PNG/TIFF, raw counts with a sidecar {sidecar_path(source).name}, "
        "or a FLIR radiometric JPEG"
    )


def _object_temperature(values: np.ndarray, sidecar: ThermalSidecar, overrides: RadiometricOverrides) -> np.ndarray:
    """Degrees Celsius of the object from the frame's numbers in the sidecar's unit."""
    constants = sidecar.planck.constants() if sidecar.planck else None
    emissivity = sidecar.emissivity if overrides.emissivity is None else overrides.emissivity
    reflected = sidecar.reflected_temperature if overrides.reflected_c is None else overrides.reflected_c
    conditions = {"atmosphere_c": overrides.atmosphere_c, "distance_m": overrides.distance_m or 0.0}
    if overrides.relative_humidity is not None:
        conditions["relative_humidity"] = overrides.relative_humidity
    if sidecar.unit == "counts":
        return counts_to_temperature(values, constants, emissivity, reflected, **conditions)
    if sidecar.unit == "linear":
        offset, scale = KELVIN_OFFSET - (sidecar.offset or 0.0), sidecar.scale
    else:
        offset, scale = {"celsius": (0.0, 1.0), "kelvin": (KELVIN_OFFSET, 1.0),
                         "centikelvin": (KELVIN_OFFSET, 0.01)}[sidecar.unit]
    apparent = values * scale - offset
    if emissivity == 1.0 and conditions["distance_m"] == 0.0:
        return apparent
    return correct_emissivity(apparent, emissivity, reflected, constants, **conditions)


def read_thermal_frame(
    path: str | Path,
    size: tuple[int, int] | None = None,
    overrides: RadiometricOverrides | None = None,
) -> np.ndarray:
    """Read a thermal frame as object temperatures in degrees Celsius.

    Parameters
    ----------
    path : path
        The frame; a sidecar JSON of the same stem, if present, gives its unit (not for R-JPEGs,
        which carry their own constants).
    size : (width, height), optional
        The thermal camera's size; a frame of another size is refused.
    overrides : RadiometricOverrides, optional
        Measurement conditions replacing the file's or sidecar's.

    Returns
    -------
    temperature : (height, width) float32 array
        Degrees Celsius, NaN where the frame has no data.

    Raises
    ------
    InputError
        Unreadable file or sidecar, a file that is not the radiometric format it claims to be,
        inconsistent constants, not a 2-D image, wrong size, no finite value.
    """
    path = Path(path)
    suffix = _check_path(path)
    sidecar = None if suffix in JPEG_SUFFIXES else _read_sidecar(sidecar_path(path))
    return decode_thermal_frame(path.read_bytes(), suffix=suffix, source=str(path), size=size,
                                overrides=overrides, sidecar=sidecar)


def decode_thermal_frame(
    content: bytes,
    *,
    suffix: str,
    source: str,
    size: tuple[int, int] | None = None,
    overrides: RadiometricOverrides | None = None,
    sidecar: ThermalSidecar | None = None,
) -> np.ndarray:
    """:func:`read_thermal_frame` of a file's bytes (e.g. an upload), its format given by ``suffix``;
    errors name ``source``."""
    suffix = suffix.lower()
    overrides = overrides or RadiometricOverrides()
    if suffix not in READ_SUFFIXES:
        raise InputError(f"{source}: thermal frames must be {', '.join(READ_SUFFIXES)} files")
    if suffix in JPEG_SUFFIXES:
        image = read_flir_jpeg(content, source)
        array = image.counts
    else:
        array = _decode_array(content, suffix, source)
    if array.ndim != 2 or not (np.issubdtype(array.dtype, np.number) and not np.iscomplexobj(array)):
        raise InputError(f"{source}: a thermal frame must be a 2-D grey image of numbers; got {array.dtype} "
                         f"{array.shape}")
    height, width = array.shape
    if size is not None and (width, height) != tuple(size):
        raise InputError(
            f"{source}: thermal frame is {width}x{height} but the thermal camera is {size[0]}x{size[1]}"
        )
    try:
        if suffix in JPEG_SUFFIXES:
            conditions = with_overrides(image.conditions, emissivity=overrides.emissivity,
                                        reflected_c=overrides.reflected_c, atmosphere_c=overrides.atmosphere_c,
                                        relative_humidity=overrides.relative_humidity,
                                        distance_m=overrides.distance_m)
            temperature = flir_temperature(image, conditions)
        else:
            sidecar = sidecar or ThermalSidecar(unit=_default_unit(source, array))
            values = array.astype(np.float64)
            if sidecar.unit in ("centikelvin", "linear") and array.dtype == np.uint16:
                values[np.isin(array, _CENTIKELVIN_NO_DATA)] = np.nan
            if not np.isfinite(values).any():
                raise InputError(f"{source}: thermal frame has no finite value (all NaN or no data)")
            temperature = _object_temperature(values, sidecar, overrides)
    except InputError:
        raise
    except ValueError as error:
        raise InputError(f"{source}: {error}") from None
    if not np.isfinite(temperature).any():
        raise InputError(f"{source}: no pixel of the thermal frame gives a temperature (check the unit and "
                         "constants)")
    return temperature.astype(np.float32)


def is_radiometric_file(content: bytes, suffix: str) -> bool:
    """Whether an image file is a radiometric thermal file (a FLIR R-JPEG, or a float TIFF of degrees C) rather
    than an 8- or 16-bit grey image, e.g. a board image."""
    suffix = suffix.lower()
    if suffix in JPEG_SUFFIXES:
        return True
    if suffix not in (".tif", ".tiff"):
        return False
    try:
        with tifffile.TiffFile(BytesIO(content)) as tiff:
            return tiff.pages[0].dtype.kind == "f"
    except Exception:  # not a readable TIFF: the image reader names what is wrong
        return False


def write_thermal_frame(path: str | Path, temperature: np.ndarray) -> None:
    """Write a temperature image (degrees C): float32 for ``.tif``/``.tiff``/``.npy``, centikelvin for ``.png``.

    PNG values outside 0.01..655.34 K are stored as no data. The file appears
    atomically (written beside the target and renamed).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    temperature = np.asarray(temperature, dtype=np.float32)
    if suffix not in THERMAL_SUFFIXES:
        raise ValueError(f"Thermal frames are written as {', '.join(THERMAL_SUFFIXES)}; got {path.name!r}.")
    with atomic_output(path) as temporary:
        if suffix == ".npy":
            with open(temporary, "wb") as handle:
                np.save(handle, temperature)
        elif suffix in (".tif", ".tiff"):
            tifffile.imwrite(temporary, temperature)
        else:
            centikelvin = np.round((temperature.astype(np.float64) + KELVIN_OFFSET) * 100.0)
            in_range = np.isfinite(centikelvin) & (centikelvin > 0) & (centikelvin < 65535)
            temporary.write_bytes(cv2.imencode(".png", np.where(in_range, centikelvin, 0).astype(np.uint16))[1])

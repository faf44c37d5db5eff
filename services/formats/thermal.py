"""Thermal frames: temperature images in degrees Celsius, centikelvin, or raw counts with Planck constants.

Formats, chosen by the file and an optional sidecar JSON of the same stem
(``frame.png`` -> ``frame.json``):

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
frames are apparent (black-body) temperatures; when an emissivity below 1 is
given (sidecar or caller), they are corrected for it on the sidecar's Planck curve
(or the typical long-wave curve). See docs/temperature-field.md for the equation.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import tifffile
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.errors import InputError
from services.formats.files import atomic_output
from services.formats.json_files import read_text, validate_json
from services.fusion.radiometry import KELVIN_OFFSET, PlanckConstants, correct_emissivity, counts_to_temperature

THERMAL_SUFFIXES = (".npy", ".tif", ".tiff", ".png")
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


def sidecar_path(frame_path: str | Path) -> Path:
    """The sidecar JSON that describes a frame: same directory and stem, ``.json``."""
    return Path(frame_path).with_suffix(".json")


def _read_sidecar(path: Path) -> ThermalSidecar | None:
    if not path.is_file():
        return None
    return validate_json(ThermalSidecar, read_text(path, "thermal sidecar"), f"{path}: invalid thermal sidecar")


def _read_array(path: Path) -> np.ndarray:
    suffix = path.suffix.lower()
    if suffix not in THERMAL_SUFFIXES:
        raise InputError(f"{path}: thermal frames must be {', '.join(THERMAL_SUFFIXES)} files")
    if not path.is_file():
        raise InputError(f"{path}: thermal frame file is missing")
    try:
        if suffix == ".npy":
            array = np.load(path, allow_pickle=False)
        elif suffix == ".png":
            array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if array is None:
                raise ValueError("OpenCV cannot decode it")
        else:
            array = tifffile.imread(path)
    except Exception as error:  # numpy, OpenCV and tifffile raise many types for corrupt files
        raise InputError(f"{path}: cannot read the thermal frame ({error})") from None
    if np.asarray(array).size == 0:
        raise InputError(f"{path}: cannot read the thermal frame (no image data; corrupt or empty file)")
    return np.asarray(array)


def _default_unit(path: Path, array: np.ndarray) -> str:
    if np.issubdtype(array.dtype, np.floating):
        return "celsius"
    if array.dtype == np.uint16:
        return "centikelvin"
    raise InputError(
        f"{path}: a {array.dtype} thermal frame is not radiometric; give degrees C as float TIFF/.npy, "
        f"centikelvin as 16-bit PNG/TIFF, or raw counts with a sidecar {sidecar_path(path).name}"
    )


def _object_temperature(values: np.ndarray, sidecar: ThermalSidecar, emissivity: float) -> np.ndarray:
    """Degrees Celsius of the object from the frame's numbers in the sidecar's unit."""
    constants = sidecar.planck.constants() if sidecar.planck else None
    if sidecar.unit == "counts":
        return counts_to_temperature(values, constants, emissivity, sidecar.reflected_temperature)
    if sidecar.unit == "linear":
        offset, scale = KELVIN_OFFSET - (sidecar.offset or 0.0), sidecar.scale
    else:
        offset, scale = {"celsius": (0.0, 1.0), "kelvin": (KELVIN_OFFSET, 1.0),
                         "centikelvin": (KELVIN_OFFSET, 0.01)}[sidecar.unit]
    apparent = values * scale - offset
    if emissivity == 1.0:
        return apparent
    return correct_emissivity(apparent, emissivity, sidecar.reflected_temperature, constants)


def read_thermal_frame(
    path: str | Path,
    size: tuple[int, int] | None = None,
    emissivity: float | None = None,
) -> np.ndarray:
    """Read a thermal frame as object temperatures in degrees Celsius.

    Parameters
    ----------
    path : path
        The frame; a sidecar JSON of the same stem, if present, gives its unit.
    size : (width, height), optional
        The thermal camera's size; a frame of another size is refused.
    emissivity : float, optional
        Emissivity of the object, overriding the sidecar's.

    Returns
    -------
    temperature : (height, width) float32 array
        Degrees Celsius, NaN where the frame has no data.

    Raises
    ------
    InputError
        Unreadable file or sidecar, not a 2-D image, wrong size, no finite value.
    """
    path = Path(path)
    sidecar = _read_sidecar(sidecar_path(path))
    array = _read_array(path)
    if array.ndim != 2 or not (np.issubdtype(array.dtype, np.number) and not np.iscomplexobj(array)):
        raise InputError(f"{path}: a thermal frame must be a 2-D grey image of numbers; got {array.dtype} {array.shape}")
    height, width = array.shape
    if size is not None and (width, height) != tuple(size):
        raise InputError(
            f"{path}: thermal frame is {width}x{height} but the thermal camera is {size[0]}x{size[1]}"
        )
    sidecar = sidecar or ThermalSidecar(unit=_default_unit(path, array))
    values = array.astype(np.float64)
    if sidecar.unit in ("centikelvin", "linear") and array.dtype == np.uint16:
        values[np.isin(array, _CENTIKELVIN_NO_DATA)] = np.nan
    if not np.isfinite(values).any():
        raise InputError(f"{path}: thermal frame has no finite value (all NaN or no data)")
    emissivity = sidecar.emissivity if emissivity is None else emissivity
    if not 0.0 < emissivity <= 1.0:
        raise InputError(f"emissivity must be in (0, 1]; got {emissivity}")
    try:
        temperature = _object_temperature(values, sidecar, emissivity)
    except ValueError as error:
        raise InputError(f"{path}: {error}") from None
    if not np.isfinite(temperature).any():
        raise InputError(f"{path}: no pixel of the thermal frame gives a temperature (check the unit and constants)")
    return temperature.astype(np.float32)


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

"""The registration file REG.json (a public format).

```json
{"model": "translation" | "rigid" | "similarity" | "affine" | "homography",
 "matrix": [[h11, h12, h13], [h21, h22, h23], [h31, h32, h33]],
 "mi": 1.52, "nmi": 1.27, "bins": 32, "log_base": 2.0}
```

``matrix`` maps infrared pixel coordinates to visible pixel coordinates
(homogeneous, pixel centres at integers as OpenCV): ``[x_v, y_v, w] = matrix
@ [x_ir, y_ir, 1]``, then divide by ``w``. ``mi`` is the mutual information in
units of ``log_base`` (2: bits) from a joint histogram of ``bins`` x ``bins``
cells, ``nmi`` the normalised mutual information (H(A) + H(B)) / H(A, B),
both over the overlap at infrared resolution. See docs/registration.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.formats.json_files import read_text, validate_json, write_text_atomically
from services.registration.models import MODELS
from services.registration.register import Registration

Row = Annotated[list[float], Field(min_length=3, max_length=3)]


class RegistrationFile(BaseModel):
    """The validated content of REG.json."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: Literal[MODELS]  # type: ignore[valid-type]
    matrix: Annotated[list[Row], Field(min_length=3, max_length=3)]
    mi: float
    nmi: float
    bins: int = Field(ge=2)
    log_base: float = Field(gt=0.0)

    @field_validator("matrix")
    @classmethod
    def _matrix_is_invertible(cls, matrix: list[list[float]]) -> list[list[float]]:
        array = np.asarray(matrix, dtype=np.float64)
        if not np.all(np.isfinite(array)):
            raise ValueError("the matrix must contain finite numbers")
        if abs(np.linalg.det(array)) < 1e-12:
            raise ValueError("the matrix must be invertible")
        return matrix

    @field_validator("log_base")
    @classmethod
    def _log_base_is_not_one(cls, log_base: float) -> float:
        if log_base == 1.0:
            raise ValueError("the log base must not be 1")
        return log_base

    @property
    def matrix_array(self) -> np.ndarray:
        return np.asarray(self.matrix, dtype=np.float64)


def registration_to_file(registration: Registration) -> RegistrationFile:
    """The file content of a registration result."""
    return RegistrationFile(
        model=registration.model, matrix=np.asarray(registration.matrix).tolist(), mi=registration.mi,
        nmi=registration.nmi, bins=registration.bins, log_base=registration.log_base,
    )


def parse_registration(text: str, source: str = "registration") -> RegistrationFile:
    """Validate REG.json text; errors name ``source`` and the field."""
    return validate_json(RegistrationFile, text, source)


def load_registration(path: str | Path) -> RegistrationFile:
    """Read and validate a REG.json file."""
    return parse_registration(read_text(path, "registration file"), str(path))


def save_registration(registration: RegistrationFile, path: str | Path) -> None:
    """Write REG.json atomically (a reader never sees half a file)."""
    write_text_atomically(path, json.dumps(registration.model_dump(), indent=2) + "\n")

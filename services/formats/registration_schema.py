"""The pydantic schema that validates REG.json when it is read (the format: :mod:`services.formats.registration`)."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.registration.models import MODELS

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

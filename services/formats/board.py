"""The calibration board specification (a public JSON format).

```json
{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0, "polarity": "auto"}
{"type": "charuco", "squares": [11, 8], "square_mm": 20.0, "marker_mm": 15.0, "dictionary": "DICT_5X5_100"}
{"type": "circles", "grid": [4, 11], "spacing_mm": 20.0, "asymmetric": true}
```

``polarity`` is ``"normal"`` (dark squares or dots on a light board),
``"inverted"`` (light on dark, as a hollowed board before a heater looks to an
infrared camera) or ``"auto"`` (try both; the default). The board frame has its
origin at the first detected feature, x along a row of ``inner_corners[0]``
(or ``grid[0]``) features, y across rows, z = 0 on the board. Unknown fields
and impossible sizes are refused. See docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Union

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, field_validator, model_validator

from services.formats.json_files import read_text, validate_json

Polarity = Literal["normal", "inverted", "auto"]
GridSize = Annotated[list[Annotated[int, Field(ge=2, le=200)]], Field(min_length=2, max_length=2)]
PositiveLength = Annotated[float, Field(gt=0, le=10_000)]


class _BoardBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    polarity: Polarity = "auto"


class ChessboardSpec(_BoardBase):
    """A chessboard; features are its inner corners."""

    type: Literal["chessboard"]
    inner_corners: GridSize
    square_mm: PositiveLength

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(columns, rows) of detectable features."""
        return self.inner_corners[0], self.inner_corners[1]

    def object_points(self) -> np.ndarray:
        """(N, 3) feature positions in board millimetres, row-major, z = 0."""
        cols, rows = self.pattern_size
        return _grid_points(cols, rows, self.square_mm, self.square_mm)


class CharucoSpec(_BoardBase):
    """A ChArUco board; features are the chessboard corners, identified by the ArUco markers."""

    type: Literal["charuco"]
    squares: GridSize
    square_mm: PositiveLength
    marker_mm: PositiveLength
    dictionary: str = "DICT_5X5_100"

    @field_validator("dictionary")
    @classmethod
    def _dictionary_exists(cls, name: str) -> str:
        if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
            raise ValueError(f"unknown ArUco dictionary {name!r} (for example DICT_5X5_100)")
        return name

    @model_validator(mode="after")
    def _marker_fits_in_square(self) -> "CharucoSpec":
        if self.marker_mm >= self.square_mm:
            raise ValueError(f"marker_mm ({self.marker_mm}) must be smaller than square_mm ({self.square_mm})")
        markers = (self.squares[0] * self.squares[1]) // 2
        available = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if markers > available:
            raise ValueError(f"the board needs {markers} markers but {self.dictionary} has only {available}")
        return self

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.squares[0] - 1, self.squares[1] - 1

    def object_points(self) -> np.ndarray:
        cols, rows = self.pattern_size
        return _grid_points(cols, rows, self.square_mm, self.square_mm)

    def opencv_board(self) -> "cv2.aruco.CharucoBoard":
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(tuple(self.squares), self.square_mm, self.marker_mm, dictionary)


class CirclesSpec(_BoardBase):
    """A grid of circles, symmetric or asymmetric (OpenCV's layout)."""

    type: Literal["circles"]
    grid: GridSize
    spacing_mm: PositiveLength
    asymmetric: bool = False

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.grid[0], self.grid[1]

    def object_points(self) -> np.ndarray:
        cols, rows = self.pattern_size
        if not self.asymmetric:
            return _grid_points(cols, rows, self.spacing_mm, self.spacing_mm)
        row, col = np.mgrid[0:rows, 0:cols]
        x = (2 * col + row % 2) * self.spacing_mm
        y = row * self.spacing_mm
        return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]).astype(np.float64)


BoardSpec = Annotated[Union[ChessboardSpec, CharucoSpec, CirclesSpec], Field(discriminator="type")]
MIN_VIEWS = 3  # board views a calibration needs at least (Zhang's method needs three poses)
_BOARD_ADAPTER = TypeAdapter(BoardSpec)
_BOARD_TYPES = frozenset({"chessboard", "charuco", "circles"})


def _grid_points(cols: int, rows: int, step_x: float, step_y: float) -> np.ndarray:
    row, col = np.mgrid[0:rows, 0:cols]
    return np.column_stack([col.ravel() * step_x, row.ravel() * step_y, np.zeros(col.size)]).astype(np.float64)


def parse_board(text: str, source: str = "board") -> BoardSpec:
    """Validate board JSON text; errors name ``source`` and the field."""
    return validate_json(_BOARD_ADAPTER, text, source, tags=_BOARD_TYPES)


def load_board(path: str | Path) -> BoardSpec:
    """Read and validate a board specification file."""
    return parse_board(read_text(path, "board file"), str(path))


def board_to_json(board: BoardSpec) -> str:
    return board.model_dump_json(indent=2)

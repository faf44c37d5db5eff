"""The camera calibration result file (JSON) and its report pictures.

```json
{"name": "thermal", "kind": "thermal", "width": 320, "height": 256,
 "K": [[...], [...], [...]], "dist": [k1, k2, p1, p2, k3], "distortion_model": "standard",
 "rms_px": 0.05, "std": {"fx": 0.1, "fy": 0.1, "cx": 0.2, ...},
 "board": {...board spec...},
 "views": [{"image": "ir01.png", "rms_px": 0.04, "polarity": "inverted",
            "R": [[...]], "t": [...], "pose_std": [rx, ry, rz, tx, ty, tz]}],
 "rejected": [{"image": "ir07.png", "reason": "reprojection RMS ... exceeds ..."}],
 "model_selection": {"reason": "radial has the lowest BIC ...",
                     "candidates": [{"model": "none", "rms_px": 0.9, "parameters": 100, "bic": -1200.0}, ...]},
 "corner_window": {"fraction": 0.2, "reason": "a half window of 0.2 of the corner spacing predicts ...",
                   "candidates": [{"fraction": 0.15, "held_out_rms_px": 0.35}, ...]}}
```

``model_selection`` is present when the lens model was chosen from the data (``--distortion auto``):
every candidate's RMS, number of estimated parameters (intrinsics and six per view) and Bayesian
information criterion, and why ``distortion_model`` won.

``corner_window`` is present for chessboard and ChArUco boards: the half window of the corners' saddle-point
refinement, as a fraction of the corner spacing, chosen from the views by cross-validation, with every
candidate's held-out reprojection RMS (empty with fewer than four views, when the default 0.25 is kept).
Projector calibrations with this camera refine its corners with the same window; files without the key
(written before it existed) mean 0.25.

``StationCalibrationFile`` (``"version": 1``) is what ``thermofield calibrate station`` writes beside the station's
rig: the device fixing the world frame, whether the intrinsics were refined, the reprojection RMS overall and in
the overlaps (px, and mm on the board), each adjusted camera's views, RMS and pose uncertainty (six degrees of
freedom: ``rx``, ``ry``, ``rz`` in degrees about the world axes, ``x``, ``y``, ``z`` of its centre in mm; the
reported sigma and the Jacobian's and the view jackknife's behind it), each pair of cameras that shared views, and
the images in which no board was found. docs/calibration.md, "Stations".

``views[i].R, t`` is the board-to-camera pose, x_cam = R x_board + t, in millimetres;
``pose_std`` holds the standard deviations of the Rodrigues vector (rad) and of t (mm).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from matplotlib.figure import Figure
from pydantic import BaseModel, ConfigDict, Field

from services.formats.board import BoardSpec
from services.formats.files import atomic_output
from services.formats.json_files import read_text, validate_json, write_model
from services.formats.rig import Matrix3
from services.geometry.camera_model import CameraModel, DeviceKind


class CalibratedView(BaseModel):
    model_config = ConfigDict(extra="forbid")

    image: str
    rms_px: float
    polarity: str
    R: Matrix3
    t: list[float]
    pose_std: list[float]


class RejectedView(BaseModel):
    model_config = ConfigDict(extra="forbid")

    image: str
    reason: str


class ModelCandidate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: str
    rms_px: float
    parameters: int
    bic: float


class ModelSelectionRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    reason: str
    candidates: list[ModelCandidate]


class WindowCandidate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fraction: float
    held_out_rms_px: float


class CornerWindowRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fraction: float = Field(gt=0, lt=0.5)
    reason: str
    candidates: list[WindowCandidate]


class CameraCalibrationFile(BaseModel):
    """What ``thermofield calibrate camera`` writes."""

    model_config = ConfigDict(extra="forbid")

    name: str
    kind: DeviceKind
    width: int
    height: int
    K: Matrix3
    dist: list[float]
    distortion_model: str
    rms_px: float
    std: dict[str, float]
    board: BoardSpec
    views: list[CalibratedView]
    rejected: list[RejectedView]
    model_selection: ModelSelectionRecord | None = None
    corner_window: CornerWindowRecord | None = None
    poorly_determined: list[str] = []

    def device(self) -> CameraModel:
        """The calibrated device at the world origin, as a rig entry."""
        return CameraModel(kind=self.kind, width=self.width, height=self.height, K=self.K, dist=self.dist)


class ProjectorCalibrationFile(BaseModel):
    """The report ``thermofield calibrate projector`` writes beside the rig."""

    model_config = ConfigDict(extra="forbid")

    projector_rms_px: float
    stereo_rms_px: float
    baseline_mm: float
    std: dict[str, float]
    views: list[str]
    per_view_rms_px: list[float]
    rejected: list[RejectedView]
    stereo_std: dict[str, float] = {}
    stereo_per_view_rms_px: list[list[float]] = []


class StereoCalibrationFile(BaseModel):
    """The report ``thermofield calibrate stereo`` writes beside the rig."""

    model_config = ConfigDict(extra="forbid")

    device: str
    reference: str
    stereo_rms_px: float
    baseline_mm: float
    pairs: list[str]
    per_view_rms_px: list[list[float]]


STATION_CALIBRATION_VERSION = 1


class StationDeviceRecord(BaseModel):
    """One camera of a station calibration (a head's camera or a thermal camera): its views, residual and the
    uncertainty of its pose in the world."""

    model_config = ConfigDict(extra="forbid")

    device: str
    head: str | None
    views: int
    rms_px: float
    pose_std: dict[str, float]
    pose_std_jacobian: dict[str, float]
    pose_std_jackknife: dict[str, float]


class StationOverlapRecord(BaseModel):
    """Two cameras that saw the board together: how many views, and their residual in those views."""

    model_config = ConfigDict(extra="forbid")

    devices: Annotated[list[str], Field(min_length=2, max_length=2)]
    views: int
    rms_px: float
    rms_mm: float


class StationCalibrationFile(BaseModel):
    """What ``thermofield calibrate station`` writes beside the station's rig (version 1)."""

    model_config = ConfigDict(extra="forbid")

    version: Literal[1] = STATION_CALIBRATION_VERSION
    world: str
    intrinsics: Literal["fixed", "refined"]
    board: BoardSpec
    rms_px: float
    overlap_rms_px: float
    overlap_rms_mm: float
    devices: list[StationDeviceRecord]
    overlaps: list[StationOverlapRecord]
    views: list[str]
    unseen: list[str] = []


def load_station_calibration(path: str | Path) -> StationCalibrationFile:
    """Read and validate a station calibration report."""
    return validate_json(StationCalibrationFile, read_text(path, "station calibration"),
                         f"{path}: not a station calibration file")


def load_camera_calibration(path: str | Path) -> CameraCalibrationFile:
    """Read and validate a camera calibration file."""
    return validate_json(CameraCalibrationFile, read_text(path, "camera calibration"),
                         f"{path}: not a camera calibration file")


def save_camera_calibration(calibration: CameraCalibrationFile, path: str | Path) -> None:
    """Write the calibration atomically (a reader never sees half a file)."""
    write_model(calibration, path)


def save_projector_calibration(report: ProjectorCalibrationFile, path: str | Path) -> None:
    """Write the projector calibration report atomically."""
    write_model(report, path)


def save_stereo_calibration(report: StereoCalibrationFile, path: str | Path) -> None:
    """Write the stereo calibration report atomically."""
    write_model(report, path)


def save_station_calibration(report: StationCalibrationFile, path: str | Path) -> None:
    """Write the station calibration report atomically."""
    write_model(report, path)


def save_figure(figure: Figure, path: str | Path) -> None:
    """Write a report figure as PNG atomically."""
    with atomic_output(path) as temporary:
        figure.savefig(temporary, format="png", dpi=100)

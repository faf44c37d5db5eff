"""The calibrated device: OpenCV's pinhole model with distortion and a world-to-device pose.

Only numpy here, so that the rig file, the API and the gateway can hold devices without loading the
compiled geometry; :mod:`services.geometry.camera` projects and back-projects through it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Literal

import numpy as np

VALID_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


def as_distortion(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients as a flat float64 array, checked to be one of OpenCV's lengths."""
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if dist.size not in VALID_DISTORTION_LENGTHS:
        raise ValueError(
            f"Distortion must have one of {VALID_DISTORTION_LENGTHS} coefficients; got {dist.size}."
        )
    return dist


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Device centre in world coordinates, C = -R^T t."""
    return -np.asarray(R, dtype=np.float64).T @ np.asarray(t, dtype=np.float64).ravel()


DeviceKind = Literal["camera", "projector", "thermal"]
DEVICE_KINDS: tuple[DeviceKind, ...] = ("camera", "projector", "thermal")


def _frozen(values: Any, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    """A read-only float64 copy of ``values``, checked against ``shape`` when given."""
    array = np.array(values, dtype=np.float64)
    if shape is not None and array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}; got {array.shape}.")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class CameraModel:
    """One calibrated device (camera, projector or thermal camera): OpenCV's pinhole model and its pose.

    Immutable and holding read-only arrays, so that geometry, triangulation, fusion and simulation share
    one object without rebuilding arrays. ``K`` (3, 3), ``dist`` (D,) in OpenCV order, ``R`` (3, 3) and
    ``t`` (3,) mapping world to device, x_dev = R x_world + t, in millimetres; ``width`` x ``height``
    pixels. Any array-like is accepted and copied. The rig file (``services.formats.rig``) parses to
    and from it.
    """

    kind: DeviceKind
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if self.kind not in DEVICE_KINDS:
            raise ValueError(f"A device kind must be one of {DEVICE_KINDS}; got {self.kind!r}.")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"A device's size must be positive; got {self.width}x{self.height}.")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "K", _frozen(self.K, (3, 3), "K"))
        object.__setattr__(self, "dist", _frozen(as_distortion(self.dist), None, "dist"))
        object.__setattr__(self, "R", _frozen(self.R, (3, 3), "R"))
        object.__setattr__(self, "t", _frozen(np.asarray(self.t, dtype=np.float64).ravel(), (3,), "t"))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    @cached_property
    def centre(self) -> np.ndarray:
        """Device centre in world coordinates, C = -R^T t (computed once)."""
        centre = camera_center(self.R, self.t)
        centre.flags.writeable = False
        return centre

    def replace(self, **changes: Any) -> CameraModel:
        """A copy with some fields changed (e.g. a new pose ``R``, ``t``)."""
        return replace(self, **changes)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """:func:`services.geometry.camera.project_points` of world points into this device."""
        from services.geometry.camera import project_points

        return project_points(points_world, self.K, self.dist, self.R, self.t)

    def to_device(self, points_world: np.ndarray) -> np.ndarray:
        """World points in this device's frame, R X + t."""
        return np.einsum("ij,nj->ni", self.R, np.asarray(points_world, dtype=np.float64)) + self.t

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (self.kind, self.size) == (other.kind, other.size) and all(
            np.array_equal(getattr(self, name), getattr(other, name)) for name in ("K", "dist", "R", "t"))

    def __hash__(self) -> int:
        return hash((self.kind, self.size, self.K.tobytes(), self.dist.tobytes(), self.R.tobytes(),
                     self.t.tobytes()))

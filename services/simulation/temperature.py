"""Temperature fields on scene surfaces, degrees Celsius (part of the scene file; see docs/simulator.md).

A ``TemperatureScene`` gives each surface of a ``Scene`` (same order) a smooth
temperature field,

    T(X, t) = base + g . (X - origin) + sum_k a_k exp(-|X - c_k|^2 / (2 r_k^2)) - cooling_rate * t,

a linear gradient plus Gaussian hot (a_k > 0) or cold (a_k < 0) spots, cooling at ``cooling_rate``
kelvin per second from the start of a capture (t in seconds; 0 by default). Rays that miss every
surface see ``background``.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class Spot(BaseModel):
    """A Gaussian hot or cold spot: ``amplitude`` kelvin at ``center``, standard deviation ``radius`` mm."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    center: Vector3
    radius: float = Field(gt=0)
    amplitude: float


class SurfaceTemperature(BaseModel):
    """A smooth temperature field on one surface, degrees Celsius, cooling at ``cooling_rate`` K/s."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base: float = Field(gt=-273.15)
    cooling_rate: float = Field(0.0, ge=0.0)
    gradient: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    origin: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    spots: list[Spot] = Field(default_factory=list)

    def evaluate(self, points: np.ndarray, time_s: float = 0.0) -> np.ndarray:
        """Temperature at world points (N, 3) -> (N,), ``time_s`` seconds after the capture started."""
        points = np.asarray(points, dtype=np.float64)
        temperature = self.base - self.cooling_rate * time_s + (points - np.asarray(self.origin)) @ np.asarray(self.gradient)
        for spot in self.spots:
            squared = np.sum((points - np.asarray(spot.center)) ** 2, axis=1)
            temperature = temperature + spot.amplitude * np.exp(-squared / (2 * spot.radius**2))
        return temperature


class TemperatureScene(BaseModel):
    """One temperature field per scene surface (same order), and what rays that miss see."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    surfaces: list[SurfaceTemperature] = Field(min_length=1)
    background: float = Field(25.0, gt=-273.15)


def surface_temperature(temperatures: TemperatureScene, points: np.ndarray, surface: np.ndarray,
                        time_s: float = 0.0) -> np.ndarray:
    """True temperature of points (N, 3) on scene surfaces ``surface`` (N,) ``time_s`` seconds into a capture;
    ``background`` where -1."""
    result = np.full(len(points), temperatures.background, dtype=np.float64)
    for index, field in enumerate(temperatures.surfaces):
        on_surface = surface == index
        if on_surface.any():
            result[on_surface] = field.evaluate(points[on_surface], time_s)
    return result

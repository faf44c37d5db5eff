"""Thermal elongation of materials: built-in tables after the Eurocodes and a handbook, or a user's table.

A material is a table of the relative thermal elongation (strain) Delta l / l, measured from the
reference temperature 20 degC, against temperature, linearly interpolated between its rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

REFERENCE_TEMPERATURE_C = 20.0
"""ISO 1: the temperature at which a part's nominal (cold) dimensions hold."""


@dataclass(frozen=True)
class Material:
    """A thermal-elongation table.

    Attributes
    ----------
    name : str
        What the table is of.
    temperatures : (K,) array
        Strictly increasing temperatures, degrees C; the table covers 20 degC.
    strains : (K,) array
        Relative elongation Delta l / l from 20 degC at each temperature.
    relative_uncertainty : float
        Standard uncertainty of the strain as a fraction of it (the table's own uncertainty).
    source : str
        Where the numbers come from.
    """

    name: str
    temperatures: np.ndarray
    strains: np.ndarray
    relative_uncertainty: float
    source: str

    def __post_init__(self) -> None:
        temperatures = np.asarray(self.temperatures, dtype=np.float64)
        strains = np.asarray(self.strains, dtype=np.float64)
        if temperatures.ndim != 1 or temperatures.shape != strains.shape or len(temperatures) < 2:
            raise ValueError(f"The elongation table of {self.name!r} needs at least two [T_C, strain] rows.")
        if not (np.isfinite(temperatures).all() and np.isfinite(strains).all()):
            raise ValueError(f"The elongation table of {self.name!r} has a non-finite value.")
        if np.any(np.diff(temperatures) <= 0):
            raise ValueError(f"The temperatures of the elongation table of {self.name!r} must increase strictly.")
        if not temperatures[0] <= REFERENCE_TEMPERATURE_C <= temperatures[-1]:
            raise ValueError(f"The elongation table of {self.name!r} must cover the reference temperature "
                             f"{REFERENCE_TEMPERATURE_C:g} degC (its range is {temperatures[0]:g} to "
                             f"{temperatures[-1]:g} degC).")
        if not 0 <= self.relative_uncertainty < 1:
            raise ValueError(f"The relative uncertainty of {self.name!r} must lie in [0, 1).")
        # strains relative to 20 degC, whatever the table's own zero
        strains = strains - np.interp(REFERENCE_TEMPERATURE_C, temperatures, strains)
        object.__setattr__(self, "temperatures", temperatures)
        object.__setattr__(self, "strains", strains)

    @property
    def range_c(self) -> tuple[float, float]:
        return float(self.temperatures[0]), float(self.temperatures[-1])

    def strain(self, temperature_c: np.ndarray) -> np.ndarray:
        """Delta l / l from 20 degC at each temperature (clamped to the table's ends)."""
        return np.interp(temperature_c, self.temperatures, self.strains)

    def mean_strain(self, start_c: float, end_c: np.ndarray) -> np.ndarray:
        """The mean of the interpolated strain over each temperature interval [start_c, end_c].

        Parameters
        ----------
        start_c : float
            The intervals' common end, degrees C.
        end_c : (N,) array
            Their other ends, degrees C.

        Returns
        -------
        (N,) array
            (E(end) - E(start)) / (end - start) with E the exact antiderivative of the piecewise-linear
            table (clamped ends continued as constants); the strain at the middle where the interval
            is shorter than 1 mK (exact there on a linear piece, and free of the difference's rounding).
        """
        end_c = np.asarray(end_c, dtype=np.float64)
        width = end_c - start_c
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (self._antiderivative(end_c) - self._antiderivative(np.float64(start_c))) / width
        short = np.abs(width) < 1e-3
        mean[short] = self.strain((start_c + end_c[short]) / 2)
        return mean

    @cached_property
    def _pieces(self) -> tuple[np.ndarray, np.ndarray]:
        """Per piece of the table: the strain's integral from the first temperature to the piece's start
        (K), and the strain's rate (1/K)."""
        widths = np.diff(self.temperatures)
        integral = np.concatenate([[0.0], np.cumsum(widths * (self.strains[:-1] + self.strains[1:]) / 2)])
        return integral[:-1], np.diff(self.strains) / widths

    def _antiderivative(self, temperature_c: np.ndarray) -> np.ndarray:
        """The integral of the strain from the table's first temperature to each temperature (exact: the
        strain is linear on each piece, constant beyond the table's ends)."""
        temperatures, strains = self.temperatures, self.strains
        piece = np.clip(np.searchsorted(temperatures, temperature_c, side="right") - 1, 0, len(temperatures) - 2)
        integral, rate = self._pieces
        clamped = np.clip(temperature_c, temperatures[0], temperatures[-1])
        offset = clamped - temperatures[piece]
        inside = integral[piece] + offset * (strains[piece] + 0.5 * rate[piece] * offset)
        # beyond an end the clamped strain is that end's: its integral grows linearly
        return inside + (temperature_c - clamped) * np.where(temperature_c > clamped, strains[-1], strains[0])

    def slope(self, temperature_c: np.ndarray) -> np.ndarray:
        """d(Delta l / l)/dT, 1/K, of the interpolated table (a central difference of 1 K)."""
        temperature_c = np.asarray(temperature_c, dtype=np.float64)
        return (self.strain(temperature_c + 0.5) - self.strain(temperature_c - 0.5)) / 1.0


def _eurocode_carbon_steel(theta: np.ndarray) -> np.ndarray:
    """EN 1993-1-2:2005, 3.4.1.1 (1): Delta l / l of carbon steel, 20..1200 degC."""
    return np.select(
        [theta < 750.0, theta <= 860.0],
        [1.2e-5 * theta + 0.4e-8 * theta**2 - 2.416e-4, np.full_like(theta, 1.1e-2)],
        2e-5 * theta - 6.2e-3,
    )


def _eurocode_stainless_steel(theta: np.ndarray) -> np.ndarray:
    """EN 1993-1-2:2005, annex C (C.3.1): Delta l / l of austenitic stainless steel, 20..1200 degC."""
    return (16.0 + 4.79e-3 * theta - 1.243e-6 * theta**2) * (theta - 20.0) * 1e-6


def _eurocode_aluminium(theta: np.ndarray) -> np.ndarray:
    """EN 1999-1-2:2007, 3.3.1.1: Delta l / l of aluminium alloys, 20..500 degC."""
    return 0.1e-7 * theta**2 + 22.5e-6 * theta - 4.5e-4


def _table(function, low: float, high: float, breaks: tuple[float, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """The function sampled every 5 K (and at its break points), fine enough that interpolation is exact to 1e-7."""
    theta = np.union1d(np.arange(low, high + 1e-9, 5.0), np.asarray(breaks, dtype=np.float64))
    return theta, function(theta)


def _titanium() -> tuple[np.ndarray, np.ndarray]:
    """Ti-6Al-4V from its mean expansion coefficients: 8.6 (20-100 degC), 9.2 (20-315), 9.7 (20-650) um/(m K)."""
    theta = np.array([20.0, 100.0, 315.0, 650.0])
    mean_coefficient = np.array([8.6, 8.6, 9.2, 9.7]) * 1e-6
    return theta, mean_coefficient * (theta - 20.0)


def _builtin() -> dict[str, Material]:
    carbon = _table(_eurocode_carbon_steel, 20.0, 1200.0, (749.999, 750.0, 860.0))
    stainless = _table(_eurocode_stainless_steel, 20.0, 1200.0)
    aluminium = _table(_eurocode_aluminium, 20.0, 500.0)
    return {
        "carbon-steel": Material("carbon-steel", *carbon, 0.03,
                                 "EN 1993-1-2:2005, 3.4.1.1: 2e-5 T - 6.2e-3 from 860 to 1200 degC, 1.1e-2 "
                                 "from 750 to 860 degC, 1.2e-5 T + 0.4e-8 T^2 - 2.416e-4 below"),
        "stainless-steel": Material("stainless-steel", *stainless, 0.03,
                                    "EN 1993-1-2:2005, annex C: (16 + 4.79e-3 T - 1.243e-6 T^2)(T - 20) 1e-6"),
        "aluminium": Material("aluminium", *aluminium, 0.03,
                              "EN 1999-1-2:2007, 3.3.1.1: 0.1e-7 T^2 + 22.5e-6 T - 4.5e-4, 20..500 degC"),
        "titanium-6al-4v": Material("titanium-6al-4v", *_titanium(), 0.05,
                                    "ASM Materials Properties Handbook: Titanium Alloys (1994), Ti-6Al-4V annealed: "
                                    "mean expansion 8.6, 9.2, 9.7 um/(m K) over 20-100, 20-315, 20-650 degC"),
    }


BUILTIN_MATERIALS: dict[str, Material] = _builtin()


def builtin_material(name: str) -> Material:
    """The built-in table of that name; a ``ValueError`` lists the known names."""
    try:
        return BUILTIN_MATERIALS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; built in are {', '.join(sorted(BUILTIN_MATERIALS))}, "
                         "or give an object with an 'elongation' table [[T_C, strain], ...]") from None

"""Radiometry of a thermal camera: raw sensor counts to object temperature with Planck's law.

A radiometric thermal camera turns the radiance it collects into raw counts that
follow a fitted Planck curve with five constants (R1, R2, B, F, O, as FLIR cameras
store them in their image metadata). The object temperature follows once the
part of the signal reflected from the surroundings is removed and the rest is
divided by the emissivity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KELVIN_OFFSET = 273.15


@dataclass(frozen=True)
class PlanckConstants:
    """The camera's fitted Planck curve, raw = R1 / (R2 (exp(B / T) - F)) - O, T in kelvin.

    The defaults are typical of a long-wave (7.5-14 um) microbolometer camera.
    """

    R1: float = 21106.77
    R2: float = 0.012545258
    B: float = 1501.0
    F: float = 1.0
    O: float = -7340.0

    def __post_init__(self) -> None:
        values = (self.R1, self.R2, self.B, self.F, self.O)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"Planck constants must be finite; got {values}.")
        if self.R1 <= 0 or self.R2 <= 0 or self.B <= 0:
            raise ValueError(f"Planck constants R1, R2 and B must be positive; got {self.R1}, {self.R2}, {self.B}.")


def blackbody_counts(temperature_c: np.ndarray, constants: PlanckConstants) -> np.ndarray:
    """Raw counts the camera reads from a black body at ``temperature_c`` degrees Celsius.

    Notes
    -----
    P(T) = R1 / (R2 (exp(B / T) - F)) - O with T in kelvin [1]_.

    References
    ----------
    .. [1] M. Vollmer and K.-P. Moellmann, "Infrared Thermal Imaging", 2nd ed.,
       Wiley-VCH, 2018, ch. 2 (Planck's law) and ch. 3 (camera calibration curves).
    """
    kelvin = np.asarray(temperature_c, dtype=np.float64) + KELVIN_OFFSET
    if np.any(kelvin <= 0):
        raise ValueError("Temperatures must be above absolute zero (-273.15 degrees C).")
    c = constants
    return c.R1 / (c.R2 * (np.exp(c.B / kelvin) - c.F)) - c.O


def blackbody_temperature(counts: np.ndarray, constants: PlanckConstants) -> np.ndarray:
    """Inverse of :func:`blackbody_counts`: degrees Celsius of a black body giving ``counts``.

    Counts at or below the curve's floor (no finite temperature) give NaN.
    """
    c = constants
    counts = np.asarray(counts, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        argument = c.R1 / (c.R2 * (counts + c.O)) + c.F
        kelvin = c.B / np.log(argument)
    kelvin = np.where((counts + c.O > 0) & (argument > 1), kelvin, np.nan)
    return kelvin - KELVIN_OFFSET


def counts_to_temperature(
    counts: np.ndarray,
    constants: PlanckConstants,
    emissivity: float = 1.0,
    reflected_temperature_c: float = 20.0,
) -> np.ndarray:
    """Object temperature in degrees Celsius from raw counts, emissivity and reflected temperature.

    Parameters
    ----------
    counts : array
        Raw sensor counts (any shape).
    constants : PlanckConstants
        The camera's Planck curve.
    emissivity : float
        Emissivity of the object in (0, 1].
    reflected_temperature_c : float
        Temperature of the surroundings the object reflects, degrees Celsius.

    Returns
    -------
    temperature : float64 array
        Object temperature, degrees Celsius; NaN where the counts are below the
        reflected part of the signal.

    Notes
    -----
    The measured signal is the emitted part plus the reflected part [1]_,

        S = e P(T_obj) + (1 - e) P(T_refl),

    so P(T_obj) = (S - (1 - e) P(T_refl)) / e and
    T_obj = B / ln(R1 / (R2 (P(T_obj) + O)) + F). Atmospheric transmission is
    taken as 1 (a short path through dry air).

    References
    ----------
    .. [1] M. Vollmer and K.-P. Moellmann, "Infrared Thermal Imaging", 2nd ed.,
       Wiley-VCH, 2018, sec. 2.4 and 3.2.
    """
    if not 0.0 < emissivity <= 1.0:
        raise ValueError(f"Emissivity must be in (0, 1]; got {emissivity}.")
    reflected = blackbody_counts(np.float64(reflected_temperature_c), constants)
    emitted = (np.asarray(counts, dtype=np.float64) - (1.0 - emissivity) * reflected) / emissivity
    return blackbody_temperature(emitted, constants)


def correct_emissivity(
    apparent_temperature_c: np.ndarray,
    emissivity: float,
    reflected_temperature_c: float = 20.0,
    constants: PlanckConstants | None = None,
) -> np.ndarray:
    """Object temperature from an apparent (black-body, emissivity 1) temperature image.

    The apparent temperature is turned back into counts on the camera's Planck
    curve (the typical long-wave curve when ``constants`` is None) and converted
    with :func:`counts_to_temperature`.
    """
    constants = constants or PlanckConstants()
    counts = blackbody_counts(apparent_temperature_c, constants)
    return counts_to_temperature(counts, constants, emissivity, reflected_temperature_c)

"""Radiometry of a thermal camera: raw sensor counts to object temperature with Planck's law.

A radiometric thermal camera turns the radiance it collects into raw counts that
follow a fitted Planck curve with five constants (R1, R2, B, F, O, as FLIR cameras
store them in their image metadata). The object temperature follows once the
parts of the signal the surroundings (reflected), the air and an external window
add are removed and the rest is divided by the emissivity and the transmissions:
FLIR's radiometric model, :func:`counts_to_temperature`.
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


@dataclass(frozen=True)
class AtmosphereConstants:
    """FLIR's fit of the atmosphere's transmission over the camera's band (the file's
    ``AtmosphericTrans*`` tags); the defaults are the values FLIR cameras store."""

    alpha1: float = 0.006569
    alpha2: float = 0.01262
    beta1: float = -0.002276
    beta2: float = -0.00667
    X: float = 1.9

    def __post_init__(self) -> None:
        values = (self.alpha1, self.alpha2, self.beta1, self.beta2, self.X)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"Atmospheric transmission constants must be finite; got {values}.")


def atmospheric_transmission(
    distance_m: float,
    atmosphere_c: float,
    relative_humidity: float,
    constants: AtmosphereConstants = AtmosphereConstants(),
) -> float:
    """Transmission of the air over half of the path from the object to the camera.

    Parameters
    ----------
    distance_m : float
        Object distance in metres (>= 0).
    atmosphere_c : float
        Air temperature, degrees Celsius.
    relative_humidity : float
        Relative humidity as a fraction in [0, 1].
    constants : AtmosphereConstants
        The camera's fit of the band's transmission.

    Returns
    -------
    tau : float
        Transmission in (0, 1] of one half of the path (FLIR's model splits the path at an
        optional external window; without one the whole path transmits ``tau**2``).

    Notes
    -----
    The water vapour content (mmHg-like units of FLIR's fit) at air temperature ``t`` (degrees C) is

        H2O = RH exp(1.5587 + 0.06939 t - 0.00027816 t^2 + 0.00000068455 t^3),

    and the transmission of a path of length d / 2 is [1]_ [2]_

        tau = X exp(-sqrt(d / 2) (alpha1 + beta1 sqrt(H2O)))
              + (1 - X) exp(-sqrt(d / 2) (alpha2 + beta2 sqrt(H2O))).

    References
    ----------
    .. [1] G. J. Tattersall, "Thermimage: Thermal Image Analysis", R package,
       ``raw2temp`` (the FLIR equations as derived on the ExifTool forum, topic 4898).
    .. [2] W. Minkina and S. Dudzik, "Infrared Thermography: Errors and Uncertainties",
       Wiley, 2009, ch. 2 (the measurement equation with atmosphere).
    """
    if not (np.isfinite(distance_m) and distance_m >= 0):
        raise ValueError(f"Object distance must be a finite number of metres >= 0; got {distance_m}.")
    if not 0.0 <= relative_humidity <= 1.0:
        raise ValueError(f"Relative humidity must be a fraction in [0, 1]; got {relative_humidity}.")
    if not (np.isfinite(atmosphere_c) and atmosphere_c > -KELVIN_OFFSET):
        raise ValueError(f"Atmospheric temperature must be above absolute zero; got {atmosphere_c} degrees C.")
    t = float(atmosphere_c)
    water = relative_humidity * np.exp(1.5587 + 0.06939 * t - 0.00027816 * t**2 + 0.00000068455 * t**3)
    c = constants
    root = -np.sqrt(distance_m / 2.0)
    return float(c.X * np.exp(root * (c.alpha1 + c.beta1 * np.sqrt(water)))
                 + (1.0 - c.X) * np.exp(root * (c.alpha2 + c.beta2 * np.sqrt(water))))


def counts_to_temperature(
    counts: np.ndarray,
    constants: PlanckConstants,
    emissivity: float = 1.0,
    reflected_temperature_c: float = 20.0,
    *,
    atmosphere_c: float | None = None,
    relative_humidity: float = 0.5,
    distance_m: float = 0.0,
    atmosphere: AtmosphereConstants = AtmosphereConstants(),
    window_temperature_c: float | None = None,
    window_transmission: float = 1.0,
) -> np.ndarray:
    """Object temperature in degrees Celsius from raw counts by FLIR's radiometric model.

    Parameters
    ----------
    counts : array
        Raw sensor counts (any shape).
    constants : PlanckConstants
        The camera's Planck curve.
    emissivity : float
        Emissivity of the object in (0, 1].
    reflected_temperature_c : float
        Apparent temperature of the surroundings the object reflects, degrees Celsius.
    atmosphere_c : float, optional
        Air temperature, degrees Celsius (default: the reflected temperature).
    relative_humidity : float
        Relative humidity of the air as a fraction in [0, 1].
    distance_m : float
        Object distance in metres; 0 means no atmosphere (transmission 1).
    atmosphere : AtmosphereConstants
        The camera's fit of the atmosphere's transmission.
    window_temperature_c : float, optional
        Temperature of an external infrared window, degrees Celsius (default: the air's).
    window_transmission : float
        Transmission of that window in (0, 1]; 1 is no window.

    Returns
    -------
    temperature : float64 array
        Object temperature, degrees Celsius; NaN where the counts are below what the
        surroundings, the air and the window alone give.

    Notes
    -----
    With P(T) = R1 / (R2 (exp(B / T) - F)) - O the black-body counts at T kelvin, tau1 and tau2
    the transmissions of the two halves of the path (:func:`atmospheric_transmission`) and
    tau_w the window's, the camera measures [1]_ [2]_

        S = e tau1 tau_w tau2 P(T_obj) + (1 - e) tau1 tau_w tau2 P(T_refl)
            + (1 - tau1) tau_w tau2 P(T_atm) + (1 - tau_w) tau2 P(T_win) + (1 - tau2) P(T_atm),

    so that

        P(T_obj) = S / (e tau1 tau_w tau2) - (1 - e) / e P(T_refl) - (1 - tau1) / (e tau1) P(T_atm)
                   - (1 - tau_w) / (e tau1 tau_w) P(T_win) - (1 - tau2) / (e tau1 tau_w tau2) P(T_atm)

    and T_obj = B / ln(R1 / (R2 (P(T_obj) + O)) + F). With no distance and no window this is
    S = e P(T_obj) + (1 - e) P(T_refl).

    References
    ----------
    .. [1] G. J. Tattersall, "Thermimage: Thermal Image Analysis", R package, ``raw2temp``.
    .. [2] M. Vollmer and K.-P. Moellmann, "Infrared Thermal Imaging", 2nd ed.,
       Wiley-VCH, 2018, sec. 2.4 and 3.2.
    """
    if not 0.0 < emissivity <= 1.0:
        raise ValueError(f"Emissivity must be in (0, 1]; got {emissivity}.")
    if not 0.0 < window_transmission <= 1.0:
        raise ValueError(f"Window transmission must be in (0, 1]; got {window_transmission}.")
    atmosphere_c = reflected_temperature_c if atmosphere_c is None else atmosphere_c
    window_temperature_c = atmosphere_c if window_temperature_c is None else window_temperature_c
    tau = atmospheric_transmission(distance_m, atmosphere_c, relative_humidity, atmosphere)
    reflected = blackbody_counts(np.float64(reflected_temperature_c), constants)
    air = blackbody_counts(np.float64(atmosphere_c), constants)
    window = blackbody_counts(np.float64(window_temperature_c), constants)
    e, tw = emissivity, window_transmission
    background = ((1.0 - e) / e * reflected + (1.0 - tau) / (e * tau) * air
                  + (1.0 - tw) / (e * tau * tw) * window + (1.0 - tau) / (e * tau * tw * tau) * air)
    emitted = np.asarray(counts, dtype=np.float64) / (e * tau * tw * tau) - background
    return blackbody_temperature(emitted, constants)


def correct_emissivity(
    apparent_temperature_c: np.ndarray,
    emissivity: float,
    reflected_temperature_c: float = 20.0,
    constants: PlanckConstants | None = None,
    **conditions: float | AtmosphereConstants | None,
) -> np.ndarray:
    """Object temperature from an apparent (black-body, emissivity 1) temperature image.

    The apparent temperature is turned back into counts on the camera's Planck
    curve (the typical long-wave curve when ``constants`` is None) and converted
    with :func:`counts_to_temperature`, to which ``conditions`` (atmosphere, distance,
    window) are passed.
    """
    constants = constants or PlanckConstants()
    counts = blackbody_counts(apparent_temperature_c, constants)
    return counts_to_temperature(counts, constants, emissivity, reflected_temperature_c, **conditions)

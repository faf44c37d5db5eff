"""Spectral optics of a hot-part scene: projector spectrum, camera band-pass filter, sensor and emissivity.

A visible camera sees two kinds of light from a forging: the pattern the projector throws on it,
reflected by its albedo, and the steel's own thermal emission eps(lambda) B(lambda, T) (Planck's
law). Both reach the sensor through the same lens, filter and quantum efficiency, so their ratio
follows from the spectra alone; the sensor's electron rate follows from the projector's power, the
lit area, the lens and the pixel. The ``optics`` block of a scene file (version 1) holds the figures;
docs/hot-parts.md derives the ratios they give.
"""

from __future__ import annotations

from functools import cached_property
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

PLANCK_H = 6.62607015e-34  # J s
LIGHT_C = 2.99792458e8  # m / s
BOLTZMANN_K = 1.380649e-23  # J / K
KELVIN_OFFSET = 273.15
WAVELENGTHS_NM = np.arange(350.0, 1101.0, 1.0)  # silicon's response ends near 1100 nm

# Typical quantum efficiency of a monochrome front-side-illuminated global-shutter CMOS sensor
# (the shape of published curves of 3..3.5 um pixel sensors, e.g. Sony Pregius mono), approximate.
_MONO_CMOS_QE = ((350, 0.20), (400, 0.50), (450, 0.66), (500, 0.72), (550, 0.71), (600, 0.64), (650, 0.55),
                 (700, 0.45), (750, 0.36), (800, 0.28), (850, 0.21), (900, 0.14), (950, 0.08), (1000, 0.04),
                 (1050, 0.015), (1100, 0.0))
# Phosphor-converted white LED: blue pump and broad phosphor emission, shares of the radiant power.
_WHITE_LED = ((450.0, 20.0, 0.25), (570.0, 110.0, 0.75))

SpectralTable = Annotated[list[Annotated[list[float], Field(min_length=2, max_length=2)]], Field(min_length=2)]


def planck_radiance(wavelength_nm: np.ndarray, temperature_c: np.ndarray) -> np.ndarray:
    """Black-body spectral radiance, W m^-2 sr^-1 nm^-1.

    Notes
    -----
    B(lambda, T) = 2 h c^2 / lambda^5 / (exp(h c / (lambda k T)) - 1) [1]_.

    References
    ----------
    .. [1] M. Planck, "Ueber das Gesetz der Energieverteilung im Normalspectrum", Annalen der Physik 309(3), 1901.
    """
    wavelength = np.asarray(wavelength_nm, dtype=np.float64) * 1e-9
    kelvin = np.asarray(temperature_c, dtype=np.float64) + KELVIN_OFFSET
    with np.errstate(over="ignore"):
        return 2 * PLANCK_H * LIGHT_C**2 / wavelength**5 / np.expm1(PLANCK_H * LIGHT_C / (wavelength * BOLTZMANN_K
                                                                                         * kelvin)) * 1e-9


def _gaussian(centre_nm: float, fwhm_nm: float) -> np.ndarray:
    sigma = fwhm_nm / (2 * np.sqrt(2 * np.log(2)))
    return np.exp(-0.5 * ((WAVELENGTHS_NM - centre_nm) / sigma) ** 2)


def _table(pairs, name: str) -> np.ndarray:
    pairs = np.asarray(pairs, dtype=np.float64)
    if np.any(np.diff(pairs[:, 0]) <= 0):
        raise ValueError(f"{name}: the wavelengths must increase")
    return np.interp(WAVELENGTHS_NM, pairs[:, 0], pairs[:, 1], left=0.0, right=0.0)


class ProjectorOptics(BaseModel):
    """The projector's light: spectrum and radiant power at full white, spread over the lit area.

    ``white_led`` is a phosphor-converted white LED (a 450 nm pump and a broad 570 nm phosphor band);
    ``blue_led`` a Gaussian line at ``centre_nm`` with ``fwhm_nm``. ``lit_area_m2`` is the area the
    full image covers at the part (1280 x 800 px at f = 1500 px and 600 mm: 0.51 x 0.32 m).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    spectrum: Literal["white_led", "blue_led"] = "white_led"
    centre_nm: float = Field(450.0, gt=300.0, lt=1100.0)
    fwhm_nm: float = Field(20.0, gt=0.0)
    radiant_power_w: float = Field(10.0, gt=0.0)
    lit_area_m2: float = Field(0.164, gt=0.0)

    def spectral_power(self) -> np.ndarray:
        """Radiant power per nm on ``WAVELENGTHS_NM``, W nm^-1, integrating to ``radiant_power_w``."""
        if self.spectrum == "blue_led":
            shape = _gaussian(self.centre_nm, self.fwhm_nm)
        else:
            shape = sum(share * _gaussian(centre, fwhm) / np.trapezoid(_gaussian(centre, fwhm), WAVELENGTHS_NM)
                        for centre, fwhm, share in _WHITE_LED)
        return self.radiant_power_w * shape / np.trapezoid(shape, WAVELENGTHS_NM)


class BandPassFilter(BaseModel):
    """An interference band-pass filter: flat top of ``peak_transmission`` over ``fwhm_nm`` about
    ``centre_nm``, steep (8th-order Butterworth) edges, blocking to optical density ``blocking_od`` outside."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    centre_nm: float = Field(gt=300.0, lt=1100.0)
    fwhm_nm: float = Field(gt=0.0)
    peak_transmission: float = Field(0.9, gt=0.0, le=1.0)
    blocking_od: float = Field(5.0, ge=0.0)

    def transmission(self) -> np.ndarray:
        """Transmission on ``WAVELENGTHS_NM``."""
        inband = self.peak_transmission / (1 + ((WAVELENGTHS_NM - self.centre_nm) / (self.fwhm_nm / 2)) ** 16)
        return np.maximum(inband, 10.0 ** -self.blocking_od)


class SensorOptics(BaseModel):
    """The visible camera's lens and sensor in physical units.

    ``quantum_efficiency`` is ``"mono_cmos"`` (a typical monochrome CMOS curve) or a table of
    [wavelength nm, QE] pairs. The gain is ``full_well_e / (2^bit_depth - 1)`` electrons per grey
    level, so the output saturates where the pixel's well does. Frames are uint8 at 8 bits and uint16
    holding 0..2^bit_depth - 1 at 10 and 12 bits.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    quantum_efficiency: Literal["mono_cmos"] | SpectralTable = "mono_cmos"
    pixel_pitch_um: float = Field(3.45, gt=0.0)
    f_number: float = Field(4.0, gt=0.0)
    lens_transmission: float = Field(0.9, gt=0.0, le=1.0)
    full_well_e: float = Field(10500.0, gt=0.0)
    read_noise_e: float = Field(2.5, ge=0.0)
    bit_depth: Literal[8, 10, 12] = 12

    def qe(self) -> np.ndarray:
        """Quantum efficiency on ``WAVELENGTHS_NM``."""
        table = _MONO_CMOS_QE if self.quantum_efficiency == "mono_cmos" else self.quantum_efficiency
        return _table(table, "quantum_efficiency")

    @property
    def full_scale(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def gain_e_per_dn(self) -> float:
        return self.full_well_e / self.full_scale

    @property
    def dtype(self) -> type:
        return np.uint8 if self.bit_depth == 8 else np.uint16


class Optics(BaseModel):
    """Version 1 of a scene's optics: projector, optional camera filter, sensor and the parts' emissivity.

    ``emissivity`` is grey (one number; oxidised steel: 0.8..0.9 across 400..1000 nm) or a table of
    [wavelength nm, emissivity] pairs, for every surface.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1] = 1
    projector: ProjectorOptics = Field(default_factory=ProjectorOptics)
    camera_filter: BandPassFilter | None = None
    sensor: SensorOptics = Field(default_factory=SensorOptics)
    emissivity: Annotated[float, Field(gt=0.0, le=1.0)] | SpectralTable = 0.85

    @model_validator(mode="after")
    def _tables_are_valid(self) -> Optics:
        self.sensor.qe()
        self._emissivity()
        return self

    def _emissivity(self) -> np.ndarray:
        if isinstance(self.emissivity, float | int):
            return np.full(WAVELENGTHS_NM.shape, float(self.emissivity))
        values = _table(self.emissivity, "emissivity")
        if np.any(values < 0) or np.any(values > 1):
            raise ValueError("emissivity: values must lie in [0, 1]")
        return values

    @cached_property
    def _band(self) -> np.ndarray:
        """Electrons per second per pixel from one photon s^-1 m^-2 sr^-1 nm^-1 of radiance at each wavelength."""
        sensor = self.sensor
        filter_ = 1.0 if self.camera_filter is None else self.camera_filter.transmission()
        etendue = (sensor.pixel_pitch_um * 1e-6) ** 2 * np.pi / (4 * sensor.f_number**2)
        return etendue * sensor.lens_transmission * filter_ * sensor.qe()

    def _electrons_per_s(self, radiance: np.ndarray) -> np.ndarray:
        """Electron rate of spectral radiances (..., wavelengths) in W m^-2 sr^-1 nm^-1."""
        photons = radiance * (WAVELENGTHS_NM * 1e-9) / (PLANCK_H * LIGHT_C)
        return np.trapezoid(photons * self._band, WAVELENGTHS_NM, axis=-1)

    @cached_property
    def white_rate(self) -> float:
        """Electrons per second per pixel from full projector light on a white Lambertian surface at normal incidence.

        Notes
        -----
        The surface's radiance is L(lambda) = E(lambda) / pi with irradiance E = P s(lambda) / A; a pixel of
        pitch p behind a lens of f-number N and transmission tau collects p^2 pi tau L / (4 N^2) [1]_.

        References
        ----------
        .. [1] R. W. Boyd, "Radiometry and the Detection of Optical Radiation", Wiley, 1983, ch. 5.
        """
        projector = self.projector
        return float(self._electrons_per_s(projector.spectral_power() / projector.lit_area_m2 / np.pi))

    def glow_rate(self, temperature_c: np.ndarray) -> np.ndarray:
        """Electrons per second per pixel from a surface's own emission eps(lambda) B(lambda, T)."""
        temperature = np.asarray(temperature_c, dtype=np.float64)
        radiance = self._emissivity() * planck_radiance(WAVELENGTHS_NM, temperature[..., None])
        return self._electrons_per_s(radiance)

    def glow_to_pattern(self, temperature_c: np.ndarray, albedo: float) -> np.ndarray:
        """The ratio of a surface's glow to the full pattern it reflects (albedo ``albedo``, normal incidence)."""
        return self.glow_rate(temperature_c) / (albedo * self.white_rate)

    @cached_property
    def _glow_table(self) -> tuple[np.ndarray, np.ndarray]:
        temperatures = np.arange(200.0, 2001.0, 1.0)
        return temperatures, np.log(self.glow_rate(temperatures) / self.white_rate)

    def relative_glow(self, temperature_c: np.ndarray) -> np.ndarray:
        """Glow in units of full projector light on white (the simulator's irradiance unit), float32.

        Interpolated in log from a table at every kelvin from 200 to 2000 C (error below 1e-4 relative);
        0 below 200 C, where steel's visible glow is more than 15 orders of magnitude below the pattern.
        """
        temperatures, log_glow = self._glow_table
        temperature = np.asarray(temperature_c, dtype=np.float64)
        if np.any(temperature > temperatures[-1]):
            raise ValueError(f"Glow is tabulated up to {temperatures[-1]:.0f} C; got {np.nanmax(temperature):.0f} C.")
        glow = np.exp(np.interp(temperature, temperatures, log_glow))
        return np.where(temperature >= temperatures[0], glow, 0.0).astype(np.float32)

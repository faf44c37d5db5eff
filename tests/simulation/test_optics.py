import numpy as np
import pytest
from pydantic import ValidationError

from services.simulation.optics import BandPassFilter, Optics, SensorOptics, WAVELENGTHS_NM, planck_radiance
from services.simulation.presets import hot_optics

PART_ALBEDO = 0.15  # oxidised steel, 1 - emissivity


def test_planck_radiance_peaks_at_wiens_wavelength():
    wavelengths = np.arange(500.0, 5000.0, 0.5)
    for temperature in (1000.0, 1500.0):
        peak = wavelengths[np.argmax(planck_radiance(wavelengths, temperature))]
        assert peak == pytest.approx(2.897771955e6 / (temperature + 273.15), abs=1.0)


def test_planck_radiance_matches_a_tabulated_value():
    # 1 um at 1273.15 K: 2hc^2/l^5 / (exp(hc/(l k T)) - 1) = 1.1912e8 / (exp(11.3017) - 1) W m^-2 sr^-1 um^-1
    expected = 1.19104e8 / np.expm1(14387.77 / 1273.15) * 1e-3
    assert planck_radiance(1000.0, 1000.0) == pytest.approx(expected, rel=1e-4)


def test_white_projector_glow_is_a_few_to_a_hundred_times_the_pattern():
    ratios = hot_optics("white").glow_to_pattern(np.array([1000.0, 1100.0, 1200.0, 1250.0]), PART_ALBEDO)
    assert 3 <= ratios[0] <= 20
    assert 50 <= ratios[-1] <= 100
    assert np.all(np.diff(ratios) > 0)


def test_blue_projector_behind_a_450_40_filter_sees_about_one_percent_glow_at_1200_c():
    ratio = float(hot_optics("blue", (450.0, 40.0)).glow_to_pattern(1200.0, PART_ALBEDO))
    assert 0.005 <= ratio <= 0.02
    unfiltered = float(hot_optics("blue").glow_to_pattern(1200.0, PART_ALBEDO))
    assert unfiltered > 50 * ratio  # the filter does the work: without it the near infrared glow passes


def test_electron_rate_follows_the_lens_and_pixel():
    base = Optics()
    slower = Optics(sensor=SensorOptics(f_number=8.0))
    bigger = Optics(sensor=SensorOptics(pixel_pitch_um=6.9))
    assert slower.white_rate == pytest.approx(base.white_rate / 4)
    assert bigger.white_rate == pytest.approx(base.white_rate * 4)
    assert base.glow_rate(1200.0) / base.white_rate == pytest.approx(float(base.relative_glow(1200.0)), rel=1e-4)


def test_relative_glow_is_zero_when_cold_and_refuses_beyond_its_table():
    optics = Optics()
    assert optics.relative_glow(np.array([25.0]))[0] == 0
    with pytest.raises(ValueError, match="up to 2000 C"):
        optics.relative_glow(np.array([2500.0]))


def test_filter_blocks_outside_its_band():
    transmission = BandPassFilter(centre_nm=450.0, fwhm_nm=40.0).transmission()
    assert transmission[WAVELENGTHS_NM == 450.0][0] == pytest.approx(0.9)
    assert transmission[WAVELENGTHS_NM == 800.0][0] == pytest.approx(1e-5)


def test_bad_optics_are_refused():
    with pytest.raises(ValidationError, match="wavelengths must increase"):
        Optics(emissivity=[[600.0, 0.8], [500.0, 0.8]])
    with pytest.raises(ValidationError):
        Optics(sensor=SensorOptics(bit_depth=14))

import numpy as np
import pytest

from services.fusion.radiometry import (
    PlanckConstants, blackbody_counts, blackbody_temperature, correct_emissivity, counts_to_temperature,
)

TEMPERATURES = np.array([-20.0, 25.0, 300.0, 750.0, 1100.0])


def test_counts_follow_plancks_law_and_invert_exactly():
    constants = PlanckConstants()
    counts = blackbody_counts(TEMPERATURES, constants)
    kelvin = TEMPERATURES + 273.15
    np.testing.assert_allclose(counts, constants.R1 / (constants.R2 * (np.exp(constants.B / kelvin) - 1)) - constants.O)
    assert np.all(np.diff(counts) > 0)
    np.testing.assert_allclose(blackbody_temperature(counts, constants), TEMPERATURES, atol=1e-9)


def test_object_temperature_removes_reflection_and_divides_by_emissivity():
    constants = PlanckConstants(R1=16000.0, R2=0.03, B=1400.0, F=1.2, O=-3000.0)
    for emissivity, reflected in [(1.0, 20.0), (0.9, 20.0), (0.5, 200.0)]:
        signal = (emissivity * blackbody_counts(TEMPERATURES, constants)
                  + (1 - emissivity) * blackbody_counts(np.float64(reflected), constants))
        np.testing.assert_allclose(counts_to_temperature(signal, constants, emissivity, reflected), TEMPERATURES,
                                   atol=1e-8)


def test_lower_emissivity_means_a_hotter_object_than_it_looks():
    apparent = np.array([400.0, 900.0])
    assert np.all(correct_emissivity(apparent, 0.8) > apparent)
    np.testing.assert_allclose(correct_emissivity(apparent, 1.0), apparent, atol=1e-9)


def test_signal_below_the_curve_is_nan():
    constants = PlanckConstants()
    assert np.isnan(blackbody_temperature(np.array([-constants.O - 1.0]), constants)).all()


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="Emissivity"):
        counts_to_temperature(np.ones(2), PlanckConstants(), emissivity=0.0)
    with pytest.raises(ValueError, match="positive"):
        PlanckConstants(R1=-1.0)
    with pytest.raises(ValueError, match="absolute zero"):
        blackbody_counts(np.array([-300.0]), PlanckConstants())

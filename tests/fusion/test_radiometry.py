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


def test_the_air_transmits_less_over_longer_and_wetter_paths():
    from services.fusion.radiometry import atmospheric_transmission

    assert atmospheric_transmission(0.0, 20.0, 0.5) == 1.0
    by_distance = [atmospheric_transmission(d, 20.0, 0.5) for d in (1.0, 10.0, 100.0)]
    assert 1.0 > by_distance[0] > by_distance[1] > by_distance[2] > 0.0
    assert atmospheric_transmission(10.0, 30.0, 0.9) < atmospheric_transmission(10.0, 30.0, 0.1)
    with pytest.raises(ValueError, match="Relative humidity must be a fraction"):
        atmospheric_transmission(1.0, 20.0, 50.0)
    with pytest.raises(ValueError, match="Object distance"):
        atmospheric_transmission(-1.0, 20.0, 0.5)


def test_the_full_model_inverts_its_forward_equation():
    """Counts built by the measurement equation (object, reflection, air over both halves of the path, a
    window) give back the object temperature."""
    from services.fusion.radiometry import AtmosphereConstants, atmospheric_transmission

    constants, air = PlanckConstants(R1=16000.0, R2=0.03, B=1400.0, F=1.2, O=-3000.0), AtmosphereConstants()
    e, reflected, atmosphere, humidity, distance, window, tw = 0.85, 40.0, 10.0, 0.7, 30.0, 25.0, 0.9
    tau = atmospheric_transmission(distance, atmosphere, humidity, air)
    p = lambda celsius: blackbody_counts(np.float64(celsius), constants)  # noqa: E731
    signal = (e * tau * tw * tau * blackbody_counts(TEMPERATURES, constants) + (1 - e) * tau * tw * tau * p(reflected)
              + (1 - tau) * tw * tau * p(atmosphere) + (1 - tw) * tau * p(window) + (1 - tau) * p(atmosphere))
    found = counts_to_temperature(signal, constants, e, reflected, atmosphere_c=atmosphere, relative_humidity=humidity,
                                  distance_m=distance, atmosphere=air, window_temperature_c=window,
                                  window_transmission=tw)
    np.testing.assert_allclose(found, TEMPERATURES, atol=1e-8)
    # no distance and no window: the reflection-only model
    plain = counts_to_temperature(signal, constants, e, reflected)
    direct = (signal - (1 - e) * p(reflected)) / e
    np.testing.assert_allclose(plain, blackbody_temperature(direct, constants), atol=1e-9)

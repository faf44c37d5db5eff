import numpy as np
import pytest

from services.structured_light.low_snr import estimate_camera_noise, phase_noise_scale, refine_low_snr


def _phase_shift_fit(amplitude, noise, steps, rng, size=(60, 80)):
    """Modulation and quality of noisy N-step samples of known amplitude, as the decoder computes them."""
    phase = rng.uniform(0, 2 * np.pi, size)
    shifts = 2 * np.pi * np.arange(steps) / steps
    samples = 100 + amplitude * np.cos(phase[None] - shifts[:, None, None]) + rng.normal(0, noise, (steps, *size))
    c = np.tensordot(np.cos(shifts), samples, axes=1)
    s = np.tensordot(np.sin(shifts), samples, axes=1)
    modulation = 2 * np.hypot(c, s) / steps
    ac = ((samples - samples.mean(axis=0)) ** 2).sum(axis=0)
    quality = steps * modulation**2 / 2 / ac
    return modulation, quality


def test_camera_noise_is_estimated_from_fit_residuals():
    rng = np.random.default_rng(0)
    modulation, quality = _phase_shift_fit(40.0, 1.5, 12, rng)
    assert estimate_camera_noise(modulation, quality, 12) == pytest.approx(1.5, rel=0.1)


def test_predicted_sigma_matches_the_spread_of_decoded_phase():
    rng = np.random.default_rng(1)
    steps, period, amplitude, noise = 8, 16.0, 5.0, 1.5
    shifts = 2 * np.pi * np.arange(steps) / steps
    samples = amplitude * np.cos(1.0 - shifts[:, None]) + rng.normal(0, noise, (steps, 20000))
    phase = np.arctan2(np.sin(shifts) @ samples, np.cos(shifts) @ samples)
    spread = np.std(phase) * period / (2 * np.pi)
    predicted = phase_noise_scale(steps, period, noise) / amplitude
    assert predicted == pytest.approx(spread, rel=0.1)


def test_refinement_reduces_noise_without_bias_and_rejects_outliers():
    rng = np.random.default_rng(2)
    v, u = np.mgrid[0:80, 0:120]
    truth = 100 + 1.5 * u + 0.2 * v
    modulation = np.clip(2 + 0.5 * u, 0, 60).astype(float)  # a terminator: the signal fades to the left
    scale = phase_noise_scale(12, 16.0, 1.5)
    sigma = scale / modulation
    noisy = truth + rng.normal(0, 1, truth.shape) * sigma
    noisy[40, 10] += 16  # a period slip in the weak region
    refined = refine_low_snr(noisy, modulation, scale, threshold=0.1)
    weak = (sigma > 0.1)[2:-2, 2:-2]
    before = (noisy - truth)[2:-2, 2:-2][weak]
    after = (refined - truth)[2:-2, 2:-2][weak]
    finite = np.isfinite(after)
    assert finite.mean() > 0.95
    assert np.abs(after[finite]).mean() < 0.4 * np.abs(before).mean()
    assert abs(after[finite].mean()) < 0.02  # unbiased although the weights are one-sided
    assert np.isnan(refined[40, 10])
    strong = sigma <= 0.1
    np.testing.assert_array_equal(refined[strong], noisy[strong].astype(np.float32))


def test_shapes_must_match():
    with pytest.raises(ValueError, match="same shape"):
        refine_low_snr(np.zeros((3, 3)), np.zeros((3, 4)), 1.0)


def test_a_steep_field_keeps_its_pixels_and_a_period_slip_is_still_rejected():
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:60, 0:80]
    truth = 100 + 5.0 * u + 0.3 * v  # a limb: the coordinate changes by more than max_step across the window
    modulation = np.full(truth.shape, 4.0)
    scale = phase_noise_scale(12, 16.0, 1.5)
    noisy = truth + rng.normal(0, 1, truth.shape) * scale / modulation
    noisy[30, 40] += 16  # a period slip
    refined = refine_low_snr(noisy, modulation, scale, threshold=0.1, max_step=4.0)
    inner = (slice(2, -2), slice(2, -2))
    kept = np.isfinite(refined[inner])
    assert kept.mean() > 0.97
    before = np.abs(noisy - truth)[inner][kept]
    assert np.abs(refined[inner][kept] - truth[inner][kept]).mean() < 0.4 * before.mean()
    assert np.isnan(refined[30, 40])

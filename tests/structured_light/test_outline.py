import cv2
import numpy as np
import pytest

from services.structured_light.decode import Rejection
from services.structured_light.outline import estimate_camera_blur, outline_corrected

SUPERSAMPLE = 5
FULL_SCALE = 255.0


def _blurred(samples, sigma):
    """Pixel areas averaged from a supersampled image, then the optics' Gaussian blur, as the simulator does."""
    height, width = samples.shape[0] // SUPERSAMPLE, samples.shape[1] // SUPERSAMPLE
    pixels = samples.reshape(height, SUPERSAMPLE, width, SUPERSAMPLE).mean(axis=(1, 3))
    return cv2.GaussianBlur(pixels, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)


def _total_spread(sigma):
    """Standard deviation of OpenCV's sampled Gaussian kernel and the pixel's 1-px box together."""
    size = int(round(sigma * 8 + 1)) | 1
    kernel = cv2.getGaussianKernel(size, sigma, cv2.CV_32F).ravel().astype(float)
    offsets = np.arange(size) - size // 2
    return np.sqrt((kernel * offsets**2).sum() / kernel.sum() + 1 / 12)


def _subpixel_grid(height, width):
    offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    v = (np.arange(height)[:, None] + offsets[None]).ravel()
    u = (np.arange(width)[:, None] + offsets[None]).ravel()
    return np.meshgrid(u, v)


def _rejection(intensity):
    return np.where(intensity < 0.02 * FULL_SCALE, Rejection.DARK, 0).astype(np.uint8)


@pytest.mark.parametrize("sigma", [0.5, 0.7, 1.0, 1.5])
def test_blur_is_measured_from_a_lit_discs_outline(sigma):
    rng = np.random.default_rng(0)
    u, v = _subpixel_grid(240, 240)
    albedo = 0.6 + 0.05 * np.sin(u / 40.0) * np.cos(v / 35.0)  # a smooth texture
    lit = np.hypot(u - 118.3, v - 121.7) < 90.0
    intensity = FULL_SCALE * 0.8 * _blurred((albedo * lit).astype(np.float32), sigma)
    intensity = np.clip(np.rint(intensity + rng.normal(0, 1.5, intensity.shape)), 0, FULL_SCALE).astype(np.float32)
    estimate = estimate_camera_blur(intensity, _rejection(intensity))
    assert estimate == pytest.approx(_total_spread(sigma), rel=0.08)


def test_a_gradual_fade_is_not_taken_for_blur():
    u, v = _subpixel_grid(200, 200)
    fade = np.clip((u - 60.0) / 40.0, 0, 1)  # a terminator: the light falls off over 40 px
    intensity = (FULL_SCALE * 0.8 * _blurred(fade.astype(np.float32), 0.7)).astype(np.float32)
    assert estimate_camera_blur(intensity, _rejection(intensity)) is None


def test_no_outline_gives_no_estimate():
    intensity = np.full((100, 100), 150.0, np.float32)
    assert estimate_camera_blur(intensity, np.zeros((100, 100), np.uint8)) is None


def _edge_capture(sigma, period, slope):
    """Light fading in over 6 px beyond column 40.3 (a terminator) on a linear coordinate field, its fringes
    and intensity blurred by the camera, and the coordinate decoded from the blurred fringe phase."""
    u, v = _subpixel_grid(60, 100)
    lit = np.clip((u - 40.3) / 6.0, 0, 1).astype(np.float32)
    truth_samples = 200.0 + slope * u + 0.1 * v
    fringe = lit * np.exp(2j * np.pi * truth_samples / period)
    signal = _blurred(fringe.real.astype(np.float32), sigma) + 1j * _blurred(fringe.imag.astype(np.float32), sigma)
    intensity = (FULL_SCALE * 0.7 * _blurred(lit, sigma)).astype(np.float32)
    cols, rows = np.meshgrid(np.arange(100.0), np.arange(60.0))
    truth = 200.0 + slope * cols + 0.1 * rows
    decoded = truth + period / (2 * np.pi) * np.angle(signal * np.exp(-2j * np.pi * truth / period))
    rejection = _rejection(intensity)
    decoded[rejection != 0] = np.nan
    return decoded.astype(np.float32), truth, intensity, rejection


def test_blur_bias_beside_the_outline_is_corrected():
    sigma, period, slope = 0.7, 16.0, 0.8
    decoded, truth, intensity, rejection = _edge_capture(sigma, period, slope)
    corrected = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma))
    beside = (slice(2, -2), 42)  # 3 px from the last dark column, 39
    before = np.abs(decoded - truth)[beside]
    after = np.abs(corrected - truth)[beside]
    assert np.nanmax(before) > 0.1  # the blur bias is there
    assert np.isfinite(after).mean() >= 0.6  # and kept, corrected, rather than dropped
    assert np.nanmax(after) < 0.2 * np.nanmax(before)
    far = (slice(None), slice(50, None))
    np.testing.assert_array_equal(corrected[far], decoded[far])  # away from the outline: untouched


def test_without_a_blur_the_wider_margin_drops_the_ramp():
    sigma, period, slope = 0.7, 16.0, 0.8
    decoded, _, intensity, rejection = _edge_capture(sigma, period, slope)
    dropped = outline_corrected(decoded, intensity, rejection, period, None)
    corrected = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma))
    assert np.isfinite(dropped).sum() < np.isfinite(corrected).sum()
    kept = np.isfinite(dropped)
    np.testing.assert_array_equal(dropped[kept], decoded[kept])


def test_a_blurrier_camera_widens_the_margin():
    """The margin scales with the measured blur: round(2.6 s) pixels, 2 px when focused, 4 px at s = 1.5."""
    sigma, period, slope = 1.5, 16.0, 0.3
    decoded, _, intensity, rejection = _edge_capture(sigma, period, slope)
    focused = outline_corrected(decoded, intensity, rejection, period, _total_spread(0.7))
    blurry = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma))
    first_decoded = np.argmax(np.isfinite(decoded[30]))
    assert np.argmax(np.isfinite(blurry[30])) > np.argmax(np.isfinite(focused[30])) >= first_decoded + 1
    assert np.isfinite(blurry).sum() < np.isfinite(focused).sum()


def test_bad_input_is_refused():
    image = np.zeros((10, 10), np.float32)
    with pytest.raises(ValueError, match="same shape"):
        estimate_camera_blur(image, np.zeros((10, 11), np.uint8))
    with pytest.raises(ValueError, match="shape of the intensity"):
        outline_corrected(np.zeros((9, 10)), image, np.zeros((10, 10), np.uint8), 16.0, 0.7)
    with pytest.raises(ValueError, match="positive number of pixels"):
        outline_corrected(image, image, np.zeros((10, 10), np.uint8), 16.0, -0.7)
    with pytest.raises(ValueError, match="positive number of projector pixels"):
        outline_corrected(image, image, np.zeros((10, 10), np.uint8), 0.0, 0.7)


def _shadow_capture(sigma, fade_px):
    """A plate under room light (ambient 40 grey levels) whose projected fringes end at column 50.3, in a step
    (a projector shadow, ``fade_px`` 0) or fading in over ``fade_px`` pixels (a terminator); the coordinate
    decoded from the blurred fringes, the pattern-less pixels LOW_MODULATION (not dark: the room lights them)."""
    u, v = _subpixel_grid(40, 100)
    lit = (u > 50.3) if fade_px == 0 else np.clip((u - 50.3) / fade_px, 0, 1)
    lit = lit.astype(np.float32)
    period, slope = 16.0, 0.8
    truth_samples = 300.0 + slope * u
    fringe = lit * np.exp(2j * np.pi * truth_samples / period)
    signal = _blurred(fringe.real.astype(np.float32), sigma) + 1j * _blurred(fringe.imag.astype(np.float32), sigma)
    modulation = (FULL_SCALE * 0.35 * np.abs(signal)).astype(np.float32)
    intensity = (40.0 + FULL_SCALE * 0.35 * _blurred(lit, sigma)).astype(np.float32)
    cols = np.meshgrid(np.arange(100.0), np.arange(40.0))[0]
    truth = 300.0 + slope * cols
    decoded = truth + period / (2 * np.pi) * np.angle(signal * np.exp(-2j * np.pi * truth / period))
    rejection = np.where(modulation < 0.004 * FULL_SCALE, Rejection.LOW_MODULATION, 0).astype(np.uint8)
    decoded[rejection != 0] = np.nan
    return decoded.astype(np.float32), intensity, modulation, rejection, cols, period


def test_a_projector_shadow_under_room_light_keeps_no_leaked_code():
    """Pixels inside the shadow that only carry their lit neighbour's blurred fringes (and code) are dropped
    when the modulation is given; by the brightness alone, which the room light holds up, they were kept."""
    sigma = 0.7
    decoded, intensity, modulation, rejection, cols, period = _shadow_capture(sigma, 0)
    inside_shadow = cols < 50.3
    leaked = inside_shadow & np.isfinite(decoded)
    assert leaked.any()  # the blur leaks a pattern into the shadow: the failure this guards against
    by_brightness = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma))
    assert np.isfinite(by_brightness[inside_shadow]).any()
    corrected = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma), modulation=modulation)
    assert not np.isfinite(corrected[inside_shadow]).any()
    assert np.isfinite(corrected[:, 56:]).all()  # the lit plate beyond the margin stays


def test_a_terminators_fade_is_not_taken_for_a_shadow():
    """Light fading in over 30 px keeps its pattern, and its code, down to a pixel beside the pattern-less ones."""
    sigma = 0.7
    decoded, intensity, modulation, rejection, cols, period = _shadow_capture(sigma, 30.0)
    corrected = outline_corrected(decoded, intensity, rejection, period, _total_spread(sigma), modulation=modulation)
    faded_in = (cols > 56) & (cols < 80)
    assert np.isfinite(corrected[faded_in]).mean() >= 0.99


def test_modulation_of_another_shape_is_refused():
    image = np.zeros((10, 10), np.float32)
    with pytest.raises(ValueError, match="modulation"):
        outline_corrected(image, image, np.zeros((10, 10), np.uint8), 16.0, 0.7, modulation=np.zeros((9, 10)))

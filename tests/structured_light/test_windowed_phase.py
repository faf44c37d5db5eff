import numpy as np
import pytest

from services.structured_light.decode import decode
from services.structured_light.patterns import generate_sequence
from services.structured_light.windowed_phase import windowed_frames

WIDTH, HEIGHT = 128, 24  # projector; the "camera" sees projector column c at pixel column c


def _decode(frames, sequence):
    return decode(frames, sequence, saturation_level=np.inf, min_intensity=-np.inf, min_modulation=0.0,
                  edge_margin=0)


def test_the_windowed_phase_is_the_centres_where_the_modulation_ramps_to_zero():
    sequence, patterns = generate_sequence(WIDTH, HEIGHT)
    ramp = np.linspace(1.0, 0.02, WIDTH)[None, :] ** 2 * 400  # a terminator: the pattern fades across the window
    frames = (ramp * patterns.astype(np.float32) / 255).astype(np.float32)
    support = np.ones((HEIGHT, WIDTH), dtype=bool)
    windowed, gain, coverage = windowed_frames(frames, sequence, support, sigma_px=1.0)
    decoded = _decode(windowed, sequence)
    inside = (slice(3, -3), slice(3, -3))
    columns = np.broadcast_to(np.arange(WIDTH, dtype=np.float64), (HEIGHT, WIDTH))
    # the 8-bit patterns' rounding is the floor of the error; an undemodulated window would read the
    # modulation-weighted centroid, s^2 d ln(B)/dx up to 0.5 px off here
    assert np.abs(decoded.projector_x - columns)[inside].max() < 0.05
    assert np.all(coverage[inside] == pytest.approx(1.0, abs=1e-5))
    assert np.nanmedian(gain[inside]) == pytest.approx(0.29, abs=0.02)


def test_the_window_divides_the_phase_noise_by_its_noise_gain():
    sequence, patterns = generate_sequence(WIDTH, HEIGHT * 4)
    rng = np.random.default_rng(0)
    frames = (200 * patterns.astype(np.float32) / 255 + 20.0 * rng.standard_normal(patterns.shape)).astype(np.float32)
    support = np.ones(frames.shape[1:], dtype=bool)
    windowed, gain, _ = windowed_frames(frames, sequence, support, sigma_px=1.0)
    inside = (slice(4, -4), slice(4, -4))
    columns = np.broadcast_to(np.arange(WIDTH, dtype=np.float64), frames.shape[1:])[inside]
    raw = _decode(frames, sequence).projector_x[inside] - columns
    filtered = _decode(windowed, sequence).projector_x[inside] - columns
    both = (np.abs(raw) < 4) & (np.abs(filtered) < 4)  # a misread Gray bit of the raw pixels is not noise
    assert both.mean() > 0.99
    assert np.std(filtered[both]) == pytest.approx(np.std(raw[both]) * np.nanmedian(gain[inside]), rel=0.25)


def test_a_window_off_the_support_has_no_value():
    sequence, patterns = generate_sequence(WIDTH, HEIGHT)
    frames = (300 * patterns.astype(np.float32) / 255).astype(np.float32)
    support = np.ones((HEIGHT, WIDTH), dtype=bool)
    support[:, 64:] = False  # another surface beyond column 64
    windowed, gain, coverage = windowed_frames(frames, sequence, support)
    assert np.all(np.isnan(gain[5:-5, 63:])) and np.all(np.isnan(windowed[:, 5:-5, 63:]))
    assert np.all(np.isfinite(gain[5:-5, 5:62])) and np.all(np.isfinite(windowed[:, 5:-5, 5:62]))
    assert coverage[10, 63] < 0.9 < coverage[10, 62]


def test_bad_input_is_refused():
    sequence, patterns = generate_sequence(WIDTH, HEIGHT)
    frames = patterns.astype(np.float32)
    with pytest.raises(ValueError, match="support"):
        windowed_frames(frames, sequence, np.ones((2, 2), dtype=bool))
    with pytest.raises(ValueError, match="sigma"):
        windowed_frames(frames, sequence, np.ones((HEIGHT, WIDTH), dtype=bool), sigma_px=0)

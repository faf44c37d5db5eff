"""Decoding: exact round trips for the default and foreign sequences, rejections, noise, bit depths."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from services.formats.sequence import parse_sequence
from services.structured_light.decode import Rejection, decode
from services.structured_light.patterns import generate_sequence, render_patterns


def _camera(patterns, dark=20.0, bright=230.0, noise=0.0, blur=0.0, axis=2, dtype=np.uint8, seed=0):
    """An identity camera: pixel (r, c) sees projector pixel (r, c), with gain, blur and noise."""
    image = dark + (bright - dark) * patterns.astype(np.float64) / 255.0
    if blur:
        image = gaussian_filter1d(image, blur, axis=axis, mode="nearest")
    if noise:
        image = image + np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return np.clip(np.rint(image), 0, np.iinfo(dtype).max).astype(dtype)


def _sequence(frames, width, height=4):
    return parse_sequence(json.dumps({"projector": {"width": width, "height": height}, "frames": frames}))


def _truth(height, width):
    rows, cols = np.mgrid[0:height, 0:width]
    return cols.astype(np.float64), rows.astype(np.float64)


def _gray(axis, bits, inverted=(False,)):
    return [{"file": f"g{axis}{bit}{inv}.png", "kind": "gray", "axis": axis, "bit": bit, "inverted": inv}
            for bit in bits for inv in inverted]


def _phase(axis, period, steps, order=None):
    return [{"file": f"p{axis}{period}_{k}.png", "kind": "phase", "axis": axis, "period": period, "step": k,
             "steps": steps} for k in (order or range(steps))]


REFERENCES = [{"file": "white.png", "kind": "white"}, {"file": "black.png", "kind": "black"}]


def test_default_sequence_round_trip_is_exact():
    sequence, patterns = generate_sequence(1280, 24)
    decoded = decode(_camera(patterns), sequence)
    truth_x, _ = _truth(24, 1280)
    assert np.all(decoded.rejection == Rejection.VALID)
    assert np.abs(decoded.projector_x - truth_x).max() < 0.02  # 8-bit quantisation of the sinusoid only
    assert np.all(np.isnan(decoded.projector_y))
    assert decoded.coded_axes == ("x",)
    assert decoded.projector_x.dtype == np.float32 and decoded.rejection.dtype == np.uint8
    assert decoded.quality.min() > 0.99
    np.testing.assert_allclose(decoded.modulation, 105.0, atol=1.0)  # (230 - 20) / 2
    np.testing.assert_allclose(decoded.intensity, 230.0)


def test_both_axes_round_trip():
    sequence, patterns = generate_sequence(200, 150, axes="xy", period=12, steps=5)
    decoded = decode(_camera(patterns), sequence)
    truth_x, truth_y = _truth(150, 200)
    assert decoded.valid.all()
    assert np.abs(decoded.projector_x - truth_x).max() < 0.05
    assert np.abs(decoded.projector_y - truth_y).max() < 0.05


FOREIGN = {
    "gray with inverses, all bits, no references": (_gray("x", range(9, -1, -1), (False, True)), 0.0),
    "gray against white/black, least significant first": (REFERENCES + _gray("x", range(10)), 0.0),
    "gray against white/black, bits shuffled": (
        [REFERENCES[1]] + _gray("x", [3, 9, 0, 5, 1, 8, 2, 7, 4, 6]) + [REFERENCES[0]], 0.0),
    "gray planes shown only inverted": (REFERENCES + _gray("x", range(9, -1, -1), (True,)), 0.0),
    "two least significant bits dropped": (REFERENCES + _gray("x", range(9, 1, -1)), 1.5),
    "gray with inverses + 4-step, period 20": (_gray("x", range(9, 2, -1), (False, True)) + _phase("x", 20, 4), 0.05),
    "gray thresholded on the phase offset + 3-step, period 16": (_gray("x", range(9, 2, -1)) + _phase("x", 16, 3), 0.05),
    "plain gray (stripes = period) + 6-step in shuffled order": (
        REFERENCES + _gray("x", range(9, 3, -1)) + _phase("x", 16, 6, [3, 0, 5, 1, 4, 2]), 0.05),
    "multi-frequency phase, no gray": (_phase("x", 1024, 4) + _phase("x", 100, 4) + _phase("x", 10, 4), 0.05),
    "multi-frequency phase unwrapped by a coarse gray code": (
        REFERENCES + _gray("x", range(9, 6, -1)) + _phase("x", 128, 5) + _phase("x", 16, 5), 0.05),
    "rows only": (_gray("y", range(9, -1, -1), (False, True)), 0.0),
}


@pytest.mark.parametrize("name", FOREIGN)
def test_foreign_sequence_round_trip(name):
    frames, tolerance = FOREIGN[name]
    axis = next(frame["axis"] for frame in frames if "axis" in frame)
    width, height = (1000, 4) if axis == "x" else (4, 1000)
    sequence = _sequence(frames, width, height)
    decoded = decode(_camera(render_patterns(sequence)), sequence)
    truth = _truth(height, width)[0 if axis == "x" else 1]
    coordinate = decoded.projector_x if axis == "x" else decoded.projector_y
    assert decoded.valid.all(), np.bincount(decoded.rejection.ravel())
    assert np.abs(coordinate - truth).max() <= tolerance + 1e-6
    other = decoded.projector_y if axis == "x" else decoded.projector_x
    assert np.all(np.isnan(other))


def test_documented_1824_example_gives_stripe_centres_or_interpolates_between_boundaries():
    frames = REFERENCES + _gray("x", range(10, 0, -1))
    sequence = _sequence(frames, 1824, 2)
    captured = _camera(render_patterns(sequence))
    truth_x, _ = _truth(2, 1824)
    centres = decode(captured, sequence, gray_boundaries=False)
    assert centres.valid.all()
    np.testing.assert_array_equal(centres.projector_x, 2 * (truth_x // 2) + 0.5)
    decoded = decode(captured, sequence)
    assert decoded.valid.all()
    np.testing.assert_allclose(decoded.projector_x, truth_x, atol=1e-4)  # sharp edges halfway between pixels
    np.testing.assert_allclose(decoded.modulation, 105.0)  # every plane 105 grey levels from the mid level
    np.testing.assert_allclose(decoded.quality, 1.0)


def _rejection_scene():
    """The default sequence on a 320x40 identity camera with one defect per 40-column block."""
    sequence, patterns = generate_sequence(320, 40, period=16, steps=8)
    frames = _camera(patterns, noise=1.0).astype(np.int64)
    phase = [i for i, f in enumerate(sequence.frames) if f.kind == "phase"]
    frames[:, :, 40:80] = 3  # shadow: nothing but a dark ambient
    frames[phase, :, 80:120] = np.minimum(frames[phase, :, 80:120] * 2, 255)  # overexposed
    frames[:, :, 120:160] = 120 + (frames[:, :, 120:160] - 125) // 60  # glare: tiny modulation
    shifts = 2 * np.pi * np.arange(len(phase)) / len(phase)
    harmonics = 130 + 40 * np.cos(shifts) + 60 * np.cos(3 * shifts)  # mostly a third harmonic
    frames[phase, :, 160:200] = np.rint(harmonics)[:, None, None]  # not a sinusoid
    half_period_later = [phase[(k + 4) % 8] for k in range(8)]
    frames[phase, :, 200:240] = frames[half_period_later, :, 200:240]  # the part moved after the Gray code
    return sequence, frames.astype(np.uint8)


def test_rejection_codes_name_the_defect():
    sequence, frames = _rejection_scene()
    decoded = decode(frames, sequence)
    expected = {(0, 40): Rejection.VALID, (40, 80): Rejection.DARK, (80, 120): Rejection.SATURATED,
                (120, 160): Rejection.LOW_MODULATION, (160, 200): Rejection.POOR_FIT,
                (200, 240): Rejection.INCONSISTENT, (240, 320): Rejection.VALID}
    for (start, stop), code in expected.items():
        block = decoded.rejection[:, start:stop]
        # a half-period phase error is caught where the pixel is not at a Gray stripe edge: 3 in 4 pixels
        share = 0.7 if code == Rejection.INCONSISTENT else 0.9
        assert np.mean(block == code) > share, (code, np.bincount(block.ravel()))
    rejected = decoded.rejection != Rejection.VALID
    assert np.all(np.isnan(decoded.projector_x[rejected]))
    assert np.all(np.isfinite(decoded.projector_x[~rejected]))


def test_thresholds_are_parameters():
    sequence, frames = _rejection_scene()
    lenient = decode(frames, sequence, min_intensity=0, min_modulation=0, min_quality=0, consistency=1,
                     saturation_level=256)
    assert np.mean(lenient.rejection[:, 80:200] == Rejection.VALID) > 0.9


def _magnified_errors(sequence, noise, blur, magnification=2.7, seed=0):
    """Decode with a camera seeing each projector pixel as ``magnification`` blurred, noisy columns.

    Camera column c sees projector column c / m - 0.5, so camera pixels fall anywhere on the
    projector's stripes, not only on pixel centres. Columns within the blur of the border are left out.
    """
    columns = np.arange(int((sequence.projector.width - 1) * magnification))
    truth = columns / magnification - 0.5
    projector_column = np.clip(np.rint(truth).astype(int), 0, sequence.projector.width - 1)
    patterns = render_patterns(sequence)[:, :, projector_column]
    decoded = decode(_camera(patterns, noise=noise, blur=blur, seed=seed), sequence)
    inside = slice(int(4 * blur) + 1, -int(4 * blur) - 1)
    errors = np.abs(decoded.projector_x - truth)[:, inside]
    valid = decoded.valid[:, inside]
    return errors[valid], valid.mean()


def test_noise_and_blur_give_small_errors_and_no_gross_ones():
    sequence, _ = generate_sequence(400, 16)
    errors, valid_fraction = _magnified_errors(sequence, noise=1.5, blur=2.0)
    assert valid_fraction > 0.995
    assert np.median(errors) < 0.05
    assert np.quantile(errors, 0.999) < 0.3
    assert errors.max() < 1.0


def test_complementary_gray_code_removes_period_edge_errors():
    """Plain Gray unwrapping (stripes = period) jumps a period at blurred edges; complementary never."""
    plain = _sequence(REFERENCES + _gray("x", range(8, 3, -1), (False, True)) + _phase("x", 16, 8), 400, 16)
    complementary = _sequence(REFERENCES + _gray("x", range(8, 2, -1), (False, True)) + _phase("x", 16, 8), 400, 16)
    plain_errors, _ = _magnified_errors(plain, noise=1.5, blur=6.0)
    complementary_errors, _ = _magnified_errors(complementary, noise=1.5, blur=6.0)
    assert np.sum(plain_errors > 4) > 0
    assert np.sum(complementary_errors > 4) == 0


@pytest.mark.parametrize("bits", [12, 16])
def test_uint16_frames_decode_like_uint8(bits):
    sequence, patterns = generate_sequence(512, 8)
    full = 2**bits - 1
    frames = _camera(patterns, dark=0.08 * full, bright=0.9 * full, noise=1.5 * full / 255, dtype=np.uint16)
    decoded = decode(frames, sequence, saturation_level=full)
    truth_x, _ = _truth(8, 512)
    assert decoded.valid.all()
    assert np.abs(decoded.projector_x - truth_x).max() < 0.2
    np.testing.assert_allclose(np.median(decoded.modulation), 0.41 * full, rtol=0.02)


def test_default_thresholds_follow_the_bit_depth():
    sequence, patterns = generate_sequence(256, 4)
    eight_bit_levels_in_16_bits = _camera(patterns, dtype=np.uint16)
    assert np.all(decode(eight_bit_levels_in_16_bits, sequence).rejection == Rejection.DARK)
    assert decode(eight_bit_levels_in_16_bits, sequence, saturation_level=255).valid.all()


@pytest.mark.parametrize(
    ("frames", "message"),
    [
        (np.zeros((30, 4, 4), np.float64), "uint8, uint16 or float32"),
        (np.zeros((30, 4, 4), np.float32), "need an explicit saturation_level"),
        (np.zeros((30, 16), np.uint8), "(F, H, W) stack"),
        (np.zeros((29, 4, 4), np.uint8), "30 frames but 29"),
    ],
)
def test_bad_frames_are_refused(frames, message):
    sequence, _ = generate_sequence(1280, 800)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        decode(frames, sequence)


def test_pixels_beside_rejected_ones_or_a_jump_are_edges():
    sequence, patterns = generate_sequence(200, 12)
    frames = _camera(patterns)
    frames[:, :, 100:110] = 2  # a shadow
    decoded = decode(frames, sequence, edge_margin=1)
    assert np.all(decoded.rejection[:, [99, 110]] == Rejection.EDGE)
    assert np.all(decoded.rejection[:, [98, 111]] == Rejection.VALID)
    assert np.all(decode(frames, sequence).rejection[:, [97, 98, 99, 110, 111, 112]] == Rejection.EDGE)  # default 3
    assert np.all(np.isnan(decoded.projector_x[:, [99, 110]]))
    assert np.all(decode(frames, sequence, edge_margin=0).rejection[:, [99, 110]] == Rejection.VALID)

    stepped = np.concatenate([frames[:, :, :50], frames[:, :, 150:]], axis=2)  # a depth step at column 50
    jumps = decode(stepped, sequence, edge_margin=0, max_jump=10)
    assert np.all(jumps.rejection[:, [49, 50]] == Rejection.EDGE)
    assert np.all(jumps.rejection[:, [48, 51]] == Rejection.VALID)


def test_the_float32_phase_is_within_4e7_rad_of_float64():
    """decode takes the phase by numpy's float32 arctan2 (ten times faster than float64): 4e-7 rad is 1e-6 px
    at a 16-pixel period, below the float32 resolution of the coordinates themselves."""
    rng = np.random.default_rng(3)
    samples = np.concatenate([rng.normal(size=(2, 2000)), [[0, 1, -1, 0, 1e-30], [1, 0, 0, -1, -1e-30]]], axis=1)
    samples = samples.astype(np.float32)
    errors = np.abs(np.arctan2(samples[0], samples[1], dtype=np.float32) - np.arctan2(*samples.astype(np.float64)))
    assert errors.max() < 4e-7


def test_slstudio_sequence_is_described_exactly():
    """SLStudio's 3-step phase shift at period 114 with a one-period cue (1824): I = 1/2 (1 + cos(2 pi c / P -
    2 pi k / 3)), pixel centres at integers; the manifest in experiments/slstudio renders it and decodes it."""
    manifest = Path(__file__).resolve().parents[2] / "experiments" / "slstudio" / "calibration_sequence.json"
    sequence = parse_sequence(manifest.read_text())
    patterns = render_patterns(sequence)
    columns = np.arange(1824)
    expected = 0.5 * (1 + np.cos(2 * np.pi * columns / 114.0 - 2 * np.pi * 1 / 3))
    np.testing.assert_allclose(patterns[1, 0].astype(float) / 255, expected, atol=0.5 / 255 + 1e-9)
    rows = np.arange(1140)
    expected = 0.5 * (1 + np.cos(2 * np.pi * rows / 1140.0 - 2 * np.pi * 2 / 3))
    np.testing.assert_allclose(patterns[11, :, 0].astype(float) / 255, expected, atol=0.5 / 255 + 1e-9)
    decoded = decode(_camera(patterns[:, ::57, ::57]), sequence, edge_margin=0)
    truth_x, truth_y = np.meshgrid(np.arange(0, 1824, 57), np.arange(0, 1140, 57))
    assert decoded.valid.all()
    # 8-bit rounding of 3 steps at period 71.25 gives up to 0.06 px
    assert np.abs(decoded.projector_x - truth_x).max() < 0.1 and np.abs(decoded.projector_y - truth_y).max() < 0.1


def test_indirect_light_is_rejected_by_its_fringe_visibility():
    """Light arriving after a bounce is unmodulated at a fine period: where it exceeds max_indirect times the
    direct light, the pixel is INDIRECT; ambient-free direct light is kept, and the test is off by default."""
    sequence, patterns = generate_sequence(256, 40, period=16, steps=4)
    direct = 0.5 * patterns.astype(np.float64)  # 127.5 grey levels under the white frame
    indirect = np.zeros(direct.shape[1:])
    indirect[:6] = 0.5 * 127.5  # G / D = 0.5
    indirect[6:12] = 0.2 * 127.5  # G / D = 0.2
    frames = np.clip(np.rint(direct + indirect + 10), 0, 255).astype(np.uint8)
    frames[sequence.black_index] = 10  # the projector is off: no direct nor indirect light
    assert decode(frames, sequence, edge_margin=0).valid.all()
    decoded = decode(frames, sequence, edge_margin=0, max_indirect=0.33)
    assert np.all(decoded.rejection[:6] == Rejection.INDIRECT)
    assert np.all(decoded.rejection[6:] == Rejection.VALID)
    assert np.isnan(decoded.projector_x[:6]).all()
    with pytest.raises(ValueError, match="max_indirect"):
        decode(frames, sequence, max_indirect=0)

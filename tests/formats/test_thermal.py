import json

import cv2
import numpy as np
import pytest
import tifffile

from services.errors import InputError
from services.formats.thermal import RadiometricOverrides, read_thermal_frame, sidecar_path, write_thermal_frame
from services.fusion.radiometry import PlanckConstants, blackbody_counts, counts_to_temperature


@pytest.fixture
def temperature():
    rng = np.random.default_rng(0)
    return (20.0 + 1000.0 * rng.random((24, 32))).astype(np.float32)


@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".npy"])
def test_float_frames_are_degrees_celsius(tmp_path, temperature, suffix):
    path = tmp_path / f"frame{suffix}"
    write_thermal_frame(path, temperature)
    read = read_thermal_frame(path, size=(32, 24))
    assert read.dtype == np.float32
    np.testing.assert_array_equal(read, temperature)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16_bit_frames_are_centikelvin_with_no_data_codes(tmp_path, suffix):
    centikelvin = np.full((4, 5), 29315, dtype=np.uint16)  # 20.00 C
    centikelvin[0, 0] = 0
    centikelvin[0, 1] = 65535
    centikelvin[1, 1] = 37315  # 100.00 C
    path = tmp_path / f"frame{suffix}"
    if suffix == ".png":
        cv2.imwrite(str(path), centikelvin)
    else:
        tifffile.imwrite(path, centikelvin)
    read = read_thermal_frame(path)
    assert np.isnan(read[0, 0]) and np.isnan(read[0, 1])
    assert read[1, 1] == pytest.approx(100.0, abs=1e-4)
    assert read[2, 2] == pytest.approx(20.0, abs=1e-4)


def test_png_written_in_centikelvin_round_trips_to_a_hundredth_of_a_kelvin(tmp_path):
    temperature = np.linspace(-50, 380, 20, dtype=np.float32).reshape(4, 5)
    write_thermal_frame(tmp_path / "f.png", temperature)
    np.testing.assert_allclose(read_thermal_frame(tmp_path / "f.png"), temperature, atol=0.0051)


def test_raw_counts_with_planck_sidecar(tmp_path, temperature):
    constants = PlanckConstants(R1=15000.0, R2=0.02, B=1450.0, F=1.0, O=-5000.0)
    emissivity, reflected = 0.85, 30.0
    signal = emissivity * blackbody_counts(temperature, constants) + (1 - emissivity) * blackbody_counts(
        np.float64(reflected), constants)
    path = tmp_path / "raw.tif"
    tifffile.imwrite(path, signal.astype(np.float32))
    sidecar_path(path).write_text(json.dumps({
        "unit": "counts", "planck": {"R1": 15000.0, "R2": 0.02, "B": 1450.0, "F": 1.0, "O": -5000.0},
        "emissivity": emissivity, "reflected_temperature": reflected}))
    np.testing.assert_allclose(read_thermal_frame(path), temperature, atol=0.05)
    # the caller's emissivity overrides the sidecar's
    other = read_thermal_frame(path, overrides=RadiometricOverrides(emissivity=0.95))
    np.testing.assert_allclose(other, counts_to_temperature(signal, constants, 0.95, reflected), atol=1e-3)


def test_integer_counts_in_a_16_bit_png(tmp_path):
    constants = PlanckConstants(R1=15000.0, R2=0.5, B=1450.0, F=1.0, O=-500.0)
    true = np.full((8, 8), 300.0)
    counts = np.round(blackbody_counts(true, constants)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "raw.png"), counts)
    (tmp_path / "raw.json").write_text(json.dumps({"unit": "counts", "planck": {
        "R1": 15000.0, "R2": 0.5, "B": 1450.0, "F": 1.0, "O": -500.0}}))
    np.testing.assert_allclose(read_thermal_frame(tmp_path / "raw.png"), true, atol=0.1)


def test_kelvin_unit_from_sidecar(tmp_path):
    np.save(tmp_path / "k.npy", np.full((3, 3), 373.15))
    (tmp_path / "k.json").write_text('{"unit": "kelvin"}')
    np.testing.assert_allclose(read_thermal_frame(tmp_path / "k.npy"), 100.0, atol=1e-4)


def test_emissivity_corrects_apparent_temperatures_upward(tmp_path, temperature):
    write_thermal_frame(tmp_path / "f.tif", temperature)
    corrected = read_thermal_frame(tmp_path / "f.tif", overrides=RadiometricOverrides(emissivity=0.7))
    hot = temperature > 100
    assert np.all(corrected[hot] > temperature[hot])


def test_nan_pixels_stay_nan(tmp_path, temperature):
    temperature[0, :5] = np.nan
    write_thermal_frame(tmp_path / "f.npy", temperature)
    read = read_thermal_frame(tmp_path / "f.npy")
    assert np.isnan(read[0, :5]).all() and np.isfinite(read[1:]).all()


def _bad_frames(tmp_path):
    np.save(tmp_path / "nan.npy", np.full((24, 32), np.nan, dtype=np.float32))
    np.save(tmp_path / "cube.npy", np.zeros((2, 24, 32), dtype=np.float32))
    cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((24, 32), np.uint8))
    cv2.imwrite(str(tmp_path / "nodata.png"), np.zeros((24, 32), np.uint16))
    (tmp_path / "corrupt.tif").write_bytes(b"II*\x00 this is not a TIFF")
    (tmp_path / "frame.jpg").write_bytes(b"")
    (tmp_path / "frame.gif").write_bytes(b"GIF89a")
    np.save(tmp_path / "counts.npy", np.ones((24, 32), dtype=np.float32))
    (tmp_path / "counts.json").write_text('{"unit": "counts"}')
    np.save(tmp_path / "typo.npy", np.ones((24, 32), dtype=np.float32))
    (tmp_path / "typo.json").write_text('{"unit": "celsius", "emisivity": 0.9}')
    np.save(tmp_path / "cold.npy", np.ones((24, 32), dtype=np.float32))
    (tmp_path / "cold.json").write_text(
        '{"unit": "counts", "planck": {"R1": 15000, "R2": 0.02, "B": 1450, "F": 1, "O": -100}}')


@pytest.mark.parametrize(("name", "message"), [
    ("missing.tif", "thermal frame file is missing"),
    ("nan.npy", "no finite value"),
    ("cube.npy", "must be a 2-D grey image"),
    ("eight.png", "uint8 thermal frame is not radiometric"),
    ("nodata.png", "no finite value"),
    ("corrupt.tif", "cannot read the thermal frame"),
    ("frame.gif", "thermal frames must be .npy, .tif, .tiff, .png, .jpg, .jpeg files"),
    ("frame.jpg", "not a FLIR radiometric JPEG (not a JPEG file)"),
    ("counts.npy", "counts.json: invalid thermal sidecar: raw counts need the camera's 'planck' constants"),
    ("typo.npy", "typo.json: invalid thermal sidecar: emisivity: Extra inputs are not permitted"),
    ("cold.npy", "no pixel of the thermal frame gives a temperature"),
])
def test_bad_frames_are_refused_naming_the_file(tmp_path, name, message):
    _bad_frames(tmp_path)
    with pytest.raises(InputError) as error:
        read_thermal_frame(tmp_path / name)
    assert message in str(error.value)
    assert str(tmp_path) in str(error.value)


def test_wrong_size_for_the_device_is_refused(tmp_path, temperature):
    write_thermal_frame(tmp_path / "f.tif", temperature)
    with pytest.raises(InputError, match=r"f.tif: thermal frame is 32x24 but the thermal camera is 320x256"):
        read_thermal_frame(tmp_path / "f.tif", size=(320, 256))


def test_bad_emissivity_is_refused():
    with pytest.raises(InputError, match=r"emissivity must be in \(0, 1\]"):
        RadiometricOverrides(emissivity=0.0)


def test_writing_is_atomic_and_leaves_no_temporary(tmp_path, temperature):
    for name in ("a.tif", "b.npy", "c.png"):
        write_thermal_frame(tmp_path / name, temperature)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tif", "b.npy", "c.png"]
    with pytest.raises(ValueError, match="written as"):
        write_thermal_frame(tmp_path / "d.jpg", temperature)


def test_16_bit_linear_frames_reach_forging_temperatures(tmp_path):
    # 0.1 K per count from 0 K: 1473.15 K (1200 C) is count 14731.5, beyond centikelvin's 382 C
    values = np.array([[14732, 12732], [0, 65535]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "hot.png"), values)
    (tmp_path / "hot.json").write_text(json.dumps({"unit": "linear", "scale": 0.1, "offset": 0.0}))
    temperature = read_thermal_frame(tmp_path / "hot.png")
    np.testing.assert_allclose(temperature[0], [1200.05, 1000.05], atol=1e-3)
    assert np.isnan(temperature[1]).all()  # no data and saturated


def test_linear_unit_needs_its_scale(tmp_path):
    cv2.imwrite(str(tmp_path / "hot.png"), np.full((2, 2), 100, np.uint16))
    (tmp_path / "hot.json").write_text(json.dumps({"unit": "linear"}))
    with pytest.raises(InputError, match="hot.json.*'scale'"):
        read_thermal_frame(tmp_path / "hot.png")


def test_16_bit_tiff_counts_on_a_stated_scale_and_offset(tmp_path):
    # 0.04 K per count from 200 K: count 30000 is 1400 K (1126.85 C)
    tifffile.imwrite(tmp_path / "hot.tif", np.array([[30000, 1000]], dtype=np.uint16))
    (tmp_path / "hot.json").write_text(json.dumps({"unit": "linear", "scale": 0.04, "offset": 200.0}))
    np.testing.assert_allclose(read_thermal_frame(tmp_path / "hot.tif")[0], [1126.85, -33.15], atol=1e-3)


def test_distance_and_air_overrides_correct_apparent_frames_by_the_model(tmp_path, temperature):
    """An apparent frame's temperatures go back to counts on the typical curve and through FLIR's model."""
    write_thermal_frame(tmp_path / "f.tif", temperature)
    overrides = RadiometricOverrides(emissivity=0.85, reflected_c=30.0, atmosphere_c=15.0, relative_humidity=0.8,
                                     distance_m=40.0)
    read = read_thermal_frame(tmp_path / "f.tif", overrides=overrides)
    constants = PlanckConstants()
    expected = counts_to_temperature(blackbody_counts(temperature, constants), constants, 0.85, 30.0,
                                     atmosphere_c=15.0, relative_humidity=0.8, distance_m=40.0)
    np.testing.assert_allclose(read, expected, rtol=1e-5)
    nearer = read_thermal_frame(tmp_path / "f.tif", overrides=RadiometricOverrides(emissivity=0.85, reflected_c=30.0))
    hot = temperature > 100
    assert np.all(read[hot] > nearer[hot])  # the air's loss over 40 m makes the part hotter than it looks

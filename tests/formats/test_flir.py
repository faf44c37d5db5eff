"""FLIR radiometric JPEGs: the six real files of ../shared/data/flir-rjpeg against FLIR's model computed here,
independently of services/formats/flir.py and services/fusion/radiometry.py, from ExifTool's tags and raw image.

ExifTool (Debian's libimage-exiftool-perl, ``make exiftool``) reads the files; the model below is FLIR's
measurement equation as published with Thermimage's ``raw2temp`` (docs/thermal-formats.md).
"""

import io
import json
import math
import shutil
import struct
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from services.errors import InputError
from services.formats import flir
from services.formats.thermal import RadiometricOverrides, decode_thermal_frame, read_thermal_frame

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data" / "flir-rjpeg"  # shared/ beside the clone
FILES = sorted(DATA.glob("*.jpg"))
ONE = DATA / "10-ir_fussbodenheizung.jpg"
STEEL = 0.85  # oxidised steel at about 1000 C


def test_the_six_real_files_are_there():
    assert len(FILES) == 6, f"the real FLIR files are missing from {DATA}"


# --- FLIR's model from ExifTool's tags, written here on its own ---------------------------------------------

def exiftool_tags(path: Path) -> dict:
    assert shutil.which("exiftool"), "exiftool is missing: make exiftool (Debian libimage-exiftool-perl)"
    out = subprocess.run(["exiftool", "-j", "-n", str(path)], capture_output=True, check=True, text=True).stdout
    return {key: value for key, value in json.loads(out)[0].items()}


def exiftool_raw(path: Path) -> np.ndarray:
    """The raw thermal image; FLIR stores PNG-coded counts little-endian, against PNG's byte order."""
    data = subprocess.run(["exiftool", "-b", "-RawThermalImage", str(path)], capture_output=True, check=True).stdout
    if data[:4] == b"\x89PNG":
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).byteswap()
    return tifffile.imread(io.BytesIO(data))


class Model:
    """FLIR's model with ExifTool's tag values (degrees C, humidity as a fraction)."""

    def __init__(self, tags: dict, **changes: float):
        number = {key: float(value) for key, value in tags.items()
                  if isinstance(value, (int, float)) or _is_number(value)}
        self.R1, self.R2, self.B = number["PlanckR1"], number["PlanckR2"], number["PlanckB"]
        self.F, self.O = number["PlanckF"], number["PlanckO"]
        self.E = changes.get("E", number["Emissivity"])
        self.OD = changes.get("OD", number["ObjectDistance"])
        self.RTemp = changes.get("RTemp", number["ReflectedApparentTemperature"])
        self.ATemp = changes.get("ATemp", number["AtmosphericTemperature"])
        self.IRWTemp, self.IRT = number["IRWindowTemperature"], number["IRWindowTransmission"]
        self.RH = changes.get("RH", number["RelativeHumidity"])
        a1, a2 = number["AtmosphericTransAlpha1"], number["AtmosphericTransAlpha2"]
        b1, b2, x = number["AtmosphericTransBeta1"], number["AtmosphericTransBeta2"], number["AtmosphericTransX"]
        h2o = self.RH * math.exp(1.5587 + 0.06939 * self.ATemp - 0.00027816 * self.ATemp ** 2
                                 + 0.00000068455 * self.ATemp ** 3)
        half = math.sqrt(self.OD / 2)
        self.tau1 = (x * math.exp(-half * (a1 + b1 * math.sqrt(h2o)))
                     + (1 - x) * math.exp(-half * (a2 + b2 * math.sqrt(h2o))))
        self.tau2 = self.tau1

    def planck(self, celsius):
        return self.R1 / (self.R2 * (np.exp(self.B / (np.asarray(celsius, float) + 273.15)) - self.F)) - self.O

    def counts(self, object_c):
        """What the camera reads from an object at ``object_c`` (the forward model)."""
        E, t1, t2, w = self.E, self.tau1, self.tau2, self.IRT
        return (E * t1 * w * t2 * self.planck(object_c) + (1 - E) * t1 * w * t2 * self.planck(self.RTemp)
                + (1 - t1) * w * t2 * self.planck(self.ATemp) + (1 - w) * t2 * self.planck(self.IRWTemp)
                + (1 - t2) * self.planck(self.ATemp))

    def temperature(self, raw):
        """The object temperature in degrees C (Thermimage's raw2temp), NaN below the background."""
        E, t1, t2, w = self.E, self.tau1, self.tau2, self.IRT
        raw_obj = (np.asarray(raw, float) / E / t1 / w / t2 - (1 - E) / E * self.planck(self.RTemp)
                   - (1 - t1) / E / t1 * self.planck(self.ATemp) - (1 - w) / E / t1 / w * self.planck(self.IRWTemp)
                   - (1 - t2) / E / t1 / w / t2 * self.planck(self.ATemp))
        with np.errstate(invalid="ignore", divide="ignore"):
            kelvin = self.B / np.log(self.R1 / (self.R2 * (raw_obj + self.O)) + self.F)
        return np.where(raw_obj + self.O > 0, kelvin - 273.15, np.nan)


def _is_number(value) -> bool:
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


@pytest.fixture(scope="module", params=FILES, ids=lambda path: path.name[:2])
def real(request):
    path = request.param
    return path, exiftool_tags(path), exiftool_raw(path)


@pytest.mark.integration  # starts exiftool
def test_reader_counts_and_constants_match_exiftool(real):
    path, tags, raw = real
    image = flir.read_flir_jpeg(path.read_bytes(), str(path))
    np.testing.assert_array_equal(image.counts, raw)
    assert image.counts.shape == (tags["RawThermalImageHeight"], tags["RawThermalImageWidth"])
    assert image.planck.R1 == pytest.approx(float(tags["PlanckR1"]), rel=1e-6)
    assert image.planck.B == pytest.approx(float(tags["PlanckB"]), rel=1e-6)
    assert image.conditions.emissivity == pytest.approx(float(tags["Emissivity"]), rel=1e-6)
    assert image.conditions.relative_humidity == pytest.approx(float(tags["RelativeHumidity"]), rel=1e-6)
    assert tags["Model"].replace("_", " ").lower() in image.camera.replace("_", " ").lower()


@pytest.mark.integration
def test_file_parameters_agree_with_flirs_model_within_a_tenth_of_a_degree(real):
    path, tags, raw = real
    expected = Model(tags).temperature(raw)
    read = read_thermal_frame(path)
    assert read.dtype == np.float32 and read.shape == raw.shape
    np.testing.assert_array_equal(np.isnan(read), np.isnan(expected))
    assert np.nanmax(np.abs(read - expected)) <= 0.1


@pytest.mark.integration
def test_emissivity_changes_the_temperature_as_the_inverted_model_says(real):
    path, tags, raw = real
    model = Model(tags, E=STEEL)
    steel = read_thermal_frame(path, overrides=RadiometricOverrides(emissivity=STEEL)).astype(np.float64)
    finite = np.isfinite(steel)
    assert finite.mean() > 0.9
    # Pushing the temperatures back through the forward model at the new emissivity gives the camera's counts:
    # a tenth of a degree's worth of counts at most.
    counts_per_degree = np.abs(model.counts(steel[finite] + 0.05) - model.counts(steel[finite] - 0.05)) / 0.1
    assert np.all(np.abs(model.counts(steel[finite]) - raw[finite]) <= 0.1 * counts_per_degree)
    # No temperature where the counts are below what the background alone gives at this emissivity.
    with np.errstate(over="ignore"):  # a black body at 0 K gives P = -O: exp(B / T) overflows to inf
        background = model.counts(-273.15 + 1e-3)
    assert np.all(raw[~finite] <= background)
    # Against the file's emissivity: hotter where the scene is warmer than its reflected surroundings.
    as_filed = read_thermal_frame(path).astype(np.float64)
    warmer = finite & (as_filed > float(tags["ReflectedApparentTemperature"]) + 1.0)
    assert np.all(steel[warmer] > as_filed[warmer])


@pytest.mark.integration
def test_every_condition_override_follows_the_model(real):
    path, tags, raw = real
    overrides = RadiometricOverrides(emissivity=0.8, reflected_c=35.0, atmosphere_c=5.0, relative_humidity=0.9,
                                     distance_m=25.0)
    expected = Model(tags, E=0.8, RTemp=35.0, ATemp=5.0, RH=0.9, OD=25.0).temperature(raw)
    read = read_thermal_frame(path, overrides=overrides)
    np.testing.assert_array_equal(np.isnan(read), np.isnan(expected))
    assert np.nanmax(np.abs(read - expected)) <= 0.1
    assert np.nanmax(np.abs(read - read_thermal_frame(path))) > 1.0  # the overrides did change something


# --- what is wrong with a bad file, in one line ---------------------------------------------------------------

def _camera_info_at(content: bytes) -> tuple[int, int]:
    """File offsets of the camera information record and the raw image's header (each within one APP1 chunk)."""
    from flyr.records import RecordIndex, extract_flir_app1, parse_flir_records

    stream = extract_flir_app1(io.BytesIO(content))
    records = parse_flir_records(stream)
    data = stream.getvalue()
    places = []
    for index in (RecordIndex.CAMERA_INFO, RecordIndex.RAW_DATA):
        offset = records[index.value][2]
        place = content.find(data[offset:offset + 128])
        assert place > 0 and content.find(data[offset:offset + 128], place + 1) < 0
        places.append(place)
    return places[0], places[1]


def _patched(content: bytes, position: int, value: bytes) -> bytes:
    return content[:position] + value + content[position + len(value):]


def _refusal(content: bytes, name: str = "bad.jpg") -> str:
    with pytest.raises(InputError) as error:
        decode_thermal_frame(content, suffix=".jpg", source=name)
    message = str(error.value)
    assert message.startswith(f"{name}: ") and "\n" not in message and "Traceback" not in message
    return message


def test_a_plain_jpeg_is_not_radiometric():
    plain = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))[1].tobytes()
    assert "not a FLIR radiometric JPEG (no FLIR radiometric data; a plain JPEG?)" in _refusal(plain)


def test_a_file_that_is_not_a_jpeg_at_all():
    assert "not a FLIR radiometric JPEG (not a JPEG file)" in _refusal(b"GIF89a" + bytes(100))
    assert "not a JPEG file" in _refusal(b"")


@pytest.mark.parametrize("fraction", [0.02, 0.3, 0.6, 0.95, 0.9999])
def test_a_truncated_file_is_refused(fraction):
    content = ONE.read_bytes()
    assert "truncated" in _refusal(content[:int(len(content) * fraction)])


@pytest.mark.parametrize("value, what", [(0.0, "emissivity 0 is not in (0, 1]"),
                                         (1.5, "emissivity 1.5 is not in (0, 1]"),
                                         (float("nan"), "emissivity nan is not in (0, 1]")])
def test_nonsense_emissivity_in_the_file(value, what):
    content = ONE.read_bytes()
    camera, _ = _camera_info_at(content)
    message = _refusal(_patched(content, camera + 32, struct.pack("<f", value)))
    assert f"inconsistent parameters: {what}" in message


@pytest.mark.parametrize("offset, name", [(88, "R1"), (96, "F"), (780, "R2")])
def test_missing_planck_constants(offset, name):
    content = ONE.read_bytes()
    camera, _ = _camera_info_at(content)
    message = _refusal(_patched(content, camera + offset, struct.pack("<f", float("nan"))))
    assert "without usable camera constants (Planck constants must be finite" in message


def test_nonsense_humidity_and_distance_in_the_file():
    content = ONE.read_bytes()
    camera, _ = _camera_info_at(content)
    assert "relative humidity 7 is not a fraction" in _refusal(_patched(content, camera + 60, struct.pack("<f", 7.0)))
    assert "object distance -3 m" in _refusal(_patched(content, camera + 36, struct.pack("<f", -3.0)))


def test_an_absurd_declared_size_is_refused_before_decoding(monkeypatch):
    content = ONE.read_bytes()
    _, raw = _camera_info_at(content)
    decoded = []
    monkeypatch.setattr("flyr.thermal.parse_raw_data", lambda *args: decoded.append(args))
    message = _refusal(_patched(content, raw + 2, struct.pack("<HH", 60000, 60000)))
    assert "FLIR raw thermal image: declares 3,600,000,000 pixels, more than the limit" in message
    assert not decoded
    assert "declares a 0x240 size" in _refusal(_patched(content, raw + 2, struct.pack("<H", 0)))


def test_a_size_that_does_not_match_the_raw_image():
    content = ONE.read_bytes()
    _, raw = _camera_info_at(content)
    assert "corrupt raw thermal image" in _refusal(_patched(content, raw + 2, struct.pack("<HH", 640, 480)))


def test_the_declared_size_check_is_one_function():
    flir.check_declared_size(1280, 1024, "x")
    with pytest.raises(InputError, match="^x: FLIR raw thermal image: declares 4,195,328 pixels, more than the limit"):
        flir.check_declared_size(4097, 1024, "x")


def test_r_jpeg_bytes_read_as_the_file(tmp_path):
    upload = decode_thermal_frame(ONE.read_bytes(), suffix=".JPG", source="upload 0", size=(320, 240))
    np.testing.assert_array_equal(upload, read_thermal_frame(ONE))
    with pytest.raises(InputError, match="^upload 0: thermal frame is 320x240 but the thermal camera is 640x480$"):
        decode_thermal_frame(ONE.read_bytes(), suffix=".jpg", source="upload 0", size=(640, 480))


@pytest.mark.parametrize("field, value, message", [
    ("emissivity", 0.0, "emissivity must be in (0, 1]; got 0.0"),
    ("relative_humidity", 50.0, "relative humidity must be a fraction in [0, 1] (0.5 is 50 %); got 50.0"),
    ("distance_m", -1.0, "object distance must be in 0..100000 m; got -1.0"),
    ("reflected_c", -300.0, "reflected temperature must be a temperature in degrees C (above -273.15); got -300.0"),
    ("atmosphere_c", float("inf"), "atmospheric temperature must be"),
])
def test_nonsense_overrides(field, value, message):
    with pytest.raises(InputError, match="^" + message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]").replace(".", r"\.").replace("+", r"\+")):
        RadiometricOverrides(**{field: value})

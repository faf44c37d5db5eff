"""``thermofield thermal convert`` and R-JPEGs wherever a thermal frame goes (``fuse``), on the six real FLIR
files of ../shared/data/flir-rjpeg; bad files end with exit code 2 and one line naming the file."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tifffile

from services.formats.ply import read_cloud, write_cloud
from services.formats.rig import Rig, save_rig
from services.formats.thermal import RadiometricOverrides, read_thermal_frame
from services.simulation.presets import forging_rig

pytestmark = pytest.mark.integration

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "flir-rjpeg"  # shared/ beside the clone
FILES = sorted(DATA.glob("*.jpg"))
E60 = DATA / "10-ir_fussbodenheizung.jpg"
BAD_INPUT = 2


def _thermofield(*args):
    return subprocess.run([sys.executable, "-m", "services.cli.main", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def _one_error_line(result, *expected: str) -> str:
    assert result.returncode == BAD_INPUT, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("thermofield: error: ") and "internal error" not in lines[0], lines[0]
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


def test_every_real_file_converts_to_float32_degrees(tmp_path):
    assert len(FILES) == 6, f"the real FLIR files are missing from {DATA}"
    for path in FILES:
        out = tmp_path / f"{path.stem}.tiff"
        result = _thermofield("thermal", "convert", path, out)
        assert result.returncode == 0, result.stderr
        converted = tifffile.imread(out)
        assert converted.dtype == np.float32
        np.testing.assert_array_equal(converted, read_thermal_frame(path))
        height, width = converted.shape
        assert result.stdout.startswith(f"{out}: {width}x{height} degrees C, min ")


def test_overrides_reach_the_model(tmp_path):
    out = tmp_path / "steel.tif"
    result = _thermofield("thermal", "convert", E60, out, "--emissivity", "0.85", "--reflected-c", "30",
                          "--atmosphere-c", "10", "--humidity", "0.8", "--distance-m", "12")
    assert result.returncode == 0, result.stderr
    expected = read_thermal_frame(E60, overrides=RadiometricOverrides(
        emissivity=0.85, reflected_c=30.0, atmosphere_c=10.0, relative_humidity=0.8, distance_m=12.0))
    np.testing.assert_array_equal(tifffile.imread(out), expected)
    assert np.nanmax(np.abs(expected - read_thermal_frame(E60))) > 1.0


@pytest.mark.parametrize("content, expected", [
    (b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00\xff\xd9",
     "not a FLIR radiometric JPEG (no FLIR radiometric data; a plain JPEG?)"),
    (None, "FLIR radiometric JPEG is truncated"),
    (b"not an image at all", "not a FLIR radiometric JPEG (not a JPEG file)"),
])
def test_a_file_that_is_not_a_good_r_jpeg_is_one_line(tmp_path, content, expected):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(E60.read_bytes()[:50000] if content is None else content)
    out = tmp_path / "out.tiff"
    _one_error_line(_thermofield("thermal", "convert", bad, out), f"{bad}: ", expected)
    assert not out.exists()


@pytest.mark.parametrize("options, expected", [
    (["--emissivity", "0"], "--emissivity must be in (0, 1]; got 0.0"),
    (["--humidity", "50"], "--humidity must be a fraction in [0, 1] (0.5 is 50 %); got 50.0"),
    (["--distance-m", "-2"], "--distance-m must be in 0..100000 m; got -2.0"),
    (["--reflected-c", "-400"], "--reflected-c must be a temperature in degrees C"),
])
def test_nonsense_conditions_are_one_line(tmp_path, options, expected):
    _one_error_line(_thermofield("thermal", "convert", E60, tmp_path / "out.tiff", *options), expected)


def test_the_output_is_a_tiff(tmp_path):
    _one_error_line(_thermofield("thermal", "convert", E60, tmp_path / "out.png"),
                    "out.png: the output is a float32 TIFF")


def _rig_and_cloud(tmp_path) -> tuple[Path, Path]:
    """The forging rig with an E60-sized (320x240) thermal camera, and a wall 600 mm in front of it."""
    rig = forging_rig()
    thermal = replace(rig.devices["thermal"], height=240)
    rig_path = tmp_path / "rig.json"
    save_rig(Rig(devices={**rig.devices, "thermal": thermal}), rig_path)
    u, v = np.meshgrid(np.arange(10, 310, 3.0), np.arange(10, 230, 3.0))
    rays = np.linalg.solve(thermal.K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    points = (thermal.R.T @ (600.0 * rays - thermal.t.reshape(3, 1))).T
    cloud_path = tmp_path / "wall.ply"
    write_cloud(cloud_path, {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]})
    return rig_path, cloud_path


def test_fuse_takes_an_r_jpeg_as_its_converted_tiff(tmp_path):
    rig, cloud = _rig_and_cloud(tmp_path)
    converted = tmp_path / "e60.tiff"
    assert _thermofield("thermal", "convert", E60, converted, "--emissivity", "0.85").returncode == 0
    fields = {}
    for name, frame in (("jpeg", E60), ("tiff", converted)):
        out = tmp_path / f"{name}.ply"
        options = ["--emissivity", "0.85"] if name == "jpeg" else []
        result = _thermofield("fuse", "--rig", rig, "--cloud", cloud, "--thermal", frame, *options, "--out", out)
        assert result.returncode == 0, result.stderr
        fields[name] = read_cloud(out)["temperature"]
    seen = np.isfinite(fields["jpeg"])
    assert seen.mean() > 0.9
    np.testing.assert_array_equal(fields["jpeg"], fields["tiff"])
    frame = tifffile.imread(converted)
    fused = fields["jpeg"][seen]
    assert np.nanmin(frame) - 1e-3 <= fused.min() and fused.max() <= np.nanmax(frame) + 1e-3


def test_fuse_names_a_bad_r_jpeg(tmp_path):
    rig, cloud = _rig_and_cloud(tmp_path)
    bad = tmp_path / "plain.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00\xff\xd9")
    _one_error_line(_thermofield("fuse", "--rig", rig, "--cloud", cloud, "--thermal", bad, "--out",
                                 tmp_path / "f.ply"), f"{bad}: not a FLIR radiometric JPEG")

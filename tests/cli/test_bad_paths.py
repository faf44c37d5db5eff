"""The command line as a new user meets it: output into a missing directory, onto a read-only or a full
disk, a corrupt frame -- each ends in one line naming the path, with nothing half-written left behind
and nothing from third-party libraries on the terminal."""

import shutil
import subprocess
import sys

import pytest


def _thermofield(*args, env=None):
    return subprocess.run([sys.executable, "-m", "services.cli.main", *map(str, args)], capture_output=True,
                          text=True, timeout=300, env=env)


def _one_error_line(result, *expected: str) -> str:
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("thermofield: error: ") and "internal error" not in lines[0], lines[0]
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    assert _thermofield("patterns", "--projector", "1024x768", "--out", root / "patterns").returncode == 0
    result = _thermofield("simulate", "--scene", "paper-plane:500", "--rig", "paper", "--patterns",
                          root / "patterns", "--out", root / "capture", "--supersample", "1")
    assert result.returncode == 0, result.stderr
    return root / "capture"


def _reconstruct(capture, out, captures=None):
    return _thermofield("reconstruct", "--rig", capture / "rig.json", "--captures", captures or capture,
                        "--out", out)


def test_output_into_a_missing_directory_names_it(capture, tmp_path):
    result = _reconstruct(capture, tmp_path / "no-such-dir" / "cloud.ply")
    assert result.returncode == 2
    _one_error_line(result, str(tmp_path / "no-such-dir" / "cloud.ply"), "does not exist")


def test_output_onto_a_read_only_disk_names_the_file(capture, small_disk):
    disk = small_disk(1 << 20, "ro")
    result = _reconstruct(capture, disk / "cloud.ply")
    assert result.returncode == 2
    _one_error_line(result, str(disk / "cloud.ply"), "cannot write")


def test_output_onto_a_full_disk_leaves_nothing_half_written(capture, small_disk):
    disk = small_disk(64 << 10)  # the cloud is megabytes
    result = _reconstruct(capture, disk / "cloud.ply")
    assert result.returncode == 2
    _one_error_line(result, str(disk / "cloud.ply"), "no space left")
    assert list(disk.iterdir()) == []


def test_patterns_onto_a_full_disk(small_disk):
    disk = small_disk(64 << 10)
    result = _thermofield("patterns", "--projector", "1024x768", "--out", disk / "patterns")
    assert result.returncode == 2
    _one_error_line(result, str(disk / "patterns"), "no space left")
    assert not [path for path in (disk / "patterns").iterdir() if ".part" in path.name]


def test_a_corrupt_frame_gets_one_line_and_no_library_noise(capture, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(capture, broken)
    frame = broken / "00_white.png"
    data = bytearray(frame.read_bytes())
    for position in range(100, len(data), 50):  # a PNG whose header is right and whose data is not
        data[position] ^= 0xFF
    frame.write_bytes(bytes(data))
    result = _reconstruct(capture, tmp_path / "cloud.ply", captures=broken)
    assert result.returncode == 2
    _one_error_line(result, str(frame), "cannot read the frame")
    assert "libpng" not in result.stderr and "[ERROR" not in result.stderr

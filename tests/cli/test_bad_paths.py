"""The command line as a new user meets it: every command that reads or writes files, given a missing
input, an output into a missing directory, onto a read-only or a full disk, or a corrupt input -- each
ends with exit code 2 and one line naming the path, with nothing half-written left behind and nothing
from third-party libraries on the terminal."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from services.formats.part import load_part
from services.formats.ply import write_cloud
from services.formats.rig import save_rig
from services.formats.thermal import write_thermal_frame
from services.simulation.hot_part import HotPart, billet_pose, cylinder_mesh, simulated_field, write_billet_part
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature

pytestmark = pytest.mark.integration

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"  # shared/ beside the clone
BAD_INPUT = 2  # the exit code of usage errors and bad input, bad paths included (README, "The command line")


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


def _flip_bytes(path: Path) -> None:
    """Corrupt a file past its first 100 bytes (a PNG's header stays right, its data does not)."""
    data = bytearray(path.read_bytes())
    for position in range(100, len(data), 50):
        data[position] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Good inputs of every command: a small forging rig, its patterns, a simulated capture, a cloud, a
    thermal frame, a billet's temperature field and part file, board images, an infrared/visible pair and
    SLStudio's calibration."""
    root = tmp_path_factory.mktemp("inputs")
    rig = forging_rig(0.2)  # 256x160 camera and projector: each command runs in about a second
    save_rig(rig, root / "rig.json")
    assert _thermofield("patterns", "--projector", "256x160", "--out", root / "patterns").returncode == 0
    result = _thermofield("simulate", "--scene", "forging", "--rig", root / "rig.json", "--patterns",
                          root / "patterns", "--out", root / "capture", "--supersample", "1")
    assert result.returncode == 0, result.stderr
    assert _thermofield("reconstruct", "--rig", root / "rig.json", "--captures", root / "capture",
                        "--out", root / "cloud.ply").returncode == 0
    thermal = rig.devices["thermal"]
    write_thermal_frame(root / "thermal.npy", np.full((thermal.height, thermal.width), 500.0))
    part = write_billet_part(root, segments=60)
    vertices, triangles = cylinder_mesh(45.0, 200.0, 60)
    hot = HotPart(vertices, triangles, load_part(part).material, SurfaceTemperature(base=1000.0), pose=billet_pose())
    devices = rig.devices
    field, _ = simulated_field(hot, devices["camera"], devices["projector"], devices["thermal"],
                               np.random.default_rng(0))
    write_cloud(root / "field.ply", field)
    (root / "board.json").write_text('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 1.0}')
    (root / "images").mkdir()
    for image in sorted((DATA / "opencv-chessboard").glob("left0[1-5].jpg")):
        shutil.copy(image, root / "images")
    return {"root": root, "rig": root / "rig.json", "patterns": root / "patterns", "captures": root / "capture",
            "cloud": root / "cloud.ply", "thermal": root / "thermal.npy", "field": root / "field.ply", "part": part,
            "board": root / "board.json", "images": root / "images",
            "fixed": DATA / "tno-ir-visible" / "vi" / "01.png", "moving": DATA / "tno-ir-visible" / "ir" / "01.png",
            "calibration": DATA / "slstudio" / "calibration" / "calibration.xml",
            "rjpeg": DATA / "flir-rjpeg" / "10-ir_fussbodenheizung.jpg"}


def _corrupt_frame(captures: Path, into: Path) -> Path:
    shutil.copytree(captures, into / "broken")
    _flip_bytes(into / "broken" / "00_white.png")
    return into / "broken"


def _corrupt_copy(text: bytes, name: str) -> Callable[[Path, Path], Path]:
    def make(original: Path, into: Path) -> Path:
        (into / name).write_bytes(text)
        return into / name
    return make


def _corrupt_image(original: Path, into: Path) -> Path:
    shutil.copy(original, into / "broken.png")
    _flip_bytes(into / "broken.png")
    return into / "broken.png"


def _corrupt_database(original: Path, into: Path) -> Path:
    (into / "data").mkdir()
    (into / "data" / "thermofield.db").write_bytes(b"this is not an SQLite database\n" * 100)
    return into / "data"


@dataclass(frozen=True)
class Command:
    """A command that reads and writes files: ``argv(inputs, out)``, the name of its output, the input the
    missing and corrupt cases replace, how to corrupt it (and the path the error must name)."""

    argv: Callable[[dict[str, Path], Path], list]
    output: str
    primary: str | None = None
    corrupt: Callable[[Path, Path], Path] | None = None
    directory: bool = False  # the output is a directory, created if missing (no missing-directory case)
    named_in_error: Callable[[Path], Path] = lambda corrupt: corrupt
    written_first: Callable[[Path], Path] = lambda out: out  # the output file whose failure is reported


COMMANDS = {
    "reconstruct": Command(lambda i, out: ["reconstruct", "--rig", i["rig"], "--captures", i["captures"],
                                           "--out", out], "cloud.ply", "captures", _corrupt_frame,
                           named_in_error=lambda broken: broken / "00_white.png"),
    "patterns": Command(lambda i, out: ["patterns", "--projector", "256x160", "--out", out], "patterns",
                        directory=True),
    "simulate": Command(lambda i, out: ["simulate", "--scene", "forging", "--rig", i["rig"], "--patterns",
                                        i["patterns"], "--out", out, "--supersample", "1"], "capture", "rig",
                        _corrupt_copy(b'{"version": 1, "devices": {', "rig.json"), directory=True),
    "fuse": Command(lambda i, out: ["fuse", "--rig", i["rig"], "--cloud", i["cloud"], "--thermal", i["thermal"],
                                    "--out", out], "field.ply", "cloud",
                    _corrupt_copy(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
                                  b"end_header\n\x00\x01", "cloud.ply")),
    "field": Command(lambda i, out: ["field", "--rig", i["rig"], "--captures", i["captures"], "--thermal",
                                     i["thermal"], "--out", out], "field.ply", "thermal",
                     _corrupt_copy(b"\x93NUMPY garbage", "thermal.npy")),
    "thermal convert": Command(lambda i, out: ["thermal", "convert", i["rjpeg"], out], "temperature.tiff", "rjpeg",
                               _corrupt_copy(b"\xff\xd8\xff\xe1\x00\x10FLIR\x00\x01\x00\x01", "IR_0042.jpg")),
    "inspect": Command(lambda i, out: ["inspect", "--field", i["field"], "--part", i["part"], "--out", out],
                       "report.json", "part", _corrupt_copy(b'{"version": 1, "name": ', "part.json")),
    "register": Command(lambda i, out: ["register", "--fixed", i["fixed"], "--moving", i["moving"], "--out", out],
                        "reg.json", "moving", _corrupt_image),
    "rig import": Command(lambda i, out: ["rig", "import", i["calibration"], "--format", "slstudio", "--out", out],
                          "rig.json", "calibration", _corrupt_copy(b"<?xml version='1.0'?>\n<opencv_storage><Kc>",
                                                                   "calibration.xml")),
    "calibrate camera": Command(lambda i, out: ["calibrate", "camera", "--board", i["board"], "--images",
                                                i["images"], "--out", out], "camera.json", "images",
                                _corrupt_copy(b"not a directory", "images"),
                                written_first=lambda out: out.with_name(f"{out.stem}_residual_bars.png")),
    "apikey create": Command(lambda i, out: ["apikey", "create", "--scopes", "read", "--data-dir", out], "data",
                             "data", _corrupt_database, directory=True,
                             named_in_error=lambda data: data / "thermofield.db"),
    "apikey list": Command(lambda i, out: ["apikey", "list", "--data-dir", out], "data", "data", _corrupt_database,
                           directory=True, named_in_error=lambda data: data / "thermofield.db"),
    "maintenance": Command(lambda i, out: ["maintenance", "--data-dir", out], "data", "data", _corrupt_database,
                           directory=True, named_in_error=lambda data: data / "thermofield.db"),
    "demo": Command(lambda i, out: ["demo", "--data-dir", out, "--exit-after-scan"], "data", "data",
                    _corrupt_database, directory=True, named_in_error=lambda data: data / "thermofield.db"),
}
CASES = [(name, case) for name, command in COMMANDS.items() for case in
         ("missing input", "missing directory", "a file in the way", "read-only disk", "full disk", "corrupt input")
         if not (case in ("missing input", "corrupt input") and command.primary is None)
         and not (case == "missing input" and command.output == "data")  # a new data directory is created
         and not (case == "missing directory" and command.directory)  # so is a new output directory
         and not (case == "a file in the way" and not command.directory)]


def _fill(disk: Path) -> None:
    """Fill a small disk to the last byte."""
    descriptor = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(descriptor, b"\0" * 4096)  # a short write, then ENOSPC
    except OSError as error:
        assert error.errno == errno.ENOSPC
    finally:
        os.close(descriptor)


@pytest.mark.parametrize(("name", "case"), CASES, ids=[f"{name}: {case}" for name, case in CASES])
def test_every_bad_path_gets_one_line_naming_it(name, case, inputs, small_disk, tmp_path):
    command = COMMANDS[name]
    given = dict(inputs)
    out = tmp_path / command.output
    expected: list[str] = []
    if case == "missing input":
        given[command.primary] = tmp_path / f"absent-{inputs[command.primary].name}"
        expected = [str(given[command.primary])]
    elif case == "corrupt input":
        given[command.primary] = command.corrupt(inputs.get(command.primary), tmp_path)
        expected = [str(command.named_in_error(given[command.primary]))]
        if command.output == "data":
            out = given["data"]
    elif case == "missing directory":
        out = tmp_path / "no-such-dir" / command.output
        expected = [str(command.written_first(out)), "does not exist"]
    elif case == "a file in the way":  # of the output directory
        out.write_text("a file\n")
        expected = [str(out), "a file is in the way of a directory"]
    elif case == "read-only disk":
        out = small_disk(1 << 20, "ro") / command.output
        expected = [str(command.written_first(out)), "read-only file system"]
    else:
        disk = small_disk(256 << 10)
        _fill(disk)
        out = disk / command.output
        expected = [str(command.written_first(out)), "no space left"]
    result = _thermofield(*command.argv(given, out))
    assert result.returncode == BAD_INPUT, (result.returncode, result.stderr)
    _one_error_line(result, *expected)
    if case == "full disk":  # nothing half-written: no file but the filler holds a byte
        assert [path for path in out.parent.rglob("*") if path.is_file() and path.stat().st_size
                and path.name != "filler"] == []


def test_a_corrupt_frame_gets_one_line_and_no_library_noise(inputs, tmp_path):
    broken = _corrupt_frame(inputs["captures"], tmp_path)
    result = _thermofield("reconstruct", "--rig", inputs["rig"], "--captures", broken, "--out", tmp_path / "c.ply")
    assert result.returncode == BAD_INPUT
    _one_error_line(result, str(broken / "00_white.png"), "cannot read the frame")
    assert "libpng" not in result.stderr and "[ERROR" not in result.stderr

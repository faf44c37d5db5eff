"""The default sequence, the pattern equations, and ``thermofield patterns``."""

import json

import numpy as np
import pytest

from services.cli.main import main
from services.formats.images import read_frame
from services.formats.sequence import load_sequence, parse_sequence, read_capture
from services.structured_light.decode import decode
from services.structured_light.patterns import complementary_gray_bit, generate_sequence, render_patterns


def test_default_sequence_layout():
    sequence, patterns = generate_sequence(1280, 800)
    kinds = [frame.kind for frame in sequence.frames]
    assert kinds[:2] == ["white", "black"]
    assert kinds.count("phase") == 12 and kinds.count("gray") == 16  # bits 10..3, each with its inverse
    planes = sequence.gray_planes("x")
    assert [plane.bit for plane in planes] == list(range(3, 11))
    assert all(plane.complement is not None for plane in planes)
    assert 2 ** planes[0].bit == sequence.phase_groups("x")[0].period / 2  # complementary: half-period stripes
    assert patterns.shape == (30, 800, 1280) and patterns.dtype == np.uint8
    assert sequence.coded_axes == ("x",)
    assert len({frame.file for frame in sequence.frames}) == 30


@pytest.mark.parametrize(("period", "bit"), [(16, 3), (20, 3), (32, 4), (2, 0), (3, 0)])
def test_complementary_bit_gives_stripes_of_at_most_half_a_period(period, bit):
    assert complementary_gray_bit(period) == bit
    assert 2**bit <= max(1, period / 2) < 2 ** (bit + 1)


def test_gray_planes_encode_the_gray_code_of_the_column():
    sequence, patterns = generate_sequence(300, 2, period=4)
    code = np.zeros(300, np.int64)
    for plane in sequence.gray_planes("x"):
        lit = patterns[plane.frame, 0] == 255
        np.testing.assert_array_equal(lit, patterns[plane.complement, 0] == 0)
        code |= lit.astype(np.int64) << plane.bit
    columns = np.arange(300)
    np.testing.assert_array_equal(code, (columns ^ (columns >> 1)) & ~1)  # bit 0 dropped at period 4


def test_phase_frames_follow_the_documented_equation():
    sequence, patterns = generate_sequence(64, 3, period=10, steps=5)
    columns = np.arange(64)
    for index, frame in enumerate(sequence.frames):
        if frame.kind == "phase":
            expected = 255 * (0.5 + 0.5 * np.cos(2 * np.pi * columns / 10 - 2 * np.pi * frame.step / 5))
            np.testing.assert_array_equal(patterns[index], np.broadcast_to(np.rint(expected), (3, 64)))


def test_rows_are_coded_along_y():
    sequence, patterns = generate_sequence(40, 100, axes="y", period=8, steps=4)
    assert sequence.coded_axes == ("y",)
    gray = sequence.gray_planes("y")[0]
    assert np.all(patterns[gray.frame] == patterns[gray.frame][:, :1])  # constant along each row
    assert not np.all(patterns[gray.frame] == patterns[gray.frame][:1])


def test_render_patterns_draws_foreign_inverted_planes():
    sequence = parse_sequence(json.dumps({"projector": {"width": 8, "height": 1}, "frames": [
        {"file": "g.png", "kind": "gray", "axis": "x", "bit": 1, "inverted": True},
        {"file": "h.png", "kind": "gray", "axis": "x", "bit": 2, "inverted": True},
        {"file": "w.png", "kind": "white"}, {"file": "b.png", "kind": "black"}]}))
    patterns = render_patterns(sequence)
    np.testing.assert_array_equal(patterns[0, 0] // 255, [1, 1, 0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(patterns[1, 0] // 255, [1, 1, 1, 1, 0, 0, 0, 0])
    assert patterns[2].min() == 255 and patterns[3].max() == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"axes": "z"}, "axes must be"), ({"steps": 2}, "at least 3 steps"), ({"period": 0.5}, "at least 1")],
)
def test_generate_refuses_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        generate_sequence(64, 64, **kwargs)


def test_cli_writes_pngs_and_a_manifest_that_decode_back(tmp_path, capsys):
    out = tmp_path / "patterns"
    assert main(["patterns", "--projector", "96x40", "--out", str(out), "--period", "8", "--steps", "4",
                 "--axes", "xy"]) == 0
    assert "sequence.json" in capsys.readouterr().out
    sequence = load_sequence(out)
    assert (sequence.projector.width, sequence.projector.height) == (96, 40)
    first = read_frame(out / sequence.frames[0].file)
    assert first.dtype == np.uint8 and first.shape == (40, 96)
    assert not list(out.glob("*.part*"))
    sequence, frames = read_capture(out)  # the patterns are their own ideal capture
    decoded = decode((20 + 0.8 * frames).astype(np.uint8), sequence)
    rows, columns = np.mgrid[0:40, 0:96]
    assert decoded.valid.all()
    assert np.abs(decoded.projector_x - columns).max() < 0.05
    assert np.abs(decoded.projector_y - rows).max() < 0.05


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--projector", "1280"], "--projector: expected WIDTHxHEIGHT"),
        (["--projector", "0x800"], "--projector: expected WIDTHxHEIGHT"),
        (["--projector", "64x32", "--steps", "2"], "--steps: phase shifting needs at least 3 steps"),
        (["--projector", "64x32", "--period", "1"], "--period: the phase period must be at least 2"),
    ],
)
def test_cli_bad_arguments_exit_2_with_a_message(tmp_path, capsys, arguments, message):
    assert main(["patterns", "--out", str(tmp_path / "out"), *arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error
    assert not (tmp_path / "out").exists()


def test_cli_refuses_a_file_as_output_directory(tmp_path, capsys):
    target = tmp_path / "file"
    target.write_text("keep me")
    assert main(["patterns", "--projector", "64x32", "--out", str(target)]) == 2
    assert "a file is in the way of a directory" in capsys.readouterr().err
    assert target.read_text() == "keep me"

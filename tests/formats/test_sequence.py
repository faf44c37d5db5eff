"""The sequence manifest: parsing, validation messages, saving, and reading captures."""

import json

import numpy as np
import pytest

from services.errors import InputError
from services.formats.images import write_png
from services.formats.sequence import load_sequence, parse_sequence, read_capture, save_sequence


def _manifest(frames, width=1824, height=1140):
    return json.dumps({"version": 1, "projector": {"width": width, "height": height}, "frames": frames})


def _example_1824():
    """The documented example: white, black, 10 column Gray planes MSB first, bit 0 dropped."""
    frames = [{"file": "white.png", "kind": "white"}, {"file": "black.png", "kind": "black"}]
    frames += [{"file": f"gray_x_{bit:02d}.png", "kind": "gray", "axis": "x", "bit": bit} for bit in range(10, 0, -1)]
    return frames


def test_documented_1824_example_parses():
    sequence = parse_sequence(_manifest(_example_1824()))
    assert sequence.code_bits("x") == 11
    planes = sequence.gray_planes("x")
    assert [plane.bit for plane in planes] == list(range(1, 11))
    assert all(plane.complement is None for plane in planes)
    assert sequence.coded_axes == ("x",)
    assert (sequence.white_index, sequence.black_index) == (0, 1)


def test_documented_example_in_docs_is_valid():
    from pathlib import Path

    text = (Path(__file__).parents[2] / "docs" / "sequence-manifest.md").read_text()
    block = text.split("```json\n", 1)[1].split("```", 1)[0]
    sequence = parse_sequence(block)
    assert sequence.projector.width == 1824
    assert [plane.bit for plane in sequence.gray_planes("x")] == list(range(1, 11))


def test_phase_groups_are_ordered_coarsest_first_and_by_step():
    frames = [
        {"file": f"p{period}_{step}.png", "kind": "phase", "axis": "y", "period": period, "step": step, "steps": 3}
        for period in (16, 2048)
        for step in (2, 0, 1)
    ]
    sequence = parse_sequence(_manifest(frames))
    groups = sequence.phase_groups("y")
    assert [group.period for group in groups] == [2048, 16]
    assert [sequence.frames[i].step for i in groups[1].frames] == [0, 1, 2]
    assert sequence.coded_axes == ("y",)


@pytest.mark.parametrize(
    ("frames", "expected"),
    [
        (_example_1824()[2:], "frames[9]: axis x Gray bit 1 has no inverse frame"),
        (_example_1824() + [{"file": "white.png", "kind": "black"}], "file 'white.png' is listed 2 times"),
        (_example_1824()[:3] + _example_1824()[4:], "the Gray code of axis x lacks bit(s) [9]"),
        (_example_1824() + [{"file": "a.png", "kind": "gray", "axis": "x", "bit": 11}], "above the most significant"),
        (_example_1824() + [{"file": "a.png", "kind": "gray", "axis": "x", "bit": 4}], "already shown by frames"),
        (_example_1824() + [{"file": "a.png", "kind": "white"}], "a second white frame"),
        ([{"file": "p.png", "kind": "phase", "axis": "x", "period": 16, "step": 8, "steps": 8}],
         "frames[0]: step 8 is out of range for steps 8"),
        ([{"file": "p.png", "kind": "phase", "axis": "x", "period": 16, "step": 0, "steps": 2}],
         "frames[0].steps: Input should be greater than or equal to 3"),
        ([{"file": f"p{k}.png", "kind": "phase", "axis": "x", "period": 4000, "step": k, "steps": 4} for k in (0, 1, 3)],
         "lacks step(s) [2]"),
        ([{"file": f"p{k}.png", "kind": "phase", "axis": "x", "period": 16, "step": k, "steps": 3} for k in range(3)],
         "cannot be unwrapped"),
        ([{"file": "w.png", "kind": "white"}], "codes no projector axis"),
        ([{"file": "../w.png", "kind": "white"}], "plain file name"),
        ([{"file": "w.png", "kind": "grey"}], "frames[0]: Input tag 'grey'"),
        ([{"file": "g.png", "kind": "gray", "axis": "z", "bit": 0, "inverted": True}], "frames[0].axis"),
    ],
)
def test_contradictions_are_refused_naming_the_field(frames, expected):
    with pytest.raises(InputError, match="^sequence.json: ") as raised:
        parse_sequence(_manifest(frames))
    assert expected in str(raised.value)


def test_gray_stripes_wider_than_period_are_refused():
    frames = [{"file": f"g{b}{inv}.png", "kind": "gray", "axis": "x", "bit": b, "inverted": inv}
              for b in range(5, 11) for inv in (False, True)]
    frames += [{"file": f"p{k}.png", "kind": "phase", "axis": "x", "period": 16, "step": k, "steps": 4} for k in range(4)]
    with pytest.raises(InputError, match="32 px wide, wider than the coarsest phase period 16"):
        parse_sequence(_manifest(frames))


def test_save_and_load_round_trip(tmp_path):
    sequence = parse_sequence(_manifest(_example_1824()))
    path = save_sequence(sequence, tmp_path)
    assert path == tmp_path / "sequence.json"
    assert load_sequence(tmp_path) == sequence
    assert not list(tmp_path.glob("*.part"))


def test_load_names_the_missing_or_invalid_file(tmp_path):
    with pytest.raises(InputError, match="sequence.json: cannot read"):
        load_sequence(tmp_path)
    (tmp_path / "sequence.json").write_text("{not json")
    with pytest.raises(InputError, match=str(tmp_path / "sequence.json")):
        load_sequence(tmp_path)


def _write_capture(directory, dtype=np.uint8, sizes=None):
    frames = [{"file": "w.png", "kind": "white"}, {"file": "b.tif", "kind": "black"}]
    frames += [{"file": f"g{b}.png", "kind": "gray", "axis": "x", "bit": b} for b in (1, 0)]
    save_sequence(parse_sequence(_manifest(frames, width=4, height=1)), directory)
    rng = np.random.default_rng(0)
    images = []
    for index, frame in enumerate(frames):
        shape = sizes[index] if sizes else (5, 7)
        image = rng.integers(0, np.iinfo(dtype).max // 2, size=shape, dtype=dtype)
        if frame["kind"] == "white":
            image += np.iinfo(dtype).max // 2
        if frame["file"].endswith(".tif"):
            import tifffile

            tifffile.imwrite(directory / frame["file"], image)
        else:
            write_png(directory / frame["file"], image)
        images.append(image)
    return images


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_read_capture_returns_frames_in_manifest_order(tmp_path, dtype):
    images = _write_capture(tmp_path, dtype)
    sequence, stack = read_capture(tmp_path)
    assert stack.dtype == dtype and stack.shape == (4, 5, 7)
    np.testing.assert_array_equal(stack, np.stack(images))
    assert sequence.frames[1].file == "b.tif"


def test_read_capture_takes_a_manifest_from_elsewhere(tmp_path):
    """Captures of other software have no sequence.json (and may be read-only): one manifest serves them all."""
    capture = tmp_path / "capture"
    capture.mkdir()
    images = _write_capture(capture)
    manifest = tmp_path / "foreign.json"
    (capture / "sequence.json").rename(manifest)
    sequence, stack = read_capture(capture, manifest)
    np.testing.assert_array_equal(stack, np.stack(images))
    with pytest.raises(InputError, match="cannot read the sequence manifest"):
        read_capture(capture)
    manifest.write_text('{"projector": {"width": 4, "height": 1}, "frames": []}')
    with pytest.raises(InputError, match=f"{manifest}: frames"):
        read_capture(capture, manifest)


def test_read_capture_names_a_missing_frame(tmp_path):
    _write_capture(tmp_path)
    (tmp_path / "g0.png").unlink()
    with pytest.raises(InputError, match="g0.png: frame file is missing"):
        read_capture(tmp_path)


def test_read_capture_names_an_unreadable_frame(tmp_path):
    _write_capture(tmp_path)
    (tmp_path / "g1.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="g1.png: cannot read the frame"):
        read_capture(tmp_path)


def test_read_capture_names_a_frame_of_another_size(tmp_path):
    _write_capture(tmp_path, sizes=[(5, 7), (5, 7), (5, 8), (5, 7)])
    with pytest.raises(InputError, match="g1.png: frame is 8x5 but w.png is 7x5"):
        read_capture(tmp_path)


def test_read_capture_names_a_frame_of_another_bit_depth(tmp_path):
    _write_capture(tmp_path)
    write_png(tmp_path / "g0.png", np.zeros((5, 7), np.uint16))
    with pytest.raises(InputError, match="g0.png: frame is uint16 but w.png is uint8"):
        read_capture(tmp_path)


def test_read_capture_refuses_a_missing_directory(tmp_path):
    with pytest.raises(InputError, match="capture directory does not exist"):
        read_capture(tmp_path / "nope")


def test_read_capture_refuses_frames_out_of_the_manifest_order(tmp_path):
    _write_capture(tmp_path)
    write_png(tmp_path / "w.png", np.full((5, 7), 10, np.uint8))
    import tifffile

    tifffile.imwrite(tmp_path / "b.tif", np.full((5, 7), 200, np.uint8))
    with pytest.raises(InputError, match="b.tif: the black frame is brighter than the white frame w.png"):
        read_capture(tmp_path)

import json

import numpy as np
import pytest

from services.cli.main import main
from services.formats.images import read_frame
from services.formats.rig import load_rig, save_rig
from services.formats.sequence import load_sequence
from services.simulation.render import render_view
from services.simulation.scene import load_scene

pytestmark = pytest.mark.integration

PLANE_SCENE = {"ambient": 0.05, "surfaces": [
    {"type": "plane", "center": [0, 0, 400], "normal": [0, 0, -1], "u_axis": [1, 0, 0], "size": [400, 300],
     "albedo": {"base": 0.7, "texture_amplitude": 0.1, "feature_size": 30, "seed": 4}}]}


@pytest.fixture
def capture_inputs(tmp_path, small_rig):
    save_rig(small_rig, tmp_path / "rig.json")
    (tmp_path / "scene.json").write_text(json.dumps(PLANE_SCENE))
    assert main(["patterns", "--projector", "160x120", "--out", str(tmp_path / "patterns")]) == 0
    return tmp_path


def _simulate(inputs, *extra):
    return main(["simulate", "--scene", str(inputs / "scene.json"), "--rig", str(inputs / "rig.json"),
                 "--patterns", str(inputs / "patterns"), "--out", str(inputs / "out"), *extra])


def test_simulate_writes_the_frames_manifest_and_ground_truth(capture_inputs, small_rig):
    assert _simulate(capture_inputs, "--noise", "1.5", "--blur", "0.7", "--seed", "3") == 0
    out = capture_inputs / "out"
    sequence = load_sequence(out)
    assert sequence == load_sequence(capture_inputs / "patterns")
    frames = [read_frame(out / frame.file) for frame in sequence.frames]
    assert all(frame.shape == (150, 200) and frame.dtype == np.uint8 for frame in frames)
    white, black = (frames[i] for i, f in enumerate(sequence.frames) if f.kind in ("white", "black"))
    depth, points = np.load(out / "depth.npy"), np.load(out / "points.npy")
    lit = read_frame(out / "lit_mask.png") > 0
    assert depth.shape == (150, 200) and points.shape == (150, 200, 3)
    seen = np.isfinite(depth)
    np.testing.assert_allclose(points[seen][:, 2], 400)
    truth = render_view(load_scene(out / "scene.json"), small_rig.devices["camera"],
                        small_rig.devices["projector"]).truth
    np.testing.assert_array_equal(depth, truth.depth)
    np.testing.assert_array_equal(lit, truth.lit)
    np.testing.assert_array_equal(np.load(out / "projector_pixels.npy"), truth.projector_pixels)
    assert lit.mean() > 0.3
    assert np.median(white[lit].astype(int) - black[lit]) > 100
    assert load_rig(out / "rig.json") == small_rig


def test_simulate_is_deterministic_by_seed_and_writes_16_bit(capture_inputs):
    assert _simulate(capture_inputs, "--seed", "5", "--bit-depth", "16") == 0
    name = load_sequence(capture_inputs / "out").frames[0].file
    first = read_frame(capture_inputs / "out" / name)
    assert first.dtype == np.uint16 and first.max() > 1000
    assert _simulate(capture_inputs, "--seed", "5", "--bit-depth", "16") == 0
    np.testing.assert_array_equal(read_frame(capture_inputs / "out" / name), first)


def test_simulate_accepts_preset_scene_and_rig(tmp_path):
    assert main(["patterns", "--projector", "1024x768", "--out", str(tmp_path / "patterns")]) == 0
    assert main(["simulate", "--scene", "paper-plane:450", "--rig", "paper", "--patterns", str(tmp_path / "patterns"),
                 "--out", str(tmp_path / "out"), "--supersample", "1"]) == 0
    depth = np.load(tmp_path / "out" / "depth.npy")
    points = np.load(tmp_path / "out" / "points.npy")
    assert np.isfinite(depth).sum() > 50_000
    np.testing.assert_allclose(points[np.isfinite(depth)][:, 2], 450)
    assert load_rig(tmp_path / "out" / "rig.json").devices["camera"].K[0][0] == 800


@pytest.mark.parametrize("change, message", [
    (lambda d: (d / "scene.json").unlink(), "scene.json: cannot read the scene file"),
    (lambda d: (d / "scene.json").write_text('{"surfaces": [{"type": "sphere", "center": [0, 0, 1]}]}'),
     "scene.json: surfaces[0].radius"),
    (lambda d: (d / "rig.json").write_text('{"devices": {}}'), "exactly one camera"),
    (lambda d: (d / "patterns" / "sequence.json").unlink(), "sequence.json: cannot read the sequence manifest"),
    (lambda d: (d / "patterns" / "00_white.png").unlink(), "00_white.png: frame file is missing"),
])
def test_simulate_bad_inputs_exit_2_naming_the_problem(capture_inputs, capsys, change, message):
    change(capture_inputs)
    assert _simulate(capture_inputs) == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error
    assert not (capture_inputs / "out").exists()


@pytest.mark.parametrize("extra, message", [
    (["--supersample", "2"], "--supersample must be a positive odd number"),
    (["--noise", "-1"], "non-negative"),
    (["--camera", "thermal"], "no device named 'thermal'"),
    (["--rig", "paper"], "projector is 160x120 but the rig's projector is 1024x768"),
    (["--scene", "paper-plane:0"], "must be a positive number"),
    (["--scene", "paper-sphere:-100"], "the radius in 'paper-sphere:-100' must be a positive number"),
    (["--scene", "paper-sphere:big"], "the radius in 'paper-sphere:big' is not a number"),
])
def test_simulate_bad_options_exit_2(capture_inputs, capsys, extra, message):
    assert _simulate(capture_inputs, *extra) == 2
    assert message in capsys.readouterr().err


def test_simulate_refuses_to_overwrite_its_patterns(capture_inputs, capsys):
    patterns = capture_inputs / "patterns"
    before = {path.name: path.read_bytes() for path in patterns.iterdir()}
    assert main(["simulate", "--scene", str(capture_inputs / "scene.json"), "--rig", str(capture_inputs / "rig.json"),
                 "--patterns", str(patterns), "--out", str(patterns)]) == 2
    assert "must differ from --patterns" in capsys.readouterr().err
    assert {path.name: path.read_bytes() for path in patterns.iterdir()} == before


def test_simulate_refuses_16_bit_frames_named_bmp(capture_inputs, capsys):
    manifest = capture_inputs / "patterns" / "sequence.json"
    sequence = json.loads(manifest.read_text())
    first = sequence["frames"][0]["file"]
    (capture_inputs / "patterns" / first).rename(capture_inputs / "patterns" / "white.bmp")
    sequence["frames"][0]["file"] = "white.bmp"
    manifest.write_text(json.dumps(sequence))
    assert _simulate(capture_inputs, "--bit-depth", "16") == 2
    assert "'white.bmp' cannot hold 16-bit images" in capsys.readouterr().err
    assert _simulate(capture_inputs, "--supersample", "1") == 0
    assert read_frame(capture_inputs / "out" / "white.bmp").dtype == np.uint8

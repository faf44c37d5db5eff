"""``thermofield reconstruct`` end to end through the files a user has, and its bad inputs."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from services.formats.ply import read_cloud

pytestmark = pytest.mark.integration


def _thermofield(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "services.cli.main", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    assert _thermofield("patterns", "--projector", "1024x768", "--out", root / "patterns").returncode == 0
    result = _thermofield("simulate", "--scene", "paper-plane:500", "--rig", "paper", "--patterns",
                          root / "patterns", "--out", root / "capture", "--supersample", "1", "--noise", "1.5")
    assert result.returncode == 0, result.stderr
    return root


def test_reconstructs_a_simulated_capture_to_ply(capture, tmp_path):
    result = _thermofield("reconstruct", "--rig", capture / "capture" / "rig.json", "--captures",
                          capture / "capture", "--out", tmp_path / "cloud.ply")
    assert result.returncode == 0, result.stderr
    cloud = read_cloud(tmp_path / "cloud.ply")
    assert {"x", "y", "z", "u", "v", "quality", "intensity", "nx", "ny", "nz"} <= set(cloud)
    assert cloud["x"].dtype == np.float32
    assert len(cloud["z"]) > 50_000
    assert np.abs(cloud["z"] - 500).mean() < 0.05
    depth = np.load(capture / "capture" / "depth.npy")
    assert np.isfinite(depth[cloud["v"].astype(int), cloud["u"].astype(int)]).all()


def _broken_copy(capture, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(capture / "capture", broken)
    return broken


def test_missing_frame_is_named(capture, tmp_path):
    broken = _broken_copy(capture, tmp_path)
    victim = json.loads((broken / "sequence.json").read_text())["frames"][5]["file"]
    (broken / victim).unlink()
    result = _thermofield("reconstruct", "--rig", broken / "rig.json", "--captures", broken, "--out",
                          tmp_path / "c.ply")
    assert result.returncode == 2
    assert victim in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "c.ply").exists()


def test_rig_without_the_named_device(capture, tmp_path):
    result = _thermofield("reconstruct", "--rig", capture / "capture" / "rig.json", "--captures",
                          capture / "capture", "--camera", "left", "--out", tmp_path / "c.ply")
    assert result.returncode == 2
    assert "no device named 'left'" in result.stderr


def test_manifest_for_another_projector(capture, tmp_path):
    broken = _broken_copy(capture, tmp_path)
    manifest = json.loads((broken / "sequence.json").read_text())
    manifest["projector"]["height"] = 800
    (broken / "sequence.json").write_text(json.dumps(manifest))
    result = _thermofield("reconstruct", "--rig", broken / "rig.json", "--captures", broken, "--out",
                          tmp_path / "c.ply")
    assert result.returncode == 2
    assert "sequence.json" in result.stderr and "1024x800 projector" in result.stderr


def test_dark_capture_is_an_error_not_an_empty_cloud(capture, tmp_path):
    broken = _broken_copy(capture, tmp_path)
    import cv2
    for frame in json.loads((broken / "sequence.json").read_text())["frames"]:
        cv2.imwrite(str(broken / frame["file"]), np.zeros((768, 1024), np.uint8))
    result = _thermofield("reconstruct", "--rig", broken / "rig.json", "--captures", broken, "--out",
                          tmp_path / "c.ply")
    assert result.returncode == 2
    assert "no point could be reconstructed" in result.stderr
    assert not (tmp_path / "c.ply").exists()


def test_frames_of_the_wrong_size_for_the_rig(capture, tmp_path):
    broken = _broken_copy(capture, tmp_path)
    rig = json.loads((broken / "rig.json").read_text())
    rig["devices"]["camera"]["width"] = 1280
    (broken / "rig.json").write_text(json.dumps(rig))
    result = _thermofield("reconstruct", "--rig", broken / "rig.json", "--captures", broken, "--out",
                          tmp_path / "c.ply")
    assert result.returncode == 2
    assert "frames are 1024x768 but the rig's camera is 1280x768" in result.stderr

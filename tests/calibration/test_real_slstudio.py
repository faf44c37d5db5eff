"""SLStudio's real rig (../shared/data/slstudio): calibrated with our commands, against SLStudio's own figures.

Each calibration and reconstruction runs once per module (module-scoped fixtures), from the files, every
time: nothing is cached between test sessions. Figures: docs/real-data.md (experiments/real_slstudio.py).
"""

import json
from pathlib import Path

import numpy as np
import pytest

from services.calibration.camera import OUTLIER_MADS, OUTLIER_RATIO
from services.cli.main import main as thermofield
from services.cli.reconstruct import reconstruct_from_files

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data" / "slstudio"  # shared/ beside the clone
CALIBRATION_MANIFEST = REPO / "experiments" / "slstudio" / "calibration_sequence.json"
SKULL_MANIFEST = REPO / "experiments" / "slstudio" / "skull_sequence.json"
SLSTUDIO = {"camera": 0.282, "projector": 0.463, "stereo": 0.422}  # calibration.xml's cam/proj/stereo_error


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """Our calibration from all six sequences, with ``thermofield calibrate camera`` then ``projector``."""
    assert (DATA / "calibration" / "calseq2").is_dir(), f"the real SLStudio data is missing from {DATA}"
    work = tmp_path_factory.mktemp("slstudio")
    board = work / "board.json"
    board.write_text(json.dumps({"type": "chessboard", "inner_corners": [13, 9], "square_mm": 10.0}))
    common = ["--board", str(board), "--captures", *[str(DATA / "calibration" / f"calseq{n}") for n in range(1, 7)],
              "--manifest", str(CALIBRATION_MANIFEST)]
    assert thermofield(["calibrate", "camera", *common, "--out", str(work / "camera.json")]) == 0
    assert thermofield(["calibrate", "projector", *common, "--camera", str(work / "camera.json"),
                        "--out", str(work / "rig.json")]) == 0
    return {"camera": json.loads((work / "camera.json").read_text()),
            "projector": json.loads((work / "rig_projector.json").read_text()), "rig": work / "rig.json"}


@pytest.fixture(scope="module")
def five_cameras(tmp_path_factory):
    """Our camera calibration from SLStudio's own five sequences (1, 3, 4, 5, 6)."""
    work = tmp_path_factory.mktemp("slstudio_five")
    board = work / "board.json"
    board.write_text(json.dumps({"type": "chessboard", "inner_corners": [13, 9], "square_mm": 10.0}))
    assert thermofield(["calibrate", "camera", "--board", str(board), "--captures",
                        *[str(DATA / "calibration" / f"calseq{n}") for n in (1, 3, 4, 5, 6)],
                        "--manifest", str(CALIBRATION_MANIFEST), "--out", str(work / "camera.json")]) == 0
    return json.loads((work / "camera.json").read_text())


@pytest.fixture(scope="module")
def slstudio_rig(tmp_path_factory):
    out = tmp_path_factory.mktemp("imported") / "rig.json"
    assert thermofield(["rig", "import", "--format", "slstudio", str(DATA / "calibration" / "calibration.xml"),
                        "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def skull(six, slstudio_rig):
    """skull_2x3 reconstructed with our calibration and with SLStudio's, as camera-pixel point maps."""
    maps = {}
    for name, rig in (("ours", six["rig"]), ("slstudio", slstudio_rig)):
        _, cloud = reconstruct_from_files(rig, DATA / "skull_2x3", manifest=SKULL_MANIFEST, max_indirect=0.33,
                                       consistency=0.5)
        points = np.full((1352, 1688, 3), np.nan)
        points[np.round(cloud["v"]).astype(int), np.round(cloud["u"]).astype(int)] = np.column_stack(
            [cloud["x"], cloud["y"], cloud["z"]])
        maps[name] = points
    return maps


def test_camera_calibration_meets_slstudios_rms_on_its_five_sequences(five_cameras):
    assert five_cameras["rms_px"] <= SLSTUDIO["camera"]
    window = five_cameras["corner_window"]
    held_out = {candidate["fraction"]: candidate["held_out_rms_px"] for candidate in window["candidates"]}
    assert window["fraction"] == min(held_out, key=held_out.get) and len(held_out) >= 5


def test_camera_calibration_of_all_six_has_every_sigma(six):
    camera = six["camera"]
    assert camera["rms_px"] <= 1.1 * SLSTUDIO["camera"]  # sequence 2's board is dimmer: 0.291 px on six
    assert set(camera["std"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert all(np.isfinite(s) and s > 0 for s in camera["std"].values())
    assert abs(camera["K"][0][0] / 2195.12 - 1) < 0.01  # SLStudio's focal length within 1 %


def test_projector_and_stereo_rms_meet_slstudios(six):
    report = six["projector"]
    assert report["projector_rms_px"] <= SLSTUDIO["projector"]
    assert report["stereo_rms_px"] <= SLSTUDIO["stereo"]
    assert all(np.isfinite(s) and s > 0 for s in report["std"].values()) and len(report["std"]) == 6
    assert set(report["stereo_std"]) == {"rx", "ry", "rz", "tx", "ty", "tz"}
    assert all(np.isfinite(s) and s > 0 for s in report["stereo_std"].values())
    assert abs(report["baseline_mm"] / 164.48 - 1) < 0.03  # SLStudio's baseline, |Tp|, within 3 %


def test_sequence_2_is_found_and_kept_because_its_residuals_are_ordinary(six):
    """SLStudio's operator left sequence 2 out; our detector finds its board and the outlier rule keeps it:
    its reprojection RMS is inside the spread of the other five, in the camera and in the projector."""
    views = {Path(view["image"]).name: view["rms_px"] for view in six["camera"]["views"]}
    assert sorted(views) == [f"calseq{n}" for n in range(1, 7)] and six["camera"]["rejected"] == []
    assert six["projector"]["rejected"] == [] and len(six["projector"]["views"]) == 6
    for rms in (np.array(list(views.values())), np.array(six["projector"]["per_view_rms_px"])):
        median = np.median(rms)
        limit = max(median + OUTLIER_MADS * 1.4826 * np.median(np.abs(rms - median)), OUTLIER_RATIO * median)
        assert rms[1] < limit  # calseq2
        assert rms[1] < 1.3 * median


def test_skull_is_covered_and_its_concavities_rejected(skull):
    ours = np.isfinite(skull["ours"][..., 2])

    def covered(x, y):
        return ours[y - 20:y + 20, x - 20:x + 20].mean()

    for x, y in ((1131, 276), (1250, 750), (1150, 980)):  # forehead, cheek, jaw: lit directly
        assert covered(x, y) > 0.9
    for x, y in ((1330, 520), (980, 560), (1200, 620)):  # inside the eye sockets and the nose: inter-reflections
        assert covered(x, y) < 0.1
    assert ours.mean() > 0.12  # 13.8 % of the image measured


def test_skull_clouds_of_both_calibrations_agree_to_their_calibration_difference(skull):
    both = np.isfinite(skull["ours"][..., 2]) & np.isfinite(skull["slstudio"][..., 2])
    assert both.sum() > 0.95 * np.isfinite(skull["ours"][..., 2]).sum()  # one decoding, two calibrations
    distance = np.linalg.norm(skull["ours"][both] - skull["slstudio"][both], axis=1)
    # 2.8 mm measured: the two calibrations differ by 3.3 mm (median) at 390 mm, docs/real-data.md
    assert np.median(distance) < 4.0

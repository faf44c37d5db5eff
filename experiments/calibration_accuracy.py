"""Calibration accuracy on real images and in simulation, and the sample report of docs/calibration.md.

1. OpenCV's 13 left chessboard images (``../shared/data/opencv-chessboard``) through
   ``thermofield calibrate camera``: the calibration JSON and its report PNGs are written to
   docs/figures/calibration/opencv_left*; the left/right pairs give the stereo RMS.
2. Simulated hollow-board infrared views at 320x256 (blur 1 px, noise 2 grey levels, lens
   distortion k1 = -0.2, k2 = 0.1), 15 views per calibration, 10 seeds: detection rate, focal
   length and principal point errors against the simulator's truth.
3. Monte-Carlo check of the predicted standard deviations: 200 calibrations from 8 exact views
   plus 0.2 px corner noise; predicted sigma (mean) over the spread of the estimates.

Run: .venv/bin/python experiments/calibration_accuracy.py  (writes docs/figures/calibration/accuracy.md)
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from services.calibration.camera import calibrate_camera
from services.calibration.corners import detect_board
from services.calibration.stereo import calibrate_stereo
from services.cli.main import main as thermofield
from services.formats.board import parse_board
from services.formats.calibration import load_camera_calibration
from services.formats.images import read_frame
from services.simulation.boards import render_board

ROOT = Path(__file__).parents[1]
IMAGES = ROOT.parent / "shared" / "data" / "opencv-chessboard"
FIGURES = ROOT / "docs" / "figures" / "calibration"
OPENCV_BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 1.0}')
IR_BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 20.0}')
IR_K = np.array([[400.0, 0.0, 161.3], [0.0, 400.0, 127.6], [0.0, 0.0, 1.0]])
IR_DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])


def real_images() -> list[str]:
    with tempfile.TemporaryDirectory() as scratch:
        left = Path(scratch) / "left"
        left.mkdir()
        for path in sorted(IMAGES.glob("left*.jpg")):
            shutil.copy(path, left / path.name)
        board = Path(scratch) / "board.json"
        board.write_text(OPENCV_BOARD.model_dump_json())
        out = FIGURES / "opencv_left.json"
        thermofield(["calibrate", "camera", "--board", str(board), "--images", str(left), "--out", str(out)])
    result = load_camera_calibration(out)
    sides = {side: [detect_board(read_frame(p), OPENCV_BOARD).image_points for p in sorted(IMAGES.glob(f"{side}*.jpg"))]
             for side in ("left", "right")}
    objects = [OPENCV_BOARD.object_points()] * len(sides["left"])
    left = calibrate_camera(objects, sides["left"], (640, 480))
    right = calibrate_camera(objects, sides["right"], (640, 480))
    stereo = calibrate_stereo(objects, sides["left"], sides["right"], (left.K, left.dist), (right.K, right.dist),
                              (640, 480))
    K = np.asarray(result.K)
    return [
        "| OpenCV chessboard images | ours | OpenCV's published |",
        "|---|---|---|",
        f"| left RMS (13 images) | {result.rms_px:.3f} px | 0.196 px |",
        f"| f_x, f_y | {K[0, 0]:.2f} +- {result.std['fx']:.2f}, {K[1, 1]:.2f} +- {result.std['fy']:.2f} | 532.81, 532.93 |",
        f"| c_x, c_y | {K[0, 2]:.2f} +- {result.std['cx']:.2f}, {K[1, 2]:.2f} +- {result.std['cy']:.2f} | 342.50, 233.89 |",
        f"| right RMS (13 images) | {right.rms:.3f} px | |",
        f"| stereo RMS (13 pairs) | {stereo.rms:.3f} px | |",
        f"| baseline | {stereo.baseline_mm:.3f} squares | |",
    ]


def infrared(seeds: int = 10, views: int = 15) -> list[str]:
    focal, principal, detected = [], [], 0
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        centre = IR_BOARD.object_points().mean(axis=0)
        points = []
        for index in range(views):
            angle = 2 * np.pi * (index + rng.uniform()) / views
            tilt = np.radians(rng.uniform(30, 40))
            R = cv2.Rodrigues(np.array([tilt * np.cos(angle), tilt * np.sin(angle), rng.uniform(-0.2, 0.2)]))[0]
            t = np.array([rng.uniform(-20, 20), rng.uniform(-15, 15), rng.uniform(340, 400)]) - R @ centre
            image = render_board(IR_BOARD, IR_K, IR_DIST, R, t, (320, 256), modality="infrared", blur_sigma=1.0,
                                 noise_sigma=2.0, rng=rng)
            detection = detect_board(image, IR_BOARD)
            if detection is not None:
                detected += 1
                points.append(detection.image_points)
        result = calibrate_camera([IR_BOARD.object_points()] * len(points), points, (320, 256), distortion="radial")
        focal.append(np.abs(np.diag(result.K)[:2] / np.diag(IR_K)[:2] - 1).max())
        principal.append(np.abs(result.K[:2, 2] - IR_K[:2, 2]).max())
    return [
        f"| simulated infrared, 320x256, {seeds} calibrations of {views} views | median | worst | target |",
        "|---|---|---|---|",
        f"| focal length error | {100 * np.median(focal):.3f}% | {100 * np.max(focal):.3f}% | <= 0.1% |",
        f"| principal point error | {np.median(principal):.3f} px | {np.max(principal):.3f} px | <= 0.5 px |",
        f"| frames detected | {detected} of {seeds * views} | | all |",
    ]


def monte_carlo(trials: int = 200) -> list[str]:
    K = np.array([[800.0, 0.0, 330.0], [0.0, 790.0, 235.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.15, 0.08, 0.0, 0.0, 0.0])
    centre = IR_BOARD.object_points().mean(axis=0)
    truth = []
    for index in range(8):
        angle = 2 * np.pi * index / 8
        R = cv2.Rodrigues(np.array([0.52 * np.cos(angle), 0.52 * np.sin(angle), 0.17 * np.sin(3 * angle)]))[0]
        t = np.array([25 * np.cos(2 * angle), 20 * np.sin(2 * angle), 450 * (1 + 0.1 * np.cos(3 * angle))]) - R @ centre
        truth.append(cv2.projectPoints(IR_BOARD.object_points(), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2))
    rng = np.random.default_rng(7)
    names = ("fx", "fy", "cx", "cy", "k1", "k2")
    estimates, predicted = [], []
    for _ in range(trials):
        noisy = [p + rng.normal(0.0, 0.2, p.shape) for p in truth]
        result = calibrate_camera([IR_BOARD.object_points()] * 8, noisy, (640, 480), distortion="radial",
                                  reject_outliers=False)
        estimates.append([result.K[0, 0], result.K[1, 1], result.K[0, 2], result.K[1, 2], *result.dist[:2]])
        predicted.append([result.std[n] for n in names])
    spread = np.std(estimates, axis=0, ddof=1)
    mean_predicted = np.mean(predicted, axis=0)
    rows = [f"| parameter ({trials} Monte-Carlo runs) | predicted sigma | Monte-Carlo spread | ratio |",
            "|---|---|---|---|"]
    rows += [f"| {n} | {p:.4g} | {s:.4g} | {p / s:.3f} |" for n, p, s in zip(names, mean_predicted, spread)]
    return rows


def main() -> None:
    FIGURES.mkdir(parents=True, exist_ok=True)
    sections = [real_images(), infrared(), monte_carlo()]
    text = "\n\n".join("\n".join(section) for section in sections) + "\n"
    (FIGURES / "accuracy.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()

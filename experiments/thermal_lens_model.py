"""Thermal calibration at low resolution: the lens model chosen from the data against stock OpenCV;
the tables of docs/calibration.md.

Run: ``.venv/bin/python experiments/thermal_lens_model.py`` (about 4 minutes on 2 cores).

1. Simulated hollow-board infrared views at 320x256 (f = 400 px, true distortion k1 = -0.2, k2 = 0.1):
   16 views of a 7x5 board (inner corners) with 30 mm squares, 300..600 mm away, tilted 20..40 degrees,
   blur 1 px, noise 2 grey levels; 10 seeds, with the board centres spread over the image or bunched
   near its centre. Each seed's corners are calibrated by stock OpenCV
   (``cv2.calibrateCamera``, five coefficients) and by ``calibrate_camera(distortion="auto")``.
2. Rich data: 40 sharp views (corner noise 0.05 px) of a 9x6 board by a 640x480 camera with a strongly
   distorted lens (k1 = -0.35, k2 = 0.15, p1 = 0.001, p2 = -0.0008, k3 = -0.03): which model is chosen.
"""

from __future__ import annotations

from collections import Counter

import cv2
import numpy as np

from services.calibration.camera import calibrate_camera
from services.calibration.corners import detect_board
from services.formats.board import parse_board
from services.simulation.boards import render_board

BOARD = parse_board('{"type": "chessboard", "inner_corners": [7, 5], "square_mm": 30.0}')
K = np.array([[400.0, 0.0, 161.3], [0.0, 400.0, 127.6], [0.0, 0.0, 1.0]])
DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])
SIZE = (320, 256)
RICH_BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')
RICH_K = np.array([[520.0, 0.0, 322.0], [0.0, 520.0, 238.0], [0.0, 0.0, 1.0]])
RICH_DIST = np.array([-0.35, 0.15, 0.001, -0.0008, -0.03])
RICH_SIZE = (640, 480)


def _poses(rng: np.random.Generator, board, K, dist, size, views: int, depth: tuple[float, float],
           margin: float = 8.0, spread: float = 0.25):
    """Board poses spread over depth and the image (board centres within ``spread`` of the image size from its
    centre), tilted 20..40 degrees, whose corners all fall inside."""
    centre = board.object_points().mean(axis=0)
    poses = []
    while len(poses) < views:
        index = len(poses)
        angle = 2 * np.pi * (index + rng.uniform()) / views
        tilt = np.radians(rng.uniform(20, 40))
        R = cv2.Rodrigues(np.array([tilt * np.cos(angle), tilt * np.sin(angle), rng.uniform(-0.3, 0.3)]))[0]
        z = depth[0] + (depth[1] - depth[0]) * (index + rng.uniform()) / views
        reach = spread * z * np.array(size) / K[0, 0]
        t = np.array([rng.uniform(-1, 1) * reach[0], rng.uniform(-1, 1) * reach[1], z]) - R @ centre
        corners = cv2.projectPoints(board.object_points(), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
        if corners.min() >= margin and np.all(corners.max(axis=0) <= np.array(size) - margin):
            poses.append((R, t))
    return poses


def thermal_views(seed: int, views: int = 16, spread: float = 0.25) -> list[np.ndarray]:
    """Detected corners of ``views`` rendered hollow-board views (views the detector misses are replaced)."""
    rng = np.random.default_rng(seed)
    points = []
    while len(points) < views:
        for R, t in _poses(rng, BOARD, K, DIST, SIZE, views - len(points), (300.0, 600.0), spread=spread):
            image = render_board(BOARD, K, DIST, R, t, SIZE, modality="infrared", blur_sigma=1.0, noise_sigma=2.0,
                                 rng=rng)
            detection = detect_board(image, BOARD)
            if detection is not None:
                points.append(detection.image_points)
    return points


def rich_views(seed: int, views: int = 40, noise_px: float = 0.05) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = _poses(rng, RICH_BOARD, RICH_K, RICH_DIST, RICH_SIZE, views, (250.0, 600.0))
    return [cv2.projectPoints(RICH_BOARD.object_points(), cv2.Rodrigues(R)[0], t, RICH_K, RICH_DIST)[0].reshape(-1, 2)
            + rng.normal(0.0, noise_px, (len(RICH_BOARD.object_points()), 2)) for R, t in poses]


def intrinsic_errors(K_estimated: np.ndarray, K_true: np.ndarray = K) -> tuple[float, float]:
    """Largest relative focal length error and largest principal point error (px)."""
    focal = float(np.abs(np.diag(K_estimated)[:2] / np.diag(K_true)[:2] - 1).max())
    return focal, float(np.abs(K_estimated[:2, 2] - K_true[:2, 2]).max())


def stock_opencv(points: list[np.ndarray], board=BOARD, size=SIZE) -> np.ndarray:
    objects = [board.object_points().astype(np.float32)] * len(points)
    _, K_estimated, _, _, _ = cv2.calibrateCamera(objects, [p.astype(np.float32) for p in points], size, None, None)
    return K_estimated


SPREADS = {"spread over the image": 0.25, "bunched near the image centre": 0.08}


def main() -> None:
    summaries = []
    for scenario, spread in SPREADS.items():
        rows = {"stock OpenCV, 5 coefficients": [], "chosen by the data (BIC)": []}
        chosen = Counter()
        print(f"Views {scenario}:")
        print()
        print("| seed | stock OpenCV f error | c error (px) | chosen model | f error | c error (px) | why |")
        print("|---|---|---|---|---|---|---|")
        for seed in range(10):
            points = thermal_views(seed, spread=spread)
            stock = intrinsic_errors(stock_opencv(points))
            result = calibrate_camera([BOARD.object_points()] * len(points), points, SIZE, "auto")
            ours = intrinsic_errors(result.K)
            rows["stock OpenCV, 5 coefficients"].append(stock)
            rows["chosen by the data (BIC)"].append(ours)
            chosen[result.distortion_model] += 1
            print(f"| {seed} | {100 * stock[0]:.3f} % | {stock[1]:.3f} | {result.distortion_model} "
                  f"| {100 * ours[0]:.3f} % | {ours[1]:.3f} | {result.model_selection.reason} |", flush=True)
        print()
        for name, values in rows.items():
            focal, principal = np.array(values).T
            summaries.append(f"| {scenario} | {name} | {100 * np.median(focal):.3f} % | {100 * focal.max():.3f} % "
                             f"| {np.median(principal):.3f} | {principal.max():.3f} | "
                             + (", ".join(f"{m} {c}" for m, c in chosen.items()) if "BIC" in name else "5 coefficients")
                             + " |")
    print("| 16 hollow-board views at 320x256, 10 seeds | calibration | focal length error, median | worst "
          "| principal point error, median (px) | worst (px) | lens model |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(summaries))
    print("| target | | <= 0.1 % | | <= 0.5 | | |")
    print()
    print("| rich data: 40 sharp views, 640x480, strong distortion | chosen model | RMS (px) | f error "
          "| c error (px) |")
    print("|---|---|---|---|---|")
    for seed in range(3):
        points = rich_views(seed)
        result = calibrate_camera([RICH_BOARD.object_points()] * len(points), points, RICH_SIZE, "auto")
        focal, principal = intrinsic_errors(result.K, RICH_K)
        bics = ", ".join(f"{fit.model} {fit.bic:.0f}" for fit in result.model_selection.fits)
        print(f"| seed {seed} (BIC: {bics}) | {result.distortion_model} | {result.rms:.4f} | {100 * focal:.4f} % "
              f"| {principal:.3f} |")


if __name__ == "__main__":
    main()

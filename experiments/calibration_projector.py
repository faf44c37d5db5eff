"""Calibrate the paper's rig from simulated board captures, then measure the paper's planes with it.

The true rig is ``presets.paper_rig()`` (projector at the origin, camera at (400, 0, 0) mm rotated
20 degrees, 1024x768 both). As in practice, the camera is calibrated first on its own: 15 views of
a 13x9-corner chessboard (20 mm squares) filling its view (``calibrate_camera``, k1 k2 model). Then
a 9x6-corner chessboard of 18 mm squares is shown in 40 poses across the projector's field at the
measuring depths (430..570 mm, tilts of 35 degrees), lit by the project's default pattern sequence
with both axes coded (camera blur 0.7 px, noise 1.5 grey levels). From these captures:

1. the projector corners, by local homographies of the decoded coordinates (``projector_corners``);
2. the projector intrinsics and camera-projector pose (``calibrate_projector``).

The calibrated rig keeps the camera's true world pose (the world anchor is a separate choice, see
Table 1) and places the projector by the calibrated camera-to-projector transform. Then the paper's
300 x 200 mm plane at depths 430..570 mm is rendered with the true rig and reconstructed with the
calibrated one; errors are distances to the true plane.

Run: .venv/bin/python experiments/calibration_projector.py  (writes docs/figures/calibration/projector.md)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.calibration.camera import calibrate_camera
from services.calibration.corners import detect_board
from services.calibration.projector import calibrate_projector, projector_corners
from services.formats.board import parse_board
from services.geometry.camera import camera_center, project_points
from services.simulation.boards import render_board, render_board_capture
from services.simulation.presets import paper_plane, paper_rig
from services.simulation.render import CameraEffects, ProjectorEffects, render_frames, render_view
from services.simulation.scene import Albedo
from services.structured_light.decode import decode
from services.structured_light.patterns import generate_sequence
from services.structured_light.reconstruct import reconstruct_points

BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 18.0}')
CAMERA_BOARD = parse_board('{"type": "chessboard", "inner_corners": [13, 9], "square_mm": 20.0}')
POSES = 40
DEPTHS_MM = list(range(430, 571, 20))
OUT = Path(__file__).parents[1] / "docs" / "figures" / "calibration" / "projector.md"


def _turning_tilts(count: int, tilt_deg: float) -> list[np.ndarray]:
    """Rotations tilted by ``tilt_deg`` about axes turning around the view direction."""
    angles = 2 * np.pi * np.arange(count) / count
    tilt = np.radians(tilt_deg)
    return [cv2.Rodrigues(np.array([tilt * np.cos(a), tilt * np.sin(a), 0.15 * np.sin(2 * a)]))[0] for a in angles]


def projector_board_poses() -> list[tuple[np.ndarray, np.ndarray]]:
    """World-from-board poses across the projector's field at the measuring depths (430..570 mm)."""
    angles = 2 * np.pi * np.arange(POSES) / POSES
    centres = np.column_stack([22 + 30 * np.cos(3 * angles), 20 * np.sin(2 * angles), 500 + 70 * np.cos(5 * angles)])
    middle = BOARD.object_points().mean(axis=0)
    return [(R, centre - R @ middle) for R, centre in zip(_turning_tilts(POSES, 35.0), centres)]


def camera_board_poses(camera_R: np.ndarray, camera_centre: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-from-board poses of a larger board filling the camera's view, for its own calibration."""
    angles = 2 * np.pi * np.arange(15) / 15
    middle = CAMERA_BOARD.object_points().mean(axis=0)
    poses = []
    for angle, facing_camera in zip(angles, _turning_tilts(15, 35.0)):
        offset = np.array([40 * np.cos(2 * angle), 30 * np.sin(2 * angle), 420 + 60 * np.cos(3 * angle)])
        R = camera_R.T @ facing_camera
        poses.append((R, camera_centre + camera_R.T @ offset - R @ middle))
    return poses


def main() -> None:
    rig = paper_rig()
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    R_c, t_c = camera.R, camera.t
    projector_from_camera = projector.replace(**{"R": (projector.R @ R_c.T).tolist(),
                                                         "t": (projector.t - projector.R @ R_c.T @ t_c).tolist()})
    rng = np.random.default_rng(12)
    camera_views = []
    for R_wb, t_wb in camera_board_poses(R_c, camera_center(R_c, t_c)):
        image = render_board(CAMERA_BOARD, camera.K, camera.dist, R_c @ R_wb, R_c @ t_wb + t_c,
                             camera.size, blur_sigma=0.7, noise_sigma=1.5, rng=rng)
        camera_views.append(detect_board(image, CAMERA_BOARD).image_points)
    camera_cal = calibrate_camera([CAMERA_BOARD.object_points()] * len(camera_views), camera_views, camera.size,
                                  distortion="radial")
    sequence, patterns = generate_sequence(projector.width, projector.height, axes="xy")
    detections, corner_errors = [], []
    for R_wb, t_wb in projector_board_poses():
        R, t = R_c @ R_wb, R_c @ t_wb + t_c
        frames = render_board_capture(BOARD, camera.K, camera.dist, R, t, camera.size,
                                      projector_from_camera, patterns, blur_sigma=0.7, noise_sigma=1.5, rng=rng)
        decoded = decode(frames, sequence)
        lit = np.clip(np.round(decoded.intensity), 0, 255).astype(np.uint8)
        detection = detect_board(lit, BOARD)
        if detection is None:
            continue
        spacing = np.median(np.linalg.norm(np.diff(detection.image_points.reshape(6, 9, 2), axis=1), axis=2))
        corners, found = projector_corners(detection.image_points, decoded.projector_x, decoded.projector_y,
                                           int(spacing / 2), decoded.modulation)
        if found.sum() < 6:
            continue
        truth = project_points(BOARD.object_points() @ R_wb.T + t_wb, projector.K, projector.dist,
                               projector.R, projector.t)
        corner_errors.append(np.linalg.norm(corners[found] - truth[found], axis=1))
        detections.append((detection.image_points[found], corners[found], BOARD.object_points()[found]))
    objects = [d[2] for d in detections]
    result = calibrate_projector(objects, [d[0] for d in detections], [d[1] for d in detections],
                                 (camera_cal.K, camera_cal.dist), camera.size, projector.size)
    R_pc, t_pc = result.stereo.R, result.stereo.t
    calibrated_camera = camera.replace(**{"K": camera_cal.K.tolist(), "dist": camera_cal.dist.tolist()})
    calibrated_projector = projector.replace(**{
        "K": result.projector.K.tolist(), "dist": result.projector.dist.tolist(),
        "R": (R_pc @ R_c).tolist(), "t": (R_pc @ t_c + t_pc).tolist()})
    true_R_pc = np.asarray(projector_from_camera.R)
    true_t_pc = np.asarray(projector_from_camera.t)
    lines = [
        f"Camera: RMS {camera_cal.rms:.3f} px over 15 views. Board captures: {len(detections)} of {POSES} poses "
        "found; projector corners from local homographies: RMS error "
        f"{np.sqrt(np.mean(np.concatenate(corner_errors) ** 2)):.3f} px, max {np.concatenate(corner_errors).max():.3f} px "
        "(against the simulator's truth).",
        "",
        "| quantity | true | calibrated | error |",
        "|---|---|---|---|",
        f"| camera f_x (px) | {camera.K[0, 0]:.3f} | {camera_cal.K[0, 0]:.3f} | "
        f"{100 * abs(camera_cal.K[0, 0] / camera.K[0, 0] - 1):.4f}% |",
        f"| projector f_x (px) | {projector.K[0, 0]:.3f} | {result.projector.K[0, 0]:.3f} | "
        f"{100 * abs(result.projector.K[0, 0] / projector.K[0, 0] - 1):.4f}% |",
        f"| projector f_y (px) | {projector.K[1, 1]:.3f} | {result.projector.K[1, 1]:.3f} | "
        f"{100 * abs(result.projector.K[1, 1] / projector.K[1, 1] - 1):.4f}% |",
        f"| projector c_x, c_y (px) | {projector.K[0, 2]:.2f}, {projector.K[1, 2]:.2f} | "
        f"{result.projector.K[0, 2]:.2f}, {result.projector.K[1, 2]:.2f} | "
        f"{np.abs(result.projector.K[:2, 2] - projector.K[:2, 2]).max():.3f} px |",
        f"| camera-projector rotation | | | "
        f"{np.degrees(np.linalg.norm(cv2.Rodrigues(R_pc @ true_R_pc.T)[0])):.4f} deg |",
        f"| camera-projector translation (mm) | {np.array2string(true_t_pc, precision=2)} | "
        f"{np.array2string(t_pc, precision=2)} | {np.linalg.norm(t_pc - true_t_pc):.3f} mm |",
        f"| projector RMS (px) | | {result.projector.rms:.3f} | target <= 0.3 |",
        f"| stereo RMS (px) | | {result.stereo.rms:.3f} | |",
        "",
        "Paper plane (300 x 200 mm) reconstructed with the calibrated rig and with the true rig:",
        "",
        "| depth (mm) | mean error, calibrated rig (mm) | max error, calibrated rig (mm) | "
        "mean error, true rig (mm) | max error, true rig (mm) |",
        "|---|---|---|---|---|",
    ]
    camera_effects = CameraEffects(exposure=0.8, blur_sigma=0.7, noise_sigma=1.5)
    projector_effects = ProjectorEffects(gamma=2.2, blur_sigma=0.8, black_level=0.02)
    plain_sequence, plain_patterns = generate_sequence(projector.width, projector.height)
    for depth in DEPTHS_MM:
        scene = paper_plane(float(depth), Albedo(base=0.7, texture_amplitude=0.15, feature_size=30.0, seed=3))
        view = render_view(scene, camera, projector, supersample=3)
        frames = render_frames(view, plain_patterns, np.random.default_rng(depth), camera_effects, projector_effects)
        row = [str(depth)]
        for cam, proj in ((calibrated_camera, calibrated_projector), (camera, projector)):
            cloud = reconstruct_points(frames, plain_sequence, cam, proj)
            errors = np.abs(cloud["z"].astype(np.float64) - depth)
            row += [f"{errors.mean():.4f}", f"{errors.max():.4f}"]
        lines.append("| " + " | ".join(row) + " |")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

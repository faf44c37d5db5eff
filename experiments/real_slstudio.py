"""Every table and picture of docs/real-data.md: SLStudio's real rig calibrated with our commands.

Runs ``thermofield calibrate camera`` and ``calibrate projector`` on SLStudio's six calibration
sequences (all six, then SLStudio's five), imports SLStudio's own calibration.xml with
``thermofield rig import``, compares the calibrations (parameters with their standard deviations, and
the displacement of reconstructed 3D points at 390 mm), reconstructs skull_2x3 with both rigs and
writes the pictures to docs/figures/real-data/.

    .venv/bin/python experiments/real_slstudio.py [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from services.cli.main import main as thermofield
from services.calibration.corners import detect_board
from services.calibration.projector import projector_corners
from services.formats.board import ChessboardSpec
from services.formats.rig import load_rig
from services.geometry.camera_model import CameraModel
from services.formats.sequence import read_capture
from services.geometry.camera import normalized_coordinates
from services.structured_light.decode import Rejection, decode
from services.structured_light.triangulate import triangulate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "slstudio"
CALIBRATION = DATA / "calibration"
SKULL = DATA / "skull_2x3"
CALIBRATION_MANIFEST = REPO / "experiments" / "slstudio" / "calibration_sequence.json"
SKULL_MANIFEST = REPO / "experiments" / "slstudio" / "skull_sequence.json"
FIGURES = REPO / "docs" / "figures" / "real-data"
BOARD = {"type": "chessboard", "inner_corners": [13, 9], "square_mm": 10.0}
SLSTUDIO_RMS = {"camera": 0.282, "projector": 0.463, "stereo": 0.422}
# The skull's sequence is unwrapped by a 3-step coarse period 16 times the fine one (noisy), and its eye
# sockets and nose inter-reflect: see docs/real-data.md.
SKULL_OPTIONS = ["--consistency", "0.5", "--max-indirect", "0.33"]
DEPTH_MM = 390.0


def calibrate(work: Path, sequences: list[int]) -> dict:
    """Our camera and projector calibration from the given calseq numbers; the files it wrote."""
    work.mkdir(parents=True, exist_ok=True)
    board = work / "board.json"
    board.write_text(json.dumps(BOARD))
    captures = [str(CALIBRATION / f"calseq{n}") for n in sequences]
    common = ["--board", str(board), "--captures", *captures, "--manifest", str(CALIBRATION_MANIFEST)]
    assert thermofield(["calibrate", "camera", *common, "--out", str(work / "camera.json")]) == 0
    assert thermofield(["calibrate", "projector", *common, "--camera", str(work / "camera.json"),
                        "--out", str(work / "rig.json")]) == 0
    return {"camera": json.loads((work / "camera.json").read_text()),
            "projector": json.loads((work / "rig_projector.json").read_text()),
            "rig": load_rig(work / "rig.json"), "rig_path": work / "rig.json"}


def import_slstudio(work: Path) -> Path:
    out = work / "slstudio_rig.json"
    assert thermofield(["rig", "import", "--format", "slstudio", str(CALIBRATION / "calibration.xml"),
                        "--out", str(out)]) == 0
    return out


def displacement_at_depth(reference: tuple[CameraModel, CameraModel], other: tuple[CameraModel, CameraModel], depth: float = DEPTH_MM,
                          step: int = 8) -> np.ndarray:
    """|X_other - X_reference| (mm) of the points the reference rig puts at ``depth`` on a grid of camera
    pixels, when the same camera pixel and decoded projector column are triangulated with the other rig."""
    (camera, projector), (camera_2, projector_2) = reference, other
    u, v = np.meshgrid(np.arange(0, camera.width, step), np.arange(0, camera.height, step))
    pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    rays = normalized_coordinates(pixels, camera.K, camera.dist)
    points_camera = np.column_stack([rays * depth, np.full(len(rays), depth)])
    points = (points_camera - camera.t) @ camera.R  # camera frame to world
    columns = projector.project(points)
    inside = (columns[:, 0] >= 0) & (columns[:, 0] <= projector.width - 1) & (columns[:, 1] >= 0) & \
        (columns[:, 1] <= projector.height - 1)
    rays_2 = normalized_coordinates(pixels[inside], camera_2.K, camera_2.dist)
    moved = triangulate(rays_2, columns[inside, 0], "x", camera_2.R, camera_2.t, projector_2.K,
                        projector_2.dist, projector_2.R, projector_2.t)
    return np.linalg.norm(moved - points[inside], axis=1)


def board_corners(sequences: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per calseq: the board's detected camera corners, their decoded projector column and the board grid (mm),
    as ``thermofield calibrate projector`` measures them."""
    board = ChessboardSpec(**BOARD)
    corners = {}
    for n in sequences:
        sequence, frames = read_capture(CALIBRATION / f"calseq{n}", CALIBRATION_MANIFEST)
        decoded = decode(frames, sequence, edge_margin=0)
        detection = detect_board(np.clip(np.round(decoded.intensity), 0, 255).astype(np.uint8), board)
        spacing = np.median(np.linalg.norm(np.diff(detection.image_points.reshape(9, 13, 2), axis=1), axis=-1))
        projector, found = projector_corners(detection.image_points, decoded.projector_x, decoded.projector_y,
                                             max(2, int(0.5 * spacing)), decoded.modulation)
        corners[n] = (detection.image_points[found], projector[found, 0], board.object_points()[detection.ids[found]])
    return corners


def board_geometry_errors(rig: tuple[CameraModel, CameraModel], corners: tuple[np.ndarray, np.ndarray, np.ndarray]
                          ) -> tuple[float, float]:
    """Triangulate the board corners with a rig and fit the true board by a similarity: the RMS distance (mm)
    of the corners from the fitted board, and the fitted scale minus one (the rig's length error)."""
    camera, projector = rig
    pixels, columns, grid = corners
    rays = normalized_coordinates(pixels, camera.K, camera.dist)
    points = triangulate(rays, columns, "x", camera.R, camera.t, projector.K, projector.dist,
                         projector.R, projector.t).astype(np.float64)
    measured, truth = points - points.mean(axis=0), grid - grid.mean(axis=0)
    u, singular, vt = np.linalg.svd(truth.T @ measured)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = (u @ flip @ vt).T
    scale = float(np.sum(singular * np.diag(flip)) / np.sum(truth ** 2))
    residual = measured - scale * truth @ rotation.T
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1)))), scale - 1.0


def devices(rig) -> tuple[CameraModel, CameraModel]:
    return rig.device(None, "camera")[1], rig.device(None, "projector")[1]


def reconstruct_skull(rig_path: Path, out: Path) -> dict[str, np.ndarray]:
    assert thermofield(["reconstruct", "--rig", str(rig_path), "--captures", str(SKULL), "--manifest",
                        str(SKULL_MANIFEST), "--out", str(out), *SKULL_OPTIONS]) == 0
    from plyfile import PlyData
    vertices = PlyData.read(str(out))["vertex"]
    return {name: np.asarray(vertices[name]) for name in ("x", "y", "z", "nx", "ny", "nz", "u", "v")}


def cloud_maps(cloud: dict[str, np.ndarray], shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The cloud as (H, W, 3) point and normal maps, NaN where there is no point."""
    points, normals = np.full(shape + (3,), np.nan), np.full(shape + (3,), np.nan)
    u, v = np.round(cloud["u"]).astype(int), np.round(cloud["v"]).astype(int)
    points[v, u] = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
    normals[v, u] = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]])
    return points, normals


def shaded_picture(points: np.ndarray, normals: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """Lambertian shading of the cloud seen from the camera (light at the camera); points whose normal is
    undefined (a missing neighbour) in dark grey, no point in black."""
    to_camera = -points / np.linalg.norm(points, axis=2, keepdims=True)
    shade = np.clip(np.sum(normals * to_camera, axis=2), 0, 1)
    picture = np.zeros(points.shape[:2], np.uint8)
    has_point = np.isfinite(points[..., 2])
    picture[has_point] = 70
    lit = has_point & np.isfinite(shade)
    picture[lit] = (40 + 215 * shade[lit]).astype(np.uint8)
    return picture[box]


def rejection_picture(rejection: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    colours = {Rejection.VALID: (200, 200, 200), Rejection.DARK: (0, 0, 0), Rejection.SATURATED: (255, 0, 255),
               Rejection.LOW_MODULATION: (255, 0, 0), Rejection.POOR_FIT: (0, 255, 255),
               Rejection.INCONSISTENT: (0, 0, 255), Rejection.EDGE: (0, 255, 0), Rejection.INDIRECT: (0, 165, 255)}
    picture = np.zeros(rejection.shape + (3,), np.uint8)
    for code, colour in colours.items():
        picture[rejection == code] = colour
    return picture[box]


def _markdown(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def _value(mean: float, std: float | None, digits: int) -> str:
    if std is None:
        return f"{mean:.{digits}f} (fixed)"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def parameter_table(ours: dict, slstudio) -> str:
    camera, projector = ours["camera"], ours["projector"]
    sl_camera, sl_projector = devices(slstudio)
    rows = []
    for label, K, dist, std, sl in (("camera", camera["K"], camera["dist"], camera["std"], sl_camera),
                                    ("projector", ours["rig"].devices["projector"].K,
                                     ours["rig"].devices["projector"].dist, projector["std"], sl_projector)):
        values = {"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]}
        values.update(zip(("k1", "k2", "p1", "p2", "k3"), dist))
        sl_values = {"fx": sl.K[0][0], "fy": sl.K[1][1], "cx": sl.K[0][2], "cy": sl.K[1][2]}
        sl_values.update(zip(("k1", "k2", "p1", "p2", "k3"), sl.dist))
        for name, value in values.items():
            digits = 2 if name in ("fx", "fy", "cx", "cy") else 4
            rows.append([label, name, _value(value, std.get(name), digits), f"{sl_values[name]:.{digits}f}"])
    projector_device = ours["rig"].devices["projector"]
    rvec = cv2.Rodrigues(projector_device.R)[0].ravel()
    sl_rvec = cv2.Rodrigues(sl_projector.R)[0].ravel()
    stereo_std = projector["stereo_std"]
    for i, axis in enumerate("xyz"):
        rows.append(["camera to projector", f"r{axis} (rad)", _value(rvec[i], stereo_std[f"r{axis}"], 5),
                     f"{sl_rvec[i]:.5f}"])
    for i, axis in enumerate("xyz"):
        rows.append(["camera to projector", f"t{axis} (mm)", _value(projector_device.t[i], stereo_std[f"t{axis}"], 3),
                     f"{sl_projector.t[i]:.3f}"])
    return _markdown(["device", "parameter", "ours (± 1 sigma)", "SLStudio"], rows)


def per_view_table(ours: dict) -> str:
    camera = {Path(view["image"]).name: view["rms_px"] for view in ours["camera"]["views"]}
    projector = ours["projector"]
    rows = []
    for index, name in enumerate(Path(view).name for view in projector["views"]):
        stereo = projector["stereo_per_view_rms_px"][index]
        rows.append([name, f"{camera[name]:.3f}", f"{projector['per_view_rms_px'][index]:.3f}",
                     f"{stereo[0]:.3f} / {stereo[1]:.3f}"])
    return _markdown(["sequence", "camera RMS (px)", "projector RMS (px)", "stereo RMS camera / projector (px)"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=None, help="directory for the calibration files (default: temporary)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="real_slstudio_"))
    FIGURES.mkdir(parents=True, exist_ok=True)
    slstudio_path = import_slstudio(work)
    slstudio = load_rig(slstudio_path)
    runs = {"all six": calibrate(work / "six", [1, 2, 3, 4, 5, 6]),
            "SLStudio's five": calibrate(work / "five", [1, 3, 4, 5, 6])}

    print("## RMS against SLStudio's\n")
    rows = []
    for label, run in runs.items():
        rows.append([f"ours, {label}", f"{run['camera']['rms_px']:.3f}", f"{run['projector']['projector_rms_px']:.3f}",
                     f"{run['projector']['stereo_rms_px']:.3f}",
                     ", ".join(Path(r["image"]).name for r in run["camera"]["rejected"] + run["projector"]["rejected"])
                     or "none"])
    rows.append(["SLStudio (1, 3, 4, 5, 6)", SLSTUDIO_RMS["camera"], SLSTUDIO_RMS["projector"], SLSTUDIO_RMS["stereo"],
                 "2 (by hand)"])
    print(_markdown(["calibration", "camera RMS (px)", "projector RMS (px)", "stereo RMS (px)", "rejected"], rows))
    for label, run in runs.items():
        print(f"\n## Per view, {label}\n")
        print(per_view_table(run))
        print(f"\n## Parameters, {label}\n")
        print(parameter_table(run, slstudio))
        for rejected in run["camera"]["rejected"] + run["projector"]["rejected"]:
            print(f"\nrejected {rejected['image']}: {rejected['reason']}")

    print(f"\n## Displacement of 3D points at {DEPTH_MM:.0f} mm\n")
    six, five = devices(runs["all six"]["rig"]), devices(runs["SLStudio's five"]["rig"])
    rows = []
    for label, reference, other in (("ours (six) vs SLStudio", six, devices(slstudio)),
                                    ("ours (five) vs SLStudio", five, devices(slstudio)),
                                    ("ours (five) vs ours (six): sequence 2's effect", five, six)):
        shift = displacement_at_depth(reference, other)
        rows.append([label, f"{np.median(shift):.3f}", f"{np.percentile(shift, 95):.3f}", f"{shift.max():.3f}"])
    print(_markdown(["calibrations", "median (mm)", "95th percentile (mm)", "max (mm)"], rows))

    print("\n## The board, triangulated with each calibration (13x9 corners, 10 mm)\n")
    corners = board_corners([1, 2, 3, 4, 5, 6])
    rigs = {"ours (six)": six, "ours (five)": five, "SLStudio": devices(slstudio)}
    rows = []
    for n, seen in corners.items():
        row = [f"calseq{n}"]
        for rig in rigs.values():
            rms, scale = board_geometry_errors(rig, seen)
            row.append(f"{rms:.3f} mm, {100 * scale:+.2f} %")
        rows.append(row)
    print(_markdown(["sequence", *[f"{label}: RMS from the board, scale error" for label in rigs]], rows))

    for label, run in runs.items():
        window = run["camera"]["corner_window"]
        print(f"\n## The corner window, chosen by cross-validation ({label})\n")
        print(_markdown(["half window / corner spacing", "held-out RMS (px)"],
                        [[f"{c['fraction']:.3f}", f"{c['held_out_rms_px']:.3f}"] for c in window["candidates"]]))
        print(f"\nchosen: {window['reason']}")

    print("\n## skull_2x3\n")
    sequence, frames = read_capture(SKULL, SKULL_MANIFEST)
    shape = frames.shape[1:]
    clouds = {"ours": reconstruct_skull(runs["all six"]["rig_path"], work / "skull_ours.ply"),
              "SLStudio's": reconstruct_skull(slstudio_path, work / "skull_slstudio.ply")}
    maps = {label: cloud_maps(cloud, shape) for label, cloud in clouds.items()}
    any_point = np.zeros(shape, bool)
    for points, _ in maps.values():
        any_point |= np.isfinite(points[..., 2])
    rows_, cols_ = np.nonzero(any_point)
    box = (slice(max(0, rows_.min() - 20), rows_.max() + 20), slice(max(0, cols_.min() - 20), cols_.max() + 20))
    (ours_points, _), (sl_points, _) = maps["ours"], maps["SLStudio's"]
    both = np.isfinite(ours_points[..., 2]) & np.isfinite(sl_points[..., 2])
    same_pixel = np.linalg.norm(ours_points[both] - sl_points[both], axis=1)
    nearest = cKDTree(np.column_stack([clouds["SLStudio's"][c] for c in "xyz"])).query(
        np.column_stack([clouds["ours"][c] for c in "xyz"]))[0]
    lit = decode(frames, sequence, edge_margin=0).rejection != Rejection.DARK
    rows = []
    for label, cloud in clouds.items():
        count = len(cloud["x"])
        rows.append([label, count, f"{count / frames[0].size:.1%}", f"{count / lit.sum():.1%}",
                     f"{np.median(cloud['z']):.1f}"])
    print(_markdown(["calibration", "points", "of the image", "of the lit pixels", "median depth (mm)"], rows))
    print(f"\nsame camera pixel in both clouds: {both.sum()} pixels, distance median {np.median(same_pixel):.3f} mm, "
          f"95th percentile {np.percentile(same_pixel, 95):.3f} mm; nearest neighbour (ours to SLStudio's): median "
          f"{np.median(nearest):.3f} mm")
    for label, (points, normals) in maps.items():
        name = "ours" if label == "ours" else "slstudio"
        cv2.imwrite(str(FIGURES / f"skull_{name}.png"), shaded_picture(points, normals, box))
    distance = np.full(shape, np.nan)
    distance[both] = same_pixel
    scaled = np.clip(distance / 5.0 * 255, 0, 255)  # 0 (dark blue) .. 5 mm (yellow)
    coloured = cv2.applyColorMap(np.nan_to_num(scaled).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    coloured[~both] = 0
    cv2.imwrite(str(FIGURES / "skull_distance.png"), coloured[box])
    rejection = decode(frames, sequence, edge_margin=0, min_quality=0.3, min_modulation=1.02, consistency=0.5,
                       max_indirect=0.33).rejection
    cv2.imwrite(str(FIGURES / "skull_rejection.png"), rejection_picture(rejection, box))
    counts = np.bincount(rejection[box].ravel(), minlength=len(Rejection))
    print("\nrejection codes in the picture's box: " + ", ".join(f"{Rejection(code).name} {n}"
                                                               for code, n in enumerate(counts) if n))
    print(f"\nfigures in {FIGURES}; calibration files in {work}")


if __name__ == "__main__":
    main()

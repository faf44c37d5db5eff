"""Station calibration on random simulated stations: each head's pose error against the simulator's truth, and how
often the reported sigma covers it.

Run (reporting seeds; a run split over processes is summarised with ``--summarise ROWS.json ...``)::

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/station_calibration.py --projected --seeds 200-229
    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/station_calibration.py --seeds 200-202
    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/station_calibration.py --detector-error 100

Seeds. TUNING (used to choose the views, the board, the lens model and the intrinsics mode, and to find what limits
the head positions; never reported): 100-119. REPORTING: 200-229.

Each station (``services.simulation.station_boards.ring_station_rig(rng)``): four heads around a horizontal axis at
600 mm (each turned up to 5 degrees, at 0.92..1.08 of the radius, its camera 1280x800 with f 1400 px within 5 %,
principal point within 2 %, random k1, k2), camera and projector 250 mm apart. The board: a 17x10 chessboard of
20 mm squares (``BOARD``), in ``--shared`` poses (default 30) per pair of neighbouring heads and ``--own`` poses
(default 50) per camera alone (``station_board_poses``). Each head's camera is first calibrated alone on the views
only it sees, as ``thermofield calibrate camera --distortion auto`` does (``calibrate_camera``, the lens model of
lowest BIC: here k1, k2); then ``calibrate_station`` (the use case of ``thermofield calibrate station``) refines
every pose, board view and intrinsic together (the focal lengths, the principal point and the coefficients of that
model), the first head's camera fixing the world frame at its true pose. A head's pose error is the rotation from
the truth (degrees) and the distance of its camera's centre from the true one (mm); a sigma covers its error when
|error| <= 1.645 sigma (the two-sided 90 % interval), per degree of freedom.

Rendered views (``station_board_views``: blur 0.7 px, noise 1.5 grey levels, one sample per pixel; 440 images per
station) cost about 6 minutes of CPU per station. ``--projected`` skips the rendering: the same views' corners are
the true projections plus Gaussian noise of ``--noise`` px per coordinate (default 0.03 px) and a shift of
``--shift`` px shared by all corners of one camera's view (default 0.02 px), adjusted by ``adjust_station`` with
the same choices as ``calibrate_station``. ``--detector-error SEED`` measures the detector on rendered views of one
station (3 poses per pair, 3 per camera): on seed 100 the corners' error about their view's mean is 0.027 px RMS per
coordinate and the views' mean error 0.002 px RMS, so the projected mode's 0.03 px is the detector's and its
0.02 px shift an allowance for a real board's errors shared by a view (print, flatness, lighting) that the
rendering does not have.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from services.calibration.camera import INTRINSIC_NAMES, calibrate_camera
from services.calibration.corners import detect_board
from services.calibration.station import POSE_NAMES, BoardObservation, adjust_station, pose_difference
from services.formats.board import ChessboardSpec
from services.pipeline.calibrate import calibrate_station
from services.simulation.station_boards import (
    ring_station_rig, station_board_poses, station_board_views,
)

Z90 = 1.6448536269514722
BOARD = ChessboardSpec(type="chessboard", inner_corners=(17, 10), square_mm=20.0)
DISTORTION = "auto"  # each head's camera calibrated alone as `thermofield calibrate camera --distortion auto`


def seeds(text: str) -> list[int]:
    values = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        values.extend(range(int(low), int(high or low) + 1))
    return values


def station_rows(seed: int, shared: int, own: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    truth = ring_station_rig(rng)
    started = time.perf_counter()
    views = station_board_views(truth, BOARD, rng, shared=shared, own=own, supersample=1)
    rendered = time.perf_counter()
    start = dict(truth.devices)
    heads = truth.heads
    for head in heads:  # each head's camera calibrated alone first, on the views only it sees
        camera = truth.devices[head.camera]
        alone = [v for v, image in views.images[head.camera].items()
                 if not any(v in views.images[other.camera] for other in heads if other != head)]
        detections = [d for d in (detect_board(views.images[head.camera][v], BOARD) for v in alone) if d is not None]
        result = calibrate_camera([BOARD.object_points()[d.ids] for d in detections],
                                  [d.image_points for d in detections], camera.size, DISTORTION, jackknife=False)
        start[head.camera] = camera.replace(K=result.K, dist=result.dist)
    start_rig = type(truth)(start, truth.units, truth.station_heads)
    labelled = {head.name: [(f"view{v:03d}.png", image) for v, image in sorted(views.images[head.camera].items())]
                for head in heads}
    outcome = calibrate_station(board=BOARD, rig=start_rig, views=labelled, source=f"station {seed}")
    finished = time.perf_counter()
    report = {record.device: record for record in outcome.report.devices}
    rows = []
    for head in heads[1:]:
        true, estimate = truth.devices[head.camera], outcome.rig.devices[head.camera]
        error = pose_difference(true.R, true.t, estimate.R, estimate.t)
        record = report[head.camera]
        rows.append({"seed": seed, "head": head.name, "error": error.tolist(),
                     "rotation_deg": float(np.linalg.norm(error[:3])), "position_mm": float(np.linalg.norm(error[3:])),
                     "sigma": [record.pose_std[n] for n in POSE_NAMES],
                     "sigma_jacobian": [record.pose_std_jacobian[n] for n in POSE_NAMES],
                     "sigma_jackknife": [record.pose_std_jackknife[n] for n in POSE_NAMES],
                     "overlap_rms_px": outcome.report.overlap_rms_px, "overlap_rms_mm": outcome.report.overlap_rms_mm,
                     "views": len(outcome.report.views), "unseen": len(outcome.report.unseen),
                     "render_s": rendered - started, "calibrate_s": finished - rendered})
    return rows


def projected_rows(seed: int, shared: int, own: int, noise: float, shift: float) -> list[dict]:
    """As :func:`station_rows`, the corners projected with noise instead of rendered and detected."""
    rng = np.random.default_rng(seed)
    truth = ring_station_rig(rng)
    started = time.perf_counter()
    cameras = [truth.devices[head.camera] for head in truth.heads]
    poses, seen = station_board_poses(cameras, BOARD, rng, shared, own)
    X, observations = BOARD.object_points(), []
    for view, ((R, t), which) in enumerate(zip(poses, seen)):
        for index in which:
            pixels = cameras[index].project(X @ R.T + t)
            pixels = pixels + rng.normal(0, noise, pixels.shape) + rng.normal(0, shift, 2)
            observations.append(BoardObservation(index, view, X, pixels))
    start = []
    for index, camera in enumerate(cameras):
        alone = [o for o, which in zip(observations, [seen[o.view] for o in observations])
                 if o.camera == index and len(which) == 1]
        result = calibrate_camera([o.object_points for o in alone], [o.image_points for o in alone], camera.size,
                                  DISTORTION, jackknife=False)
        start.append((result.K, result.dist))
    refined = [INTRINSIC_NAMES[:4] + tuple(INTRINSIC_NAMES[4 + i] for i in np.flatnonzero(dist)) for _, dist in start]
    bundle = adjust_station(observations, start, reference_pose=(cameras[0].R, cameras[0].t),
                            refined_intrinsics=refined)
    finished = time.perf_counter()
    rows = []
    for index, head in list(enumerate(truth.heads))[1:]:
        error = pose_difference(cameras[index].R, cameras[index].t, bundle.rotations[index],
                                bundle.translations[index])
        rows.append({"seed": seed, "head": head.name, "error": error.tolist(),
                     "rotation_deg": float(np.linalg.norm(error[:3])), "position_mm": float(np.linalg.norm(error[3:])),
                     "sigma": bundle.pose_std[index].tolist(), "sigma_jacobian": bundle.pose_std_jacobian[index].tolist(),
                     "sigma_jackknife": bundle.pose_std_jackknife[index].tolist(),
                     "overlap_rms_px": bundle.overlap_rms_px, "overlap_rms_mm": bundle.overlap_rms_mm,
                     "views": len(poses), "unseen": 0, "render_s": 0.0, "calibrate_s": finished - started})
    return rows


def detector_error(seed: int) -> str:
    """The detector's corner error on rendered views of one station: about each view's mean, and the views' means."""
    rng = np.random.default_rng(seed)
    truth = ring_station_rig(rng)
    views = station_board_views(truth, BOARD, rng, shared=3, own=3, supersample=1)
    spread, means = [], []
    for head in truth.heads:
        camera = truth.devices[head.camera]
        for view, image in views.images[head.camera].items():
            detection = detect_board(image, BOARD)
            if detection is None:
                continue
            R, t = views.poses[view]
            error = detection.image_points - camera.project(BOARD.object_points()[detection.ids] @ R.T + t)
            means.append(error.mean(axis=0))
            spread.append(error - means[-1])
    return (f"seed {seed}, {len(means)} rendered views of a {BOARD.inner_corners[0]}x{BOARD.inner_corners[1]} board "
            f"of {BOARD.square_mm:g} mm squares: corner error about the view's mean "
            f"{np.sqrt(np.mean(np.concatenate(spread) ** 2)):.4f} px RMS per coordinate, views' mean error "
            f"{np.sqrt(np.mean(np.square(means))):.4f} px RMS")


def summary(rows: list[dict]) -> str:
    def line(name, values, unit, digits):
        values = np.asarray(values)
        return (f"| {name} | {np.median(values):.{digits}f} {unit} | {np.percentile(values, 95):.{digits}f} {unit} | "
                f"{values.max():.{digits}f} {unit} |")

    stations = sorted({row["seed"] for row in rows})
    seen = sorted({row["seed"] for row in rows})
    lines = [f"| {len(stations)} simulated stations (seeds {seen[0]}-{seen[-1]}), {len(rows)} heads placed "
             "| median | 95th percentile | worst |", "|---|---|---|---|",
             line("head rotation error", [r["rotation_deg"] for r in rows], "deg", 4),
             line("head position error (camera centre)", [r["position_mm"] for r in rows], "mm", 3),
             line("reported sigma, rotation (per axis)", [s for r in rows for s in r["sigma"][:3]], "deg", 4),
             line("reported sigma, position (per axis)", [s for r in rows for s in r["sigma"][3:]], "mm", 3),
             line("overlap residual", [r["overlap_rms_px"] for r in rows[::3]], "px", 3),
             line("overlap residual on the board", [r["overlap_rms_mm"] for r in rows[::3]], "mm", 4), ""]
    error = np.array([r["error"] for r in rows])
    lines += ["| sigma coverage at 90 % (share of \\|error\\| <= 1.645 sigma) | reported | Jacobian | jackknife |",
              "|---|---|---|---|"]
    for label, columns in (("rotation (rx, ry, rz)", slice(0, 3)), ("position (x, y, z)", slice(3, 6)),
                           ("all six", slice(0, 6))):
        shares = []
        for key in ("sigma", "sigma_jacobian", "sigma_jackknife"):
            sigma = np.array([r[key] for r in rows])
            shares.append(100 * np.mean(np.abs(error[:, columns]) <= Z90 * sigma[:, columns]))
        lines.append(f"| {label} | {shares[0]:.1f} % | {shares[1]:.1f} % | {shares[2]:.1f} % |")
    render = np.median([r["render_s"] for r in rows])
    calibrate = np.median([r["calibrate_s"] for r in rows])
    lines.append(f"\nmedian per station: rendering {render:.0f} s, calibration (detection, adjustment, jackknife) "
                 f"{calibrate:.0f} s; views per station: {int(np.median([r['views'] for r in rows]))}, "
                 f"images without a board found: {sum(r['unseen'] for r in rows[::3])}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=seeds, default=[], help="e.g. 200-209")
    parser.add_argument("--shared", type=int, default=30, help="board poses per pair of neighbouring heads")
    parser.add_argument("--own", type=int, default=50, help="board poses per camera alone")
    parser.add_argument("--projected", action="store_true",
                        help="corners projected with noise instead of rendered views (see the module docstring)")
    parser.add_argument("--noise", type=float, default=0.03, help="with --projected: corner noise, px")
    parser.add_argument("--shift", type=float, default=0.02, help="with --projected: a view's shared shift, px")
    parser.add_argument("--detector-error", type=int, default=None, metavar="SEED",
                        help="only measure the detector's corner error on rendered views of one station")
    parser.add_argument("--rows-out", type=Path, default=None, help="also save the per-head rows as JSON")
    parser.add_argument("--summarise", type=Path, nargs="+", default=None,
                        help="only print the tables of saved --rows-out files (runs split over processes)")
    args = parser.parse_args()
    if args.detector_error is not None:
        print(detector_error(args.detector_error))
        return
    if args.summarise:
        rows = [row for path in args.summarise for row in json.loads(path.read_text())]
    else:
        rows = []
        for seed in args.seeds:
            rows += (projected_rows(seed, args.shared, args.own, args.noise, args.shift) if args.projected
                     else station_rows(seed, args.shared, args.own))
            print(f"seed {seed}: " + ", ".join(f"{r['head']} {r['rotation_deg']:.4f} deg {r['position_mm']:.3f} mm"
                                               for r in rows[-3:]), flush=True)
            if args.rows_out:
                args.rows_out.write_text(json.dumps(rows, indent=1))
    print(summary(rows))


if __name__ == "__main__":
    main()

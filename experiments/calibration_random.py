"""Calibration over cameras drawn at random: the distribution of the errors of f, the principal point and the
distortion against the simulator's truth, and how often each reported sigma covers its error.

Run (reporting seeds, both populations; the rendered views and detected corners are cached, so a second run
only calibrates; a run split over processes is summarised with ``--summarise ROWS.json ...``)::

    nice -n 10 .venv/bin/python experiments/calibration_random.py --seeds 100-149 --cache /tmp/calib-random
    nice -n 10 .venv/bin/python experiments/calibration_random.py --thermal16 --seeds 1100-1149 --cache /tmp/calib-random

Seeds. TUNING (used to choose the sigma rule, the board-frame corners and the "poorly determined" limits; never
reported): random population 0-99, thermal 320x256 population 1000-1099 (issue 35's rule was chosen on all of
these). REPORTING: random population 100-149 and 150-199, thermal 320x256 population 1100-1149 and 1150-1249
(the previous sigma rule); random 200-249 and thermal 1250-1349 (issue 35's rule, never used before); random
250-299 and thermal 1350-1449 (the flattened board-frame corners, never used before).

The cache keeps the true corners (``truth``), from which each row's ``corner_error`` says how far the corners the
calibration used lie from them and how much of that every view shares (``corner_errors``).

The rows (``--rows-out``) keep, per camera, the chosen and the standard lens model's estimates, Jacobian sigmas
and delete-one-view replicates, so the sigma rules of ``RULES`` are compared from them (``--summarise``)
without calibrating again::

    .venv/bin/python experiments/calibration_random.py --thermal16 --summarise t16-1000-1039.json t16-1040-1099.json

Populations (``services.simulation.boards.random_calibration``):

- random: infrared (hollow heated board) or visible (printed board) with equal odds, sizes 160x120..640x512
  (infrared) and 640x480..1024x768 (visible), fields of view 25..65 degrees, random distortion, boards of
  5..10 x 4..7 corners, 8..20 views, blur 0.4..1.5 px, noise 0.5..3 grey levels;
- thermal16: the issue's unseen case, 320x256 infrared behind a hollow heated board, 16 views, blur 1 px,
  noise 2 grey levels, the rest drawn as above.

Each camera is calibrated as ``thermofield calibrate camera --distortion auto`` does (board detection, corner
window chosen by cross-validation, outlier views, lens model by BIC, corners refined again in the board frame
and kept if they fit better, sigmas from the view jackknife, with the lens-model choice's term); the thermal16 population is also
calibrated by stock OpenCV (``cv2.calibrateCamera``, five coefficients, on the detector's corners).
A sigma covers its error when |error| <= 1.645 sigma (the two-sided 90 % interval).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from services.calibration.camera import (_ESTIMATED, INTRINSIC_NAMES, _calibrate_views, _intrinsic_values,
                                         jackknife_replicates)
from services.calibration.corner_window import select_corner_window
from services.calibration.corners import detect_board
from services.calibration.determination import FOCAL_LIMIT, PRINCIPAL_POINT_LIMIT, poorly_determined
from services.calibration.frontal import calibrate_with_frontal_refinement
from services.simulation.boards import random_calibration

Z90 = 1.6448536269514722  # two-sided 90 % normal quantile


def seeds(text: str) -> list[int]:
    values = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        values.extend(range(int(low), int(high or low) + 1))
    return values


def corners(seed: int, thermal16: bool, cache: Path) -> dict:
    """Render one camera's views and detect the board (cached per seed)."""
    path = cache / f"{'thermal16' if thermal16 else 'random'}_{seed}.npz"
    if path.exists():
        data = np.load(path, allow_pickle=True)
        return {key: data[key] for key in data.files}
    rng = np.random.default_rng(seed)
    extra = dict(modality="infrared", image_size=(320, 256), views=16, blur_sigma=1.0, noise_sigma=2.0) if thermal16 \
        else {}
    session = random_calibration(rng, **extra)
    detections = [detect_board(image, session.board) for image in session.images]
    found = [i for i, d in enumerate(detections) if d is not None]
    objects = [session.board.object_points()[detections[i].ids] for i in found]
    raw = [detections[i].image_points for i in found]
    truth = [cv2.projectPoints(o, cv2.Rodrigues(session.poses[i][0])[0], session.poses[i][1], session.K,
                               session.dist)[0].reshape(-1, 2) for o, i in zip(objects, found)]
    record = dict(modality=session.modality, size=np.array(session.image_size), K=session.K, dist=session.dist,
                  pattern=np.array(session.board.pattern_size), square=session.board.square_mm,
                  views=len(session.images), blur=session.blur_sigma, noise=session.noise_sigma, found=len(found))
    if len(found) >= 4:
        record.update(objects=np.array(objects, dtype=object), raw=np.array(raw, dtype=object),
                      truth=np.array(truth, dtype=object), images=np.array([session.images[i] for i in found]))
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **record)
    return {key: np.asarray(value) for key, value in record.items()}


def distortion_error_px(K_true, dist_true, K, dist, size) -> float:
    """Largest difference of the lens displacement over the image, in pixels of the true focal length.

    Only over the pixels the true lens reaches: a strong barrel lens (k1 < 0, k2 = 0) folds back beyond some
    radius, and an image corner outside that radius has no ray (its undistortion does not return to it).
    """
    width, height = size
    u, v = np.meshgrid(np.linspace(0, width - 1, 17), np.linspace(0, height - 1, 15))
    pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    normal = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K_true, dist_true).reshape(-1, 2)
    rays = np.column_stack([normal, np.ones(len(normal))])
    back = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_true, dist_true)[0].reshape(-1, 2)
    rays = rays[np.linalg.norm(back - pixels, axis=1) < 0.01]
    true = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.eye(3), dist_true)[0].reshape(-1, 2)
    estimated = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, float))[0].reshape(-1, 2)
    return float(np.max(np.linalg.norm(estimated - true, axis=1)) * K_true[0, 0])


def corner_errors(objects: list[np.ndarray], corners: list[np.ndarray], truth: list[np.ndarray],
                  square_mm: float) -> dict[str, float]:
    """How far the corners a calibration used lie from the simulator's true corners.

    ``rms_px``: over every corner; ``board_fixed_squares``: the RMS over the board's corners of each corner's
    error in the board frame (the error mapped through the local inverse of the true board-to-image Jacobian,
    in squares) averaged over the views, less the similarity of the board that fits these means best (a
    scale, rotation or shift of the whole board is taken up by the poses), i.e. the part shared by every view
    that no view resampling sees; ``board_fixed_noise_squares``: what that would be from the views' scatter
    alone.
    """
    errors, keys = [], []
    for obj, found, true in zip(objects, corners, truth):
        obj, found, true = (np.asarray(a, np.float64) for a in (obj, found, true))
        homography = cv2.findHomography(obj[:, :2], true)[0]  # local Jacobian of the board-to-image map
        h = homography @ np.column_stack([obj[:, :2], np.ones(len(obj))]).T
        jacobians = (homography[:2, :2][None] * h[2][:, None, None] - np.einsum("in,j->nij", h[:2], homography[2, :2]))
        jacobians /= (h[2] ** 2)[:, None, None]
        errors.append(np.einsum("nij,nj->ni", np.linalg.inv(jacobians), found - true) / square_mm)
        keys.append([tuple(k) for k in np.round(obj[:, :2] / square_mm).astype(int)])
    per_corner: dict[tuple, list] = {}
    for view_keys, view_errors in zip(keys, errors):
        for key, error in zip(view_keys, view_errors):
            per_corner.setdefault(key, []).append(error)
    means = np.array([np.mean(v, axis=0) for v in per_corner.values()])
    # a similarity of the board (scale, rotation, shift) is taken up by the poses: only the rest is an error
    where = np.array(list(per_corner), np.float64)
    design = np.block([[where[:, :1], -where[:, 1:], np.ones((len(where), 1)), np.zeros((len(where), 1))],
                       [where[:, 1:], where[:, :1], np.zeros((len(where), 1)), np.ones((len(where), 1))]])
    stacked = np.concatenate([means[:, 0], means[:, 1]])
    rest = stacked - design @ np.linalg.lstsq(design, stacked, rcond=None)[0]
    means = np.column_stack([rest[:len(where)], rest[len(where):]])
    kept_share = np.sqrt(max(2 * len(where) - 4, 1) / (2 * len(where)))
    noise = kept_share * np.array([np.std(v, axis=0) / np.sqrt(len(v)) for v in per_corner.values() if len(v) > 1])
    residual = np.concatenate([np.asarray(f, np.float64) - np.asarray(t) for f, t in zip(corners, truth)])
    return {"rms_px": float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))),
            "board_fixed_squares": float(np.sqrt(np.mean(np.sum(means**2, axis=1)))),
            "board_fixed_noise_squares": float(np.sqrt(np.mean(np.sum(noise**2, axis=1))))}


def evaluate(seed: int, thermal16: bool, cache: Path) -> dict | None:
    data = corners(seed, thermal16, cache)
    if "raw" not in data:
        return {"seed": seed, "modality": str(data["modality"]), "size": data["size"].tolist(), "views": int(data["views"]),
                "found": int(data["found"]), "failed": True}
    size = tuple(int(s) for s in data["size"])
    K_true, dist_true = data["K"], data["dist"]
    objects = [np.asarray(o, np.float64) for o in data["objects"]]
    window = select_corner_window(list(data["images"]), [np.asarray(p, np.float64) for p in data["raw"]], objects,
                                  size, "auto")
    result, refined = calibrate_with_frontal_refinement(list(data["images"]), objects, window.image_points, size, "auto",
                                                        float(data["square"]), window.fraction)
    names = list(result.std)
    truth = dict(zip(INTRINSIC_NAMES, [K_true[0, 0], K_true[1, 1], K_true[0, 2], K_true[1, 2], *dist_true]))
    estimate = dict(zip(INTRINSIC_NAMES, [result.K[0, 0], result.K[1, 1], result.K[0, 2], result.K[1, 2],
                                          *result.dist]))
    errors = {name: float(estimate[name] - truth.get(name, 0.0)) for name in names}
    kept = list(result.views)
    kept_objects = [np.asarray(objects[i], np.float32) for i in kept]
    kept_images = [np.asarray(refined[i], np.float32) for i in kept]
    models = {}  # what a sigma rule needs, so that rules can be compared from the rows without calibrating again
    for model in dict.fromkeys((result.distortion_model, "standard")):
        full = _calibrate_views(kept_objects, kept_images, size, model)
        model_names = _ESTIMATED[model]
        values = _intrinsic_values(full)[[INTRINSIC_NAMES.index(name) for name in model_names]]
        replicates = jackknife_replicates(kept_objects, kept_images, size, model, full)
        models[model] = {"names": list(model_names), "estimate": values.tolist(),
                         "jacobian": [float(full["std_intrinsics"][INTRINSIC_NAMES.index(name)]) for name in model_names],
                         "replicates": replicates.tolist()}
    chosen = models[result.distortion_model]
    deviations = np.asarray(chosen["replicates"]) - np.mean(chosen["replicates"], axis=0)
    jack = np.sqrt((len(kept) - 1) / len(kept) * np.sum(deviations**2, axis=0))
    row = {
        "seed": seed, "modality": str(data["modality"]), "size": list(size), "views": int(data["views"]),
        "found": int(data["found"]), "kept": len(kept), "blur": float(data["blur"]), "noise": float(data["noise"]),
        "f_true": float(K_true[0, 0]), "model": result.distortion_model, "window": window.fraction,
        "f_error_pct": float(100 * max(abs(errors["fx"]) / truth["fx"], abs(errors["fy"]) / truth["fy"])),
        "c_error_px": float(np.hypot(errors["cx"], errors["cy"])),
        "distortion_error_px": distortion_error_px(K_true, dist_true, result.K, result.dist, size),
        "errors": errors, "std": result.std, "std_jacobian": result.std_jacobian,
        "std_jackknife": dict(zip(names, map(float, jack))),
        "std_model_choice": result.std_model_choice or {name: 0.0 for name in names},
        "warnings": poorly_determined(result),
        "truth": {name: float(truth.get(name, 0.0)) for name in INTRINSIC_NAMES},
        "models": models,
    }
    if "truth" in data:  # caches written before the true corners were kept have none
        row["corner_error"] = corner_errors(objects, refined, list(data["truth"]), float(data["square"]))
    if thermal16:
        objects32 = [o.astype(np.float32) for o in objects]
        raw = [np.asarray(p, np.float32) for p in data["raw"]]
        _, K_stock, _, _, _ = cv2.calibrateCamera(objects32, raw, size, None, None)
        row["stock_f_error_pct"] = float(100 * np.max(np.abs(np.diag(K_stock)[:2] / np.diag(K_true)[:2] - 1)))
        row["stock_c_error_px"] = float(np.hypot(*(K_stock[:2, 2] - K_true[:2, 2])))
    return row


def sigma(row: dict, kind: str, name: str) -> float:
    """One of a row's sigmas; "std_conditional" is the reported one without the lens-model-choice term."""
    if kind == "std_conditional":
        return float(np.sqrt(max(row["std"][name] ** 2 - row.get("std_model_choice", {}).get(name, 0.0) ** 2, 0.0)))
    return row[kind][name]


def _rule_inputs(row: dict) -> dict[str, dict]:
    """Per parameter of a row: error, Jacobian and jackknife sigma, the view count, and against the standard
    model the difference d, its paired jackknife sigma and the standard model's jackknife sigma."""
    def jackknife(replicates):
        replicates = np.asarray(replicates)
        return np.sqrt((len(replicates) - 1) / len(replicates) * np.sum((replicates - replicates.mean(0)) ** 2, axis=0))
    chosen, standard = row["models"][row["model"]], row["models"]["standard"]
    chosen_replicates, standard_replicates = np.asarray(chosen["replicates"]), np.asarray(standard["replicates"])
    chosen_jackknife, standard_jackknife = jackknife(chosen_replicates), jackknife(standard_replicates)
    inputs = {}
    for i, name in enumerate(chosen["names"]):
        if name in standard["names"]:
            j = standard["names"].index(name)
            general, general_replicates, general_jackknife = standard["estimate"][j], standard_replicates[:, j], \
                standard_jackknife[j]
        else:  # k4..k6: zero in the standard model
            general, general_replicates, general_jackknife = 0.0, np.zeros(len(chosen_replicates)), 0.0
        inputs[name] = dict(error=row["errors"][name], jacobian=chosen["jacobian"][i], jackknife=chosen_jackknife[i],
                            views=len(chosen_replicates), model=row["model"], d=general - chosen["estimate"][i],
                            d_jackknife=float(jackknife(general_replicates - chosen_replicates[:, i])),
                            standard_jackknife=general_jackknife)
    return inputs


#: Sigma rules compared on the tuning cameras (docs/calibration.md): the base sigma, whether a simpler model's
#: sigma is floored by the standard model's (pinhole parameters or all), and the model-choice term on the
#: distortion coefficients (none, d^2, or Hausman's max(0, d^2 - var d)); fx..cy always carry d^2.
RULES = {
    "previous (max of jackknife and Jacobian, floor all, d^2 on f and c)": ("max", "all", "none"),
    "Student jackknife, floor all, d^2 on f and c": ("student", "all", "none"),
    "Student jackknife, floor all, d^2 on all": ("student", "all", "plain"),
    "Student jackknife, floor f and c, d^2 on all": ("student", "pinhole", "plain"),
    "max, floor f and c, Hausman on distortion": ("max", "pinhole", "hausman"),
    "jackknife alone, floor f and c, Hausman on distortion": ("jackknife", "pinhole", "hausman"),
    "reported now: Student jackknife, floor f and c, Hausman on distortion": ("student", "pinhole", "hausman"),
}


def rule_sigma(p: dict, name: str, rule: tuple[str, str, str]) -> float:
    base, floor, term = rule
    factor = np.sqrt((p["views"] - 1) / (p["views"] - 3))
    sigma = {"max": max(p["jackknife"], p["jacobian"]), "student": factor * p["jackknife"],
             "jackknife": p["jackknife"]}[base]
    pinhole = name in ("fx", "fy", "cx", "cy")
    if p["model"] in ("none", "radial") and p["standard_jackknife"] > 0 and (floor == "all" or pinhole):
        sigma = max(sigma, (factor if base == "student" else 1.0) * p["standard_jackknife"])
    if p["model"] != "standard":
        if pinhole or term == "plain":
            sigma = np.hypot(sigma, p["d"])
        elif term == "hausman":
            sigma = np.sqrt(sigma**2 + max(0.0, p["d"] ** 2 - p["d_jackknife"] ** 2))
    return float(sigma)


def compare_rules(rows: list[dict]) -> None:
    """Coverage of each of ``RULES`` from rows that keep the models' replicates (``--rows-out`` of this version)."""
    good = [r for r in rows if not r.get("failed") and "models" in r]
    if not good:
        return
    inputs = [_rule_inputs(r) for r in good]
    groups = {"f": ("fx", "fy"), "c_x": ("cx",), "c_y": ("cy",), "distortion": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
              "k1": ("k1",), "k2": ("k2",), "p1, p2": ("p1", "p2"), "k3": ("k3",)}
    print(f"\n| sigma rule ({len(good)} cameras): coverage at 90 % | " + " | ".join(groups) + " |\n|---"
          + "|---" * len(groups) + "|")
    for label, rule in RULES.items():
        cells = []
        for members in groups.values():
            hits = [abs(p[n]["error"]) <= Z90 * rule_sigma(p[n], n, rule) for p in inputs for n in members if n in p]
            cells.append(f"{100 * np.mean(hits):.1f} %" if hits else "-")
        print(f"| {label} | " + " | ".join(cells) + " |")


def summary(rows: list[dict], title: str) -> None:
    good = [r for r in rows if not r.get("failed")]
    print(f"\n{title}: {len(good)} cameras calibrated of {len(rows)} "
          f"({sum(r['modality'] == 'infrared' for r in good)} infrared, {sum(r['modality'] == 'visible' for r in good)} "
          f"visible); views found {sum(r['found'] for r in rows)} of {sum(r['views'] for r in rows)}")
    print("\n| error | median | 95th percentile | worst |\n|---|---|---|---|")
    for key, label in (("f_error_pct", "focal length (%)"), ("c_error_px", "principal point (px)"),
                       ("distortion_error_px", "distortion, largest over the image (px)")):
        values = np.array([r[key] for r in good])
        print(f"| {label} | {np.median(values):.3f} | {np.percentile(values, 95):.3f} | {values.max():.3f} |")
    if good and "stock_f_error_pct" in good[0]:
        for key, label in (("stock_f_error_pct", "stock OpenCV focal length (%)"),
                           ("stock_c_error_px", "stock OpenCV principal point (px)")):
            values = np.array([r[key] for r in good])
            print(f"| {label} | {np.median(values):.3f} | {np.percentile(values, 95):.3f} | {values.max():.3f} |")
    with_truth = [r for r in good if "corner_error" in r]
    if with_truth:
        print("\n| corners used against the true corners | median | 95th percentile |\n|---|---|---|")
        for key, label in (("rms_px", "RMS error (px)"),
                           ("board_fixed_squares", "shared by every view: board-frame mean per corner (squares)"),
                           ("board_fixed_noise_squares", "its noise level from the views' scatter (squares)")):
            values = np.array([r["corner_error"][key] for r in with_truth])
            print(f"| {label} | {np.median(values):.5f} | {np.percentile(values, 95):.5f} |")
    bias = {name: [r["errors"][name] / r["std"][name] for r in good if name in r["errors"]] for name in ("fx", "fy", "cx", "cy")}
    print("\n| error / reported sigma | " + " | ".join(bias) + " |\n|---" + "|---" * len(bias) + "|")
    print("| mean (its standard error) | " + " | ".join(f"{np.mean(v):+.2f} ({np.std(v) / np.sqrt(len(v)):.2f})"
                                                    for v in bias.values()) + " |")
    groups = {"f (fx, fy)": ("fx", "fy"), "principal point (cx, cy)": ("cx", "cy"),
              "distortion terms": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")}
    print("\n| parameter | sigma covers 1.645 sigma: reported | without the lens-model term | Jacobian only "
          "| jackknife only | estimates |\n|---|---|---|---|---|---|")
    for label, members in list(groups.items()) + [(n, (n,)) for n in ("fx", "fy", "cx", "cy", "k1", "k2")]:
        hits = {kind: [] for kind in ("std", "std_conditional", "std_jacobian", "std_jackknife")}
        for r in good:
            for name in members:
                if name in r["errors"]:
                    for kind in hits:
                        hits[kind].append(abs(r["errors"][name]) <= Z90 * sigma(r, kind, name))
        if hits["std"]:
            print(f"| {label} | {100 * np.mean(hits['std']):.1f} % | {100 * np.mean(hits['std_conditional']):.1f} % "
                  f"| {100 * np.mean(hits['std_jacobian']):.1f} % | {100 * np.mean(hits['std_jackknife']):.1f} % "
                  f"| {len(hits['std'])} |")
    compare_rules(good)
    flagged = {"focal length": [r for r in good if Z90 * max(r["std"]["fx"] / r["f_true"], r["std"]["fy"] / r["f_true"])
                                > FOCAL_LIMIT],
               "principal point": [r for r in good if Z90 * max(r["std"]["cx"], r["std"]["cy"])
                                   > PRINCIPAL_POINT_LIMIT * r["size"][0]]}
    print("\n| called poorly determined (from the sigmas) | cameras | their median error | the others' median error |"
          "\n|---|---|---|---|")
    for label, key, unit in (("focal length", "f_error_pct", "%"), ("principal point", "c_error_px", "px")):
        named = [r[key] for r in flagged[label]]
        others = [r[key] for r in good if r not in flagged[label]]
        print(f"| {label} | {len(named)} of {len(good)} | "
              + (f"{np.median(named):.3f} {unit}" if named else "-") + " | "
              + (f"{np.median(others):.3f} {unit}" if others else "-") + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=seeds, default=[], help="e.g. 100-149")
    parser.add_argument("--summarise", type=Path, nargs="+", default=None,
                        help="only print the tables of saved --rows-out files (runs split over processes)")
    parser.add_argument("--thermal16", action="store_true", help="the 320x256 infrared population with 16 views")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/calibration-random"), help="corner cache")
    parser.add_argument("--render-only", action="store_true", help="only render and detect into the cache")
    parser.add_argument("--rows-out", type=Path, default=None, help="also save the per-camera rows as JSON")
    args = parser.parse_args()
    if args.summarise:
        rows = [row for path in args.summarise for row in json.loads(path.read_text())]
        summary(rows, "320x256 infrared, 16 views" if args.thermal16 else "random cameras")
        return
    rows = []
    for seed in args.seeds:
        if args.render_only:
            corners(seed, args.thermal16, args.cache)
            continue
        row = evaluate(seed, args.thermal16, args.cache)
        rows.append(row)
        if args.rows_out is not None:
            args.rows_out.write_text(json.dumps(rows, indent=1))
        if row.get("failed"):
            print(f"seed {seed}: {row['modality']} {row['size']}: board found in {row['found']} of {row['views']} views,"
                  " too few", flush=True)
        else:
            print(f"seed {seed}: {row['modality']} {row['size']} {row['kept']}/{row['views']} views, {row['model']}, "
                  f"f {row['f_error_pct']:.3f} %, c {row['c_error_px']:.2f} px, "
                  f"distortion {row['distortion_error_px']:.2f} px", flush=True)
    if args.render_only:
        return
    summary(rows, "320x256 infrared, 16 views" if args.thermal16 else "random cameras")
    if args.rows_out is not None:
        args.rows_out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

"""Compare structured-light codings on the simulated paper rig; prints the Markdown table of docs/coding.md.

Run: ``.venv/bin/python experiments/coding_comparison.py`` (a few minutes on 2 cores).

Each coding is projected onto the paper's plane (at 430 and 570 mm) and sphere (radius 100 mm),
filmed by the simulated camera (sensor noise 1.5 grey levels, camera blur sigma 1 px, projector blur
0.5 px, 8 bits) with a linear projector and with a projector gamma of 2.2, decoded by
``services.structured_light.decode`` with default thresholds and triangulated as decoded (no
point-cloud filtering, so that the codings are compared as they decode). Errors are measured
against the simulator's ground truth: the projector column of each fully lit camera pixel's centre
(pixel errors, coverage), and the 3D surface point of every reconstructed pixel whose centre ray meets
the object (3D errors; this includes the object's outline). Points whose pixel centre misses the object
are counted as off the object. Each cell is the worst over the three scenes. Every distinct pattern is rendered once per scene and condition with its own noise.
"""

from __future__ import annotations

import numpy as np

from services.formats.sequence import BlackFrame, GrayFrame, PhaseFrame, ProjectorSize, Sequence, WhiteFrame
from services.simulation.presets import paper_plane, paper_rig, paper_sphere
from services.simulation.render import CameraEffects, ProjectorEffects, render_frames, render_view
from services.structured_light.decode import decode
from services.structured_light.patterns import render_patterns
from services.structured_light.triangulate import camera_ray_table, triangulate

WIDTH, HEIGHT = 1024, 768
TOP_BIT = 9  # Gray code of 1024 columns: bits 9..0
GROSS_PX = 1.0


def _frame_name(frame) -> str:
    if frame.kind in ("white", "black"):
        return frame.kind
    if frame.kind == "gray":
        return f"gray_{frame.bit}{'_inv' if frame.inverted else ''}"
    return f"phase_{frame.period:g}_{frame.step}of{frame.steps}"


def _sequence(*, finest_bit=None, inverses=True, period=None, steps=None, periods=()) -> Sequence:
    frames = [WhiteFrame(kind="white", file="white"), BlackFrame(kind="black", file="black")]
    if finest_bit is not None:
        for bit in range(TOP_BIT, finest_bit - 1, -1):
            for inverted in (False, True) if inverses else (False,):
                frames.append(GrayFrame(kind="gray", file="?", axis="x", bit=bit, inverted=inverted))
    for p, n in ([(period, steps)] if period else []) + list(periods):
        frames += [PhaseFrame(kind="phase", file="?", axis="x", period=p, step=k, steps=n) for k in range(n)]
    frames = [frame.model_copy(update={"file": _frame_name(frame)}) for frame in frames]
    return Sequence(projector=ProjectorSize(width=WIDTH, height=HEIGHT), frames=frames)


CODINGS = {
    "Gray code, 10 bits + inverses": _sequence(finest_bit=0),
    "Gray code, 10 bits, white/black threshold": _sequence(finest_bit=0, inverses=False),
    "Gray (16 px stripes) + 4-step, plain unwrapping": _sequence(finest_bit=4, period=16, steps=4),
    "complementary Gray + 4-step, P = 16": _sequence(finest_bit=3, period=16, steps=4),
    "Gray (16 px stripes) + 8-step, plain unwrapping": _sequence(finest_bit=4, period=16, steps=8),
    "complementary Gray + 8-step, P = 16": _sequence(finest_bit=3, period=16, steps=8),
    "**complementary Gray + 12-step, P = 16 (default)**": _sequence(finest_bit=3, period=16, steps=12),
    "complementary Gray + 8-step, P = 32": _sequence(finest_bit=4, period=32, steps=8),
    "3-frequency 4-step (P = 1100, 110, 16), no Gray": _sequence(periods=[(1100, 4), (110, 4), (16, 4)]),
}

SCENES = {"plane 430 mm": paper_plane(430.0), "plane 570 mm": paper_plane(570.0), "sphere r = 100 mm": paper_sphere(100.0)}
CONDITIONS = {
    "linear projector": ProjectorEffects(blur_sigma=0.5),
    "projector gamma 2.2": ProjectorEffects(blur_sigma=0.5, gamma=2.2),
}
CAMERA = CameraEffects(exposure=0.8, blur_sigma=1.0, noise_sigma=1.5)


def _unique_frames() -> dict[str, np.ndarray]:
    patterns = {}
    for sequence in CODINGS.values():
        for frame, image in zip(sequence.frames, render_patterns(sequence)):
            patterns.setdefault(frame.file, image)
    return patterns


def _measure(sequence, captured, view, camera, projector, rays) -> dict[str, float]:
    frames = np.stack([captured[frame.file] for frame in sequence.frames])
    decoded = decode(frames, sequence, gray_boundaries=False)  # Gray-only codings as stripe centres (docs/coding.md)
    truth = view.truth
    decoded_lit = decoded.valid & truth.lit
    error_px = np.abs(decoded.projector_x - truth.projector_pixels[..., 0])[decoded_lit]
    decoded_pixels = np.flatnonzero(decoded.valid)
    points = triangulate(rays.reshape(-1, 2)[decoded_pixels], decoded.projector_x.ravel()[decoded_pixels], "x",
                         camera.R, camera.t, projector.K, projector.dist,
                         projector.R, projector.t)
    v, u = np.divmod(decoded_pixels, camera.width)
    on_surface = truth.surface[v, u] >= 0
    points = points[on_surface]
    error_mm = np.linalg.norm(points - truth.points[v[on_surface], u[on_surface]], axis=1)
    return {
        "frames": len(sequence.frames),
        "coverage": np.sum(decoded.valid & truth.lit) / truth.lit.sum(),
        "mean_px": error_px.mean(),
        "p999_px": np.quantile(error_px, 0.999),
        "gross": np.mean(error_px > GROSS_PX),
        "mean_mm": error_mm.mean(),
        "max_mm": error_mm.max(),
        "stray": np.sum(~on_surface),
    }


def main() -> None:
    rig = paper_rig()
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    rays = camera_ray_table(camera.K, camera.dist, camera.width, camera.height)
    patterns = _unique_frames()
    names = list(patterns)
    stack = np.stack([patterns[name] for name in names])
    results: dict[tuple[str, str], list[dict[str, float]]] = {}
    by_scene: dict[tuple[str, str], dict[str, float]] = {}
    for scene_name, scene in SCENES.items():
        view = render_view(scene, camera, projector)
        for condition_name, effects in CONDITIONS.items():
            rng = np.random.default_rng(0)
            captured = dict(zip(names, render_frames(view, stack, rng, CAMERA, effects)))
            for coding_name, sequence in CODINGS.items():
                measured = _measure(sequence, captured, view, camera, projector, rays)
                results.setdefault((coding_name, condition_name), []).append(measured)
                if condition_name == "linear projector":
                    by_scene[coding_name, scene_name] = measured
                print(f"<!-- {scene_name}, {condition_name}, {coding_name}: "
                      + ", ".join(f"{k} {v:.4g}" for k, v in measured.items()) + " -->", flush=True)
    print()
    print("| coding | frames | projector | coverage of lit pixels | mean error (px) | 99.9 % error (px) "
          "| gross errors > 1 px | mean 3D error (mm) | max 3D error (mm) | points off the object |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (coding_name, condition_name), rows in results.items():
        worst = {key: max(row[key] for row in rows) for key in rows[0]}
        least = {key: min(row[key] for row in rows) for key in rows[0]}
        print(f"| {coding_name} | {rows[0]['frames']} | {condition_name} | {100 * least['coverage']:.2f} % "
              f"| {worst['mean_px']:.4f} | {worst['p999_px']:.3f} | {100 * worst['gross']:.3f} % "
              f"| {worst['mean_mm']:.4f} | {worst['max_mm']:.3f} | {int(worst['stray'])} |")

    print()
    print("| coding (linear projector) | scene | coverage of lit pixels | mean error (px) | 99.9 % error (px) "
          "| mean 3D error (mm) | max 3D error (mm) |")
    print("|---|---|---|---|---|---|---|")
    for (coding_name, scene_name), row in by_scene.items():
        print(f"| {coding_name} | {scene_name} | {100 * row['coverage']:.2f} % | {row['mean_px']:.4f} "
              f"| {row['p999_px']:.3f} | {row['mean_mm']:.4f} | {row['max_mm']:.3f} |")


if __name__ == "__main__":
    main()

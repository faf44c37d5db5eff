"""Gray-code-only captures: sub-pixel boundary interpolation against stripe centres; the table of
docs/structured-light.md.

Run: ``.venv/bin/python experiments/gray_subpixel.py`` (a few minutes on 2 cores).

A foreign scanner's sequence, white, black and the 10 column Gray planes of an 1824-pixel projector with
the finest bit dropped (stripes 2 projector pixels wide, no inverse planes), is projected onto a plane and a
sphere in the Gray-code scanner rig (``presets.gray_scanner_rig``: 1824x1140 projector, 1280x1024 camera)
and filmed with camera blur 0.8 px and noise 1.5 grey levels (8 bits, linear projector). The same frames
are reconstructed by ``reconstruct_points`` twice: with stripe centres (``gray_boundaries=False``) and with
the coordinates interpolated between the located stripe boundaries (the default). Errors are distances
along each pixel's ray to the simulator's true surface point; outliers are errors above 1 mm.
"""

from __future__ import annotations

import sys

import numpy as np

from services.formats.sequence import BlackFrame, GrayFrame, ProjectorSize, Sequence, WhiteFrame
from services.simulation.presets import gray_scanner_rig, paper_plane, paper_sphere
from services.simulation.render import CameraEffects, render_frames, render_view
from services.structured_light.patterns import render_patterns
from services.structured_light.reconstruct import reconstruct_points

CAMERA = CameraEffects(exposure=0.8, blur_sigma=0.8, noise_sigma=1.5)
OUTLIER_MM = 1.0


def gray_only_sequence(width: int, height: int, inverses: bool = False, dropped_bits: int = 1) -> Sequence:
    """White, black and the column Gray planes, most significant first, without the ``dropped_bits`` finest."""
    top = (width - 1).bit_length() - 1
    frames = [WhiteFrame(kind="white", file="white.png"), BlackFrame(kind="black", file="black.png")]
    for bit in range(top, dropped_bits - 1, -1):
        for inverted in (False, True) if inverses else (False,):
            frames.append(GrayFrame(kind="gray", file=f"gray_x_{bit:02d}{'_inv' if inverted else ''}.png", axis="x",
                                    bit=bit, inverted=inverted))
    return Sequence(projector=ProjectorSize(width=width, height=height), frames=frames)


def depth_errors(scene, rig, sequence, camera_effects=CAMERA, seed=0) -> dict[str, dict[str, float]]:
    """Stripe-centre and boundary-interpolated reconstructions of the same frames against the truth."""
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    view = render_view(scene, camera, projector)
    frames = render_frames(view, render_patterns(sequence), np.random.default_rng(seed), camera_effects)
    truth = view.truth
    results = {}
    for name, boundaries in (("stripe centres", False), ("boundary interpolation", True)):
        cloud = reconstruct_points(frames, sequence, camera, projector, gray_boundaries=boundaries)
        u, v = cloud["u"].astype(int), cloud["v"].astype(int)
        on_object = truth.surface[v, u] >= 0
        points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])[on_object]
        error = np.linalg.norm(points - truth.points[v[on_object], u[on_object]], axis=1)
        pixel_error = np.abs(cloud["projector"][on_object] - truth.projector_pixels[v[on_object], u[on_object], 0])
        lit = truth.lit.sum()
        results[name] = {
            "points": len(error),
            "coverage": np.count_nonzero(truth.lit[v[on_object], u[on_object]]) / lit,
            "rms_mm": float(np.sqrt(np.nanmean(error**2))),
            "mean_mm": float(np.nanmean(error)),
            "max_mm": float(np.nanmax(error)),
            "outliers": float(np.mean(error > OUTLIER_MM)),
            "rms_px": float(np.sqrt(np.nanmean(pixel_error**2))),
            "off_object": int(np.count_nonzero(~on_object)),
        }
    return results


SCENES = {"plane 300 x 200 mm at 500 mm": paper_plane(500.0), "sphere r = 100 mm at 480 mm": paper_sphere(100.0)}


def main() -> None:
    rig = gray_scanner_rig()
    sequence = gray_only_sequence(1824, 1140)
    print("| scene | decoding | points | coverage of lit pixels | RMS error (mm) | mean (mm) | max (mm) "
          "| outliers > 1 mm | RMS projector error (px) | RMS ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for scene_name, scene in SCENES.items():
        rows = depth_errors(scene, rig, sequence)
        ratio = rows["stripe centres"]["rms_mm"] / rows["boundary interpolation"]["rms_mm"]
        for name, row in rows.items():
            print(f"| {scene_name} | {name} | {row['points']} | {100 * row['coverage']:.2f} % | {row['rms_mm']:.4f} "
                  f"| {row['mean_mm']:.4f} | {row['max_mm']:.3f} | {100 * row['outliers']:.3f} % "
                  f"| {row['rms_px']:.3f} | {'' if name == 'stripe centres' else f'{ratio:.1f}x'} |", flush=True)
    sys.stdout.flush()


if __name__ == "__main__":
    main()

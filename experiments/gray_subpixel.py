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
from pathlib import Path

import cv2
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


# --- SLStudio's real skull, coded by Gray code alone (docs/real-data.md) -------------------------------------

SLSTUDIO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "slstudio"
SKULL_MANIFEST = Path(__file__).resolve().parent / "slstudio" / "skull_sequence.json"
ROUGHNESS_WINDOW_PX = 7


def slstudio_gray_capture(seed: int = 0) -> tuple[Sequence, np.ndarray, dict[str, np.ndarray]]:
    """A Gray-code-only capture of SLStudio's real skull, made from its real phase-shift frames.

    The shared data hold no Gray-code capture, so the skull's Gray planes are rendered from what its real
    frames measure at every camera pixel: the offset A (mean of the fine period's 3 frames), the
    modulation B (their amplitude) and the projector column c (the phase decoded and unwrapped, filled
    from the nearest decoded pixel where it is not). Plane b shows A + B (2 g_b(c) - 1), the white frame
    A + B and the black A - B, the binary edges blurred by the capture's own camera blur
    (``estimate_camera_blur``), and each frame gets the capture's own noise: the fine and the coarse
    period's offsets both estimate A, so their difference has variance 2 sigma^2 / 3. The sequence is
    ``gray_only_sequence(1824, 1140)``: white, black and the column planes 10..1, 2-pixel stripes.
    Returns the sequence, the uint8 frames and the real maps (``A``, ``B``, ``c``, ``sigma``, ``blur``).
    """
    from scipy.ndimage import distance_transform_edt

    from services.formats.sequence import read_capture
    from services.structured_light.decode import decode
    from services.structured_light.outline import ASSUMED_CAMERA_BLUR_PX, estimate_camera_blur

    phase_sequence, real = read_capture(SLSTUDIO / "skull_2x3", SKULL_MANIFEST)
    real = real.astype(np.float64)
    offset_fine, offset_coarse = real[0:3].mean(axis=0), real[3:6].mean(axis=0)
    decoded = decode(real.astype(np.uint8), phase_sequence, consistency=0.5, edge_margin=0)
    c = decoded.projector_x.astype(np.float64)
    known = np.isfinite(c)
    nearest = distance_transform_edt(~known, return_distances=False, return_indices=True)
    c = c[nearest[0], nearest[1]]
    modulation = decoded.modulation.astype(np.float64)
    lit = decoded.rejection != 1  # not DARK
    sigma = float(np.std((offset_fine - offset_coarse)[lit]) * np.sqrt(1.5))
    blur = estimate_camera_blur(decoded.intensity, decoded.rejection) or ASSUMED_CAMERA_BLUR_PX
    sequence = gray_only_sequence(1824, 1140)
    column = np.clip(np.floor(c + 0.5), 0, 1823).astype(np.int64)
    gray = column ^ (column >> 1)
    rng = np.random.default_rng(seed)
    frames = []
    for frame in sequence.frames:
        if frame.kind == "white":
            sign = np.ones_like(c)
        elif frame.kind == "black":
            sign = -np.ones_like(c)
        else:
            sign = 2.0 * ((gray >> frame.bit) & 1) - 1.0
            sign = cv2.GaussianBlur(sign, (0, 0), blur)
        image = offset_fine + modulation * sign + rng.normal(0.0, sigma, c.shape)
        frames.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    return sequence, np.stack(frames), {"A": offset_fine, "B": modulation, "c": c, "sigma": np.array(sigma),
                                        "blur": np.array(blur)}


def local_roughness(points: np.ndarray, window: int = ROUGHNESS_WINDOW_PX) -> np.ndarray:
    """Per pixel of an (H, W, 3) point map (NaN where no point), the distance along z of its point from the
    least-squares plane z = a + b u + c v through the points of its ``window`` x ``window`` neighbourhood
    (at least half of them present); NaN elsewhere."""
    z = points[..., 2]
    height, width = z.shape
    have = np.isfinite(z).astype(np.float64)
    zz = np.where(have > 0, z, 0.0)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    box = lambda image: cv2.boxFilter(image, -1, (window, window), normalize=False,  # noqa: E731
                                      borderType=cv2.BORDER_CONSTANT)
    # Moments about each pixel: coordinates relative to the window's centre keep the system well conditioned.
    n, su, sv = box(have), box(have * u), box(have * v)
    suu, svv, suv = box(have * u * u), box(have * v * v), box(have * u * v)
    sz, suz, svz = box(zz), box(zz * u), box(zz * v)
    su_c, sv_c = su - n * u, sv - n * v
    suu_c = suu - 2 * u * su + n * u * u
    svv_c = svv - 2 * v * sv + n * v * v
    suv_c = suv - u * sv - v * su + n * u * v
    suz_c, svz_c = suz - u * sz, svz - v * sz
    system = np.stack([np.stack([n, su_c, sv_c], -1), np.stack([su_c, suu_c, suv_c], -1),
                       np.stack([sv_c, suv_c, svv_c], -1)], -2)
    rhs = np.stack([sz, suz_c, svz_c], -1)
    enough = (n >= window * window / 2) & (have > 0)
    out = np.full(z.shape, np.nan)
    solution = np.linalg.solve(system[enough], rhs[enough][..., None])[..., 0]
    out[enough] = z[enough] - solution[:, 0]
    return out

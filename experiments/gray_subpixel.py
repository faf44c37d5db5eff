"""Gray-code-only captures: sub-pixel boundary interpolation against stripe centres; the table of
docs/structured-light.md.

Run: ``.venv/bin/python experiments/gray_subpixel.py`` (a few minutes on 2 cores); with ``--slstudio`` the table of
docs/real-data.md instead: SLStudio's real skull coded by Gray code alone (``slstudio_rows``).

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


# --- SLStudio's real skull, coded by Gray code alone (docs/real-data.md) -------------------------------------

SLSTUDIO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "slstudio"
SKULL_MANIFEST = Path(__file__).resolve().parent / "slstudio" / "skull_sequence.json"
ROUGHNESS_WINDOW_PX = 7


def slstudio_gray_capture(seed: int = 0) -> tuple[Sequence, np.ndarray, float, float]:
    """A Gray-code-only capture of SLStudio's real skull (``gray_from_phase``), ``gray_only_sequence(1824, 1140)``:
    white, black and the column planes 10..1 (2-pixel stripes); the sequence, frames, noise and blur."""
    from services.formats.sequence import read_capture
    from services.simulation.gray_from_phase import gray_frames_from_phase

    phase_sequence, real = read_capture(SLSTUDIO / "skull_2x3", SKULL_MANIFEST)
    sequence = gray_only_sequence(1824, 1140)
    frames, noise, blur = gray_frames_from_phase(real, phase_sequence, sequence, np.random.default_rng(seed))
    return sequence, frames, noise, blur


# The commit before the sub-pixel Gray work (git log -- services/structured_light/gray_subpixel.py): its
# decoder gave stripe centres.
BEFORE_SUBPIXEL = "df1f3b4^"
BEFORE_COVERAGE_FIX = "8d9d7aa"  # the sub-pixel Gray decoding as issue 35 found it
_OLD_CODE_SCRIPT = """
import sys, numpy as np
from services.formats.rig import load_rig
from services.formats.sequence import load_sequence
from services.structured_light.reconstruct import reconstruct_points
rig = load_rig(sys.argv[1])
frames = np.load(sys.argv[2])["frames"]
cloud = reconstruct_points(frames, load_sequence(sys.argv[3]), rig.devices["camera"], rig.devices["projector"])
np.savez(sys.argv[4], **{name: cloud[name] for name in ("x", "y", "z", "u", "v")})
"""


def _point_map(cloud, shape: tuple[int, int]) -> np.ndarray:
    points = np.full(shape + (3,), np.nan)
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    points[v, u] = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
    return points


def _old_code_points(commit: str, work: Path, rig_path: Path, frames_path: Path, sequence_path: Path) -> dict:
    """The cloud of an earlier commit's ``reconstruct_points``, run from a copy of its tree."""
    import subprocess

    repo = Path(__file__).resolve().parents[1]
    tree = work / commit.replace("^", "-parent")
    tree.mkdir()
    archive = subprocess.run(["git", "-C", str(repo), "archive", commit, "services"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    out = tree / "cloud.npz"
    subprocess.run([sys.executable, "-c", _OLD_CODE_SCRIPT, str(rig_path), str(frames_path), str(sequence_path),
                    str(out)], check=True, cwd=tree, env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"})
    return dict(np.load(out))


def slstudio_rows(seed: int = 0) -> list[dict]:
    """Gray-only decodings of SLStudio's skull (``slstudio_gray_capture``) against its phase decoding."""
    import tempfile

    from services.cli.main import main as thermofield
    from services.formats.rig import load_rig
    from services.geometry.roughness import local_roughness
    from services.formats.sequence import read_capture, save_sequence

    sequence, frames, noise, blur = slstudio_gray_capture(seed)
    print(f"Gray capture rendered from skull_2x3: noise {noise:.2f} grey levels, blur {blur:.2f} px", flush=True)
    phase_sequence, real = read_capture(SLSTUDIO / "skull_2x3", SKULL_MANIFEST)
    shape = real.shape[1:]
    with tempfile.TemporaryDirectory() as directory:
        work = Path(directory)
        rig_path = work / "slstudio_rig.json"
        assert thermofield(["rig", "import", "--format", "slstudio", str(SLSTUDIO / "calibration" / "calibration.xml"),
                            "--out", str(rig_path)]) == 0
        rig = load_rig(rig_path)
        camera, projector = rig.device(None, "camera")[1], rig.device(None, "projector")[1]
        np.savez(work / "frames.npz", frames=frames)
        save_sequence(sequence, work)
        clouds = {"phase (SLStudio's 2x3 capture)": reconstruct_points(real, phase_sequence, camera, projector,
                                                                       consistency=0.5, max_indirect=0.33),
                  "Gray, stripe centres (`gray_boundaries=False`)": reconstruct_points(
                      frames, sequence, camera, projector, gray_boundaries=False),
                  "Gray, sub-pixel boundaries (now)": reconstruct_points(frames, sequence, camera, projector),
                  f"Gray, before the sub-pixel work ({BEFORE_SUBPIXEL})": _old_code_points(
                      BEFORE_SUBPIXEL, work, rig_path, work / "frames.npz", work),
                  f"Gray, sub-pixel boundaries before the coverage fix ({BEFORE_COVERAGE_FIX})": _old_code_points(
                      BEFORE_COVERAGE_FIX, work, rig_path, work / "frames.npz", work)}
    maps = {name: _point_map(cloud, shape) for name, cloud in clouds.items()}
    reference = maps["phase (SLStudio's 2x3 capture)"]
    object_pixels = np.isfinite(reference[..., 2])
    common = object_pixels.copy()
    for points in maps.values():
        common &= np.isfinite(points[..., 2])
    rows = []
    for name, points in maps.items():
        have = np.isfinite(points[..., 2])
        roughness = local_roughness(points, ROUGHNESS_WINDOW_PX)
        on_object = have & object_pixels
        rows.append({"decoding": name, "points": int(have.sum()),
                     "object_share": float(on_object.sum() / object_pixels.sum()),
                     "roughness_mm": float(np.sqrt(np.nanmean(roughness[on_object]**2))),
                     "roughness_common_mm": float(np.sqrt(np.nanmean(roughness[common]**2))),
                     "to_phase_mm": float(np.sqrt(np.mean(np.sum((points[on_object] - reference[on_object])**2,
                                                                 axis=-1))))})
    return rows


def slstudio_table(seed: int = 0) -> str:
    rows = slstudio_rows(seed)
    lines = ["| decoding | points | of the object pixels | roughness RMS on them (mm) | on the pixels all decode (mm) "
             "| RMS distance to the phase cloud (mm) |", "|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['decoding']} | {row['points']} | {100 * row['object_share']:.2f} % | "
                     f"{row['roughness_mm']:.3f} | {row['roughness_common_mm']:.3f} | {row['to_phase_mm']:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    if "--slstudio" in sys.argv[1:]:
        print(slstudio_table(), flush=True)
    else:
        main()

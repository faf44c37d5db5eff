"""Accuracy of the 3D temperature field on the simulated forging (tables and figures of docs/temperature-field.md).

Run: .venv/bin/python experiments/field_accuracy.py [--out docs/figures/field]

Simulates the forging station (presets.forging_rig / forging_scene with
thermal.forging_temperatures), a structured-light capture of it and one 320x256
thermal frame with 50 mK NETD; reconstructs the cloud, fuses the frame and
compares with the simulator's ground truth, for the reconstructed cloud and for
the exact cloud (true surface points at the camera pixels, isolating fusion).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from services.geometry.camera_model import CameraModel  # noqa: E402
from services.fusion.field import temperature_field  # noqa: E402
from services.fusion.fuse import ThermalView  # noqa: E402
from services.geometry.cloud import PointCloud  # noqa: E402
from services.pipeline.field import measuring_cameras  # noqa: E402
from services.fusion.visibility import (fill_empty_pixels, nearest_pixel_index, splat_nearest,  # noqa: E402
                                       within_tolerance)
from services.simulation.presets import forging_rig, forging_scene, look_at_rotation  # noqa: E402
from services.simulation.render import CameraEffects, render_frames, render_view  # noqa: E402
from services.simulation.thermal import (  # noqa: E402
    ThermalEffects, forging_temperatures, render_thermal, seen_by, surface_temperature,
)
from services.structured_light.patterns import generate_sequence  # noqa: E402
from services.structured_light.reconstruct import reconstruct_points  # noqa: E402


def simulate(seed: int = 0):
    """The forging rig, its capture and thermal frame, and per-pixel ground truth."""
    rig, scene, temperatures = forging_rig(), forging_scene(), forging_temperatures()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    rng = np.random.default_rng(seed)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    view = render_view(scene, camera, projector, supersample=3)
    frames = render_frames(view, patterns, rng,
                           CameraEffects(noise_sigma=1.0))
    image = render_thermal(scene, temperatures, thermal, ThermalEffects(netd=0.05), rng)
    return rig, scene, temperatures, sequence, frames, image, view.truth


def evaluate(cloud, rig, scene, temperatures, truth, image) -> tuple[dict, dict]:
    """Fuse ``cloud`` (which has camera pixels u, v) and score it against the truth at those pixels."""
    camera, thermal = rig.devices["camera"], rig.devices["thermal"]
    # as `thermofield field` fuses: the unseen space of the camera (and projector) that measured the cloud
    field = temperature_field(cloud, [ThermalView(thermal, image)], camera.centre,
                              witnesses=measuring_cameras(PointCloud(dict(cloud)), rig))
    row, column = cloud["v"].astype(int), cloud["u"].astype(int)
    true_points = truth.points[row, column]
    on_surface = truth.surface[row, column] >= 0
    true_temperature = surface_temperature(temperatures, true_points, truth.surface[row, column])
    pixels = thermal.project(true_points)
    in_image = on_surface & np.all((pixels > -0.5) & (pixels < [thermal.width - 0.5, thermal.height - 0.5]), axis=1)
    visible = np.zeros(len(row), dtype=bool)
    visible[in_image] = seen_by(scene, thermal, true_points[in_image])
    occluded = in_image & ~visible
    error = np.abs(field["temperature"] - true_temperature)
    seen = visible & np.isfinite(error)
    scores = {
        "points": len(row),
        "seen by thermal (truth)": int(visible.sum()),
        "occluded (truth)": int(occluded.sum()),
        "coverage of seen points": float(seen.sum() / max(visible.sum(), 1)),
        "median |error| K": float(np.median(error[seen])),
        "90th percentile |error| K": float(np.percentile(error[seen], 90)),
        "99th percentile |error| K": float(np.percentile(error[seen], 99)),
        "occluded points NaN": float(np.mean(np.isnan(field["temperature"][occluded]))),
    }
    return scores, field


def exact_cloud(truth) -> dict[str, np.ndarray]:
    """True surface points at the camera pixel centres, as a cloud with u, v (normals estimated)."""
    valid = truth.surface >= 0
    v, u = np.nonzero(valid)
    points = truth.points[valid]
    return {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
            "u": u.astype(np.float32), "v": v.astype(np.float32)}


def _virtual_camera(centre, target, focal: float, width: int, height: int) -> CameraModel:
    """A distortion-free camera at ``centre`` looking at ``target`` (image y roughly along world y)."""
    centre = np.asarray(centre, dtype=float)
    R = look_at_rotation(centre, target)
    return CameraModel(kind="camera", width=width, height=height,
                  K=[[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], R=R.tolist(), t=(-R @ centre).tolist())


def render_field_picture(field: dict, path: Path, title: str) -> None:
    """The coloured points seen from a virtual camera off the rig's axis, z-buffered and shaded by normal."""
    view = _virtual_camera((-260.0, -240.0, 100.0), (-10.0, 30.0, 660.0), 430.0, 520, 360)
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    pixels = view.project(points)
    depth = np.einsum("j,nj->n", view.R[2], points) + view.t[2]
    index = nearest_pixel_index(pixels[:, 0], pixels[:, 1], view.width, view.height)
    buffer = np.full(view.width * view.height, np.inf)
    splat_nearest(buffer, index, depth)
    buffer = fill_empty_pixels(buffer.reshape(view.height, view.width))
    front = within_tolerance(index, depth, buffer.ravel(), np.full(len(depth), 3.0))
    normals = np.column_stack([field["nx"], field["ny"], field["nz"]])
    light = np.array([-0.3, -0.6, -0.75]) / np.linalg.norm([-0.3, -0.6, -0.75])
    shade = 0.55 + 0.45 * np.clip(np.nan_to_num(np.abs(normals @ light), nan=1.0), 0, 1)
    rgb = np.column_stack([field["red"], field["green"], field["blue"]]) / 255.0 * shade[:, None]
    picture = np.ones((view.height, view.width, 3))
    column, row = np.rint(pixels[front]).astype(int).T
    picture[row, column] = rgb[front]
    seen = np.isfinite(field["temperature"])
    figure, axes = plt.subplots(figsize=(8.4, 5.2))
    axes.imshow(picture, interpolation="nearest")
    axes.set_axis_off()
    norm = plt.Normalize(np.min(field["temperature"][seen]), np.max(field["temperature"][seen]))
    figure.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="inferno"), ax=axes, shrink=0.8,
                    label="temperature (°C); grey: not seen by the thermal camera")
    axes.set_title(title)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/figures/field"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rig, scene, temperatures, sequence, frames, image, truth = simulate(args.seed)

    reconstructed = reconstruct_points(frames, sequence, rig.devices["camera"], rig.devices["projector"])
    rows = {}
    rows["reconstructed cloud"], field = evaluate(reconstructed, rig, scene, temperatures, truth, image)
    render_field_picture(field, args.out / "forging_field.png", "Simulated forging: fused 3D temperature field")
    rows["exact cloud"], _ = evaluate(exact_cloud(truth), rig, scene, temperatures, truth, image)

    names = list(next(iter(rows.values())))
    print("| quantity | " + " | ".join(rows) + " |")
    print("|---|" + "---|" * len(rows))
    for name in names:
        cells = [f"{row[name]:.4g}" if isinstance(row[name], float) else str(row[name]) for row in rows.values()]
        print(f"| {name} | " + " | ".join(cells) + " |")

    figure, axes = plt.subplots(figsize=(5, 4))
    shown = axes.imshow(image, cmap="inferno")
    figure.colorbar(shown, ax=axes, label="°C")
    axes.set_title("Simulated 320x256 thermal frame (50 mK NETD)")
    figure.tight_layout()
    figure.savefig(args.out / "thermal_frame.png", dpi=110)
    plt.close(figure)


if __name__ == "__main__":
    main()

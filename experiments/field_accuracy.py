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

from services.fusion.field import temperature_field  # noqa: E402
from services.fusion.fuse import ThermalView  # noqa: E402
from services.geometry.camera import camera_center  # noqa: E402
from services.simulation.presets import forging_rig, forging_scene  # noqa: E402
from services.simulation.render import CameraEffects, render_frames, render_view  # noqa: E402
from services.simulation.thermal import (  # noqa: E402
    ThermalEffects, forging_temperatures, render_thermal, seen_by, surface_temperature,
)
from services.structured_light.patterns import generate_sequence, render_patterns  # noqa: E402
from services.structured_light.reconstruct import reconstruct_points  # noqa: E402


def simulate(seed: int = 0):
    """The forging rig, its capture and thermal frame, and per-pixel ground truth."""
    rig, scene, temperatures = forging_rig(), forging_scene(), forging_temperatures()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    rng = np.random.default_rng(seed)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    view = render_view(scene, camera, projector, supersample=3)
    frames = render_frames(view, patterns if patterns is not None else render_patterns(sequence), rng,
                           CameraEffects(noise_sigma=1.0))
    image = render_thermal(scene, temperatures, thermal, ThermalEffects(netd=0.05), rng)
    return rig, scene, temperatures, sequence, frames, image, view.truth


def evaluate(cloud, rig, scene, temperatures, truth, image) -> tuple[dict, dict]:
    """Fuse ``cloud`` (which has camera pixels u, v) and score it against the truth at those pixels."""
    camera, thermal = rig.devices["camera"], rig.devices["thermal"]
    field = temperature_field(cloud, [ThermalView(thermal, image)],
                              camera_center(camera.R_array, camera.t_array))
    row, column = cloud["v"].astype(int), cloud["u"].astype(int)
    true_points = truth.points[row, column]
    on_surface = truth.surface[row, column] >= 0
    true_temperature = surface_temperature(temperatures, true_points, truth.surface[row, column])
    visible = np.zeros(len(row), dtype=bool)
    visible[on_surface] = seen_by(scene, thermal, true_points[on_surface])
    occluded = on_surface & ~visible
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


def render_field_picture(field: dict, path: Path, title: str) -> None:
    """An orthographic splat of the coloured points seen from the camera side, with a colour bar."""
    seen = np.isfinite(field["temperature"])
    x, y, z = field["x"], field["y"], field["z"]
    rgb = np.column_stack([field["red"], field["green"], field["blue"]]) / 255.0
    step = max(1, len(x) // 200_000)
    figure = plt.figure(figsize=(8, 5.5))
    axes = figure.add_subplot(projection="3d")
    order = np.argsort(-z[::step])
    axes.scatter(x[::step][order], z[::step][order], -y[::step][order], c=rgb[::step][order], s=0.3,
                 linewidths=0, depthshade=False)
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("z (mm)")
    axes.set_zlabel("-y (mm)")
    axes.view_init(elev=20, azim=-70)
    axes.set_box_aspect((np.ptp(x), np.ptp(z), np.ptp(y)))
    mappable = plt.cm.ScalarMappable(cmap="inferno", norm=plt.Normalize(np.nanmin(field["temperature"][seen]),
                                                                         np.nanmax(field["temperature"][seen])))
    figure.colorbar(mappable, ax=axes, shrink=0.6, label="temperature (°C); grey: unseen")
    axes.set_title(title)
    figure.tight_layout()
    figure.savefig(path, dpi=130)
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
    rows["exact cloud"], _ = evaluate(exact_cloud(truth), rig, scene, temperatures, truth, image)

    names = list(next(iter(rows.values())))
    print("| quantity | " + " | ".join(rows) + " |")
    print("|---|" + "---|" * len(rows))
    for name in names:
        cells = [f"{row[name]:.4g}" if isinstance(row[name], float) else str(row[name]) for row in rows.values()]
        print(f"| {name} | " + " | ".join(cells) + " |")

    render_field_picture(field, args.out / "forging_field.png", "Simulated forging: fused 3D temperature field")
    figure, axes = plt.subplots(figsize=(5, 4))
    shown = axes.imshow(image, cmap="inferno")
    figure.colorbar(shown, ax=axes, label="°C")
    axes.set_title("Simulated 320x256 thermal frame (50 mK NETD)")
    figure.tight_layout()
    figure.savefig(args.out / "thermal_frame.png", dpi=110)
    plt.close(figure)


if __name__ == "__main__":
    main()

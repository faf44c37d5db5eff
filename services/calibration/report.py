"""The pictures of a calibration report: per-view residual bars, residual vectors, corner coverage.

Each function returns a matplotlib ``Figure`` (object API, no global pyplot state); the caller
saves it.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

_VECTOR_GAIN_TARGET_PX = 40.0  # the largest residual arrow is drawn this long


def residual_bars(per_view_rms: np.ndarray, labels: list[str], overall_rms: float) -> Figure:
    """Bar chart of the reprojection RMS of every kept view, with the overall RMS as a line.

    Parameters
    ----------
    per_view_rms : (V,) array
        RMS reprojection error of each view in pixels.
    labels : list of str
        View names (image file names).
    overall_rms : float
        RMS over all features.
    """
    per_view_rms = np.asarray(per_view_rms, dtype=float)
    if len(labels) != len(per_view_rms):
        raise ValueError(f"Got {len(labels)} labels for {len(per_view_rms)} views.")
    figure = Figure(figsize=(max(6.0, 0.35 * len(labels) + 2), 4), layout="constrained")
    axes = figure.subplots()
    axes.bar(np.arange(len(labels)), per_view_rms, color="tab:blue")
    axes.axhline(overall_rms, color="tab:red", linestyle="--", label=f"overall RMS {overall_rms:.3f} px")
    axes.set_xticks(np.arange(len(labels)), labels, rotation=60, ha="right", fontsize=8)
    axes.set_ylabel("reprojection RMS (px)")
    axes.set_title("Per-view reprojection error")
    axes.legend()
    return figure


def residual_vectors(image_points: list[np.ndarray], residuals: list[np.ndarray],
                     image_size: tuple[int, int]) -> Figure:
    """Residual (observed minus reprojected) of every feature as an arrow at its image position.

    The arrows are magnified so that the largest is about 40 pixels long; the gain is in the
    title. A systematic swirl or radial pattern betrays a wrong lens model or a bent board.
    """
    points = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in image_points])
    vectors = np.concatenate([np.asarray(r, float).reshape(-1, 2) for r in residuals])
    if points.shape != vectors.shape:
        raise ValueError(f"image_points and residuals must match; got {points.shape} and {vectors.shape}.")
    largest = float(np.max(np.linalg.norm(vectors, axis=1), initial=0.0))
    gain = _VECTOR_GAIN_TARGET_PX / largest if largest > 0 else 1.0
    figure = Figure(figsize=(7, 7 * image_size[1] / image_size[0] + 0.6), layout="constrained")
    axes = figure.subplots()
    axes.quiver(points[:, 0], points[:, 1], vectors[:, 0] * gain, vectors[:, 1] * gain,
                angles="xy", scale_units="xy", scale=1, color="tab:red", width=0.002)
    _image_axes(axes, image_size)
    axes.set_title(f"Reprojection residuals x{gain:.0f} (largest {largest:.3f} px)")
    return figure


def coverage_map(image_points: list[np.ndarray], image_size: tuple[int, int], cells: int = 12) -> Figure:
    """Where the board features fell in the image: a count per cell with every feature dotted.

    Empty cells near the border mean the distortion there is extrapolated, not measured.
    """
    width, height = image_size
    points = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in image_points])
    rows = max(1, round(cells * height / width))
    counts, _, _ = np.histogram2d(points[:, 1], points[:, 0], bins=(rows, cells),
                                  range=((-0.5, height - 0.5), (-0.5, width - 0.5)))
    figure = Figure(figsize=(7, 7 * height / width + 0.6), layout="constrained")
    axes = figure.subplots()
    shown = axes.imshow(counts, extent=(-0.5, width - 0.5, height - 0.5, -0.5), cmap="viridis",
                        interpolation="nearest")
    axes.plot(points[:, 0], points[:, 1], ".", color="white", markersize=1.5)
    figure.colorbar(shown, ax=axes, label="features per cell")
    _image_axes(axes, image_size)
    empty = float(np.mean(counts == 0))
    axes.set_title(f"Feature coverage ({100 * empty:.0f}% of cells empty)")
    return figure


def _image_axes(axes, image_size: tuple[int, int]) -> None:
    width, height = image_size
    axes.set_xlim(-0.5, width - 0.5)
    axes.set_ylim(height - 0.5, -0.5)
    axes.set_aspect("equal")
    axes.set_xlabel("u (px)")
    axes.set_ylabel("v (px)")

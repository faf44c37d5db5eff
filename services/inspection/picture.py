"""A colour-mapped picture of the deviation map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.formats.files import atomic_output


def deviation_picture(points_part: np.ndarray, deviation: np.ndarray, tolerance: tuple[float, float],
                      path: str | Path, title: str = "") -> Path:
    """Save a PNG of the part's points seen along their least principal axis, coloured by deviation (mm).

    The diverging map spans the surface tolerance, so saturated blue (missing material) or red
    (excess) is at or beyond a limit.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finite = np.isfinite(deviation) & np.isfinite(points_part).all(axis=1)
    points, values = points_part[finite], deviation[finite]
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov(centred.T)) if len(points) > 3 else (None, np.eye(3))
    plane = centred @ vectors[:, [2, 1]]
    span = max(abs(tolerance[0]), abs(tolerance[1]))
    figure, axes = plt.subplots(figsize=(8, 5), dpi=120)
    order = np.argsort(np.abs(values))  # extremes drawn last, on top
    scatter = axes.scatter(plane[order, 0], plane[order, 1], c=values[order], s=0.5, cmap="coolwarm",
                           vmin=-span, vmax=span, linewidths=0)
    axes.set_aspect("equal")
    axes.set_xlabel("mm along the part's first principal axis")
    axes.set_ylabel("mm along its second")
    axes.set_title(title or "deviation from the nominal surface")
    figure.colorbar(scatter, ax=axes, label="deviation, mm (cold-equivalent)")
    figure.tight_layout()
    try:
        with atomic_output(path) as temporary:
            figure.savefig(temporary)
    finally:
        plt.close(figure)
    return Path(path)

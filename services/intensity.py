"""Grey-level stretching shared by registration, board detection and the thermal board views."""

from __future__ import annotations

import numpy as np

STRETCH_PERCENTILES = (0.5, 99.5)


def percentile_stretch(image: np.ndarray, out_max: float = 1.0,
                       percentiles: tuple[float, float] = STRETCH_PERCENTILES) -> np.ndarray:
    """Map an image's grey levels linearly so that its low and high percentiles become 0 and ``out_max``.

    Parameters
    ----------
    image : array
        Any numeric image; NaN and infinite pixels are ignored and become 0.
    out_max : float
        The value the high percentile maps to (255 for 8 bits, 65535 for 16 bits).
    percentiles : (float, float)
        The percentiles that map to 0 and ``out_max`` (default 0.5 and 99.5: robust to a few hot or dead
        pixels).

    Returns
    -------
    stretched : float32 array
        Clipped to [0, out_max]. A flat image (high <= low) is shifted to 0 without scaling.

    Raises
    ------
    ValueError
        When the image has no finite pixel.
    """
    values = np.asarray(image)
    finite = np.isfinite(values) if np.issubdtype(values.dtype, np.floating) else None
    sample = values if finite is None else values[finite]
    if sample.size == 0:
        raise ValueError("The image has no finite pixel.")
    low, high = np.percentile(sample, percentiles)
    span = high - low if high > low else 1.0
    stretched = (values.astype(np.float32) - np.float32(low)) * np.float32(out_max / span)
    if finite is not None:
        stretched[~finite] = 0.0
    return np.clip(stretched, 0.0, out_max)

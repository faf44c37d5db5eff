"""Intensity preprocessing that makes visible and infrared images comparable before MI registration.

Every function takes a 2-D grey image of any numeric type and returns float32
in [0, 1]. ``"paper"`` is the paper's recipe (invert the visible image, then
equalise its histogram); ``"clahe"`` equalises locally, which copes with a hot
part that dominates the infrared histogram; ``"gradient"`` compares edge
strength, which is blind to how bright a surface is in either band.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.intensity import STRETCH_PERCENTILES, percentile_stretch

PREPROCESSING = ("paper", "clahe", "gradient", "none")



def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"Registration works on 2-D grey images; got shape {image.shape}.")
    if min(image.shape) < 16:
        raise ValueError(f"The image is too small to register ({image.shape[1]}x{image.shape[0]} pixels).")
    if not np.issubdtype(image.dtype, np.number):
        raise ValueError(f"The image must be numeric; got {image.dtype}.")
    return image


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Stretch any grey image to uint8 between its 0.5th and 99.5th percentiles.

    8-bit images are returned unchanged, so 16-bit infrared counts and float
    temperatures become displayable and equalisable.
    """
    image = _check_image(image)
    if image.dtype == np.uint8:
        return image
    return np.rint(percentile_stretch(image, 255.0)).astype(np.uint8)


def invert_equalize(image: np.ndarray, invert: bool = True) -> np.ndarray:
    """The paper's preprocessing: anti-colour (negative) image, then global histogram equalisation.

    References
    ----------
    .. [1] Paper, section 4, Figure 11.
    """
    grey = to_uint8(image)
    if invert:
        grey = 255 - grey
    return cv2.equalizeHist(grey).astype(np.float32) / 255.0


def clahe(image: np.ndarray, invert: bool = False, clip_limit: float = 2.0, tiles: int = 8) -> np.ndarray:
    """Contrast-limited adaptive histogram equalisation (OpenCV), optionally of the negative image.

    References
    ----------
    .. [1] K. Zuiderveld, "Contrast limited adaptive histogram equalization",
       Graphics Gems IV, 1994.
    """
    if clip_limit <= 0.0 or tiles < 1:
        raise ValueError(f"CLAHE needs a positive clip limit and tile count; got {clip_limit} and {tiles}.")
    grey = to_uint8(image)
    if invert:
        grey = 255 - grey
    equaliser = cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tiles, tiles))
    return equaliser.apply(grey).astype(np.float32) / 255.0


def gradient_magnitude(image: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Gaussian-smoothed gradient magnitude, scaled to [0, 1] at its 99.5th percentile.

    Notes
    -----
    |grad I| = sqrt((dI/dx)^2 + (dI/dy)^2) from Scharr derivatives of the image
    blurred with a Gaussian of standard deviation ``sigma`` pixels. The result
    does not depend on the sign of the contrast, so no inversion is needed.
    """
    if sigma < 0.0:
        raise ValueError(f"The gradient smoothing sigma must be non-negative; got {sigma}.")
    grey = to_uint8(image).astype(np.float32)
    if sigma > 0.0:
        grey = cv2.GaussianBlur(grey, (0, 0), sigma)
    dx = cv2.Scharr(grey, cv2.CV_32F, 1, 0)
    dy = cv2.Scharr(grey, cv2.CV_32F, 0, 1)
    # not cv2.magnitude: its SIMD path rounds by the buffers' memory alignment, so the same image could
    # register to a different matrix from one call to the next
    magnitude = np.sqrt(dx * dx + dy * dy)
    top = float(np.percentile(magnitude, STRETCH_PERCENTILES[1]))
    return np.clip(magnitude / (top if top > 0.0 else 1.0), 0.0, 1.0).astype(np.float32)


def preprocess(image: np.ndarray, method: str, invert: bool = False) -> np.ndarray:
    """Apply one named preprocessing; ``invert`` is for the visible image (its negative resembles infrared).

    Parameters
    ----------
    image : 2-D array
        Grey image (uint8, uint16 or float).
    method : {"paper", "clahe", "gradient", "none"}
        See the module docstring.
    invert : bool
        Use the negative image (ignored by ``"gradient"``).

    Returns
    -------
    float32 array in [0, 1] of the image's shape.
    """
    if method == "paper":
        return invert_equalize(image, invert)
    if method == "clahe":
        return clahe(image, invert)
    if method == "gradient":
        return gradient_magnitude(image)
    if method == "none":
        grey = to_uint8(image)
        return (255 - grey if invert else grey).astype(np.float32) / 255.0
    raise ValueError(f"Unknown preprocessing {method!r}; choose one of {', '.join(PREPROCESSING)}.")

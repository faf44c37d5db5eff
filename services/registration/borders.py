"""Find the pixels of an image that carry no data: a border that a move or a crop brought in, or padding.

A moved, rotated or cropped image is padded with one constant value where
the original did not reach, and a camera or an export may add constant
bars. Such a border draws a straight, strong edge against the data that the
other image does not have; registration must not take it for structure.
It is found from the image itself: the regions of the image's least or
greatest value connected to the image border, less what lies inside the
convex outline of the rest. A
moved or cropped rectangle is convex, so its padding lies wholly outside
that outline; a constant region inside it (a saturated sky between roofs,
touching the border) keeps its outline as structure.
"""

from __future__ import annotations

import cv2
import numpy as np

_MIN_RUN = 8  # a border value is a candidate only where it runs this many pixels along the image border


def _run_starts(image: np.ndarray) -> list[tuple[int, int]]:
    """(row, column) of one pixel of every run of at least ``_MIN_RUN`` pixels along the image border of the
    image's minimum or maximum value."""
    height, width = image.shape
    rows = np.concatenate([np.zeros(width - 1, int), np.arange(height - 1), np.full(width - 1, height - 1),
                           np.arange(height - 1, 0, -1)])
    columns = np.concatenate([np.arange(width - 1), np.full(height - 1, width - 1), np.arange(width - 1, 0, -1),
                              np.zeros(height - 1, int)])
    ring = image[rows, columns]
    starts = np.flatnonzero(np.concatenate([[True], ring[1:] != ring[:-1]]))
    lengths = np.diff(np.concatenate([starts, [ring.size]]))
    if ring[0] == ring[-1] and starts.size > 1:  # the ring closes: its last run continues its first
        lengths[0] += lengths[-1]
        lengths[-1] = lengths[0]
    extreme = np.isin(ring[starts], [image.min(), image.max()])
    return [(int(rows[start]), int(columns[start])) for start in starts[(lengths >= _MIN_RUN) & extreme]]


def data_mask(image: np.ndarray) -> np.ndarray | None:
    """The pixels that carry data: all but a constant border that a move, a crop or padding brought in.

    Parameters
    ----------
    image : 2-D array
        Grey image of any numeric type.

    Returns
    -------
    2-D bool array or None
        True where the pixel carries data; None when every pixel does (no
        such border found), so that callers can keep their unmasked path.

    Notes
    -----
    With C the union of the 4-connected regions of the image's minimum or
    maximum value (what padding brings in: 0, or the largest value) that run
    at least 8 pixels along the image border, and D the rest of the image,
    the pixels without data are C minus the convex hull of D. The padding of
    a rectangle moved by a similarity or cut by a crop lies outside the
    convex hull of the rectangle's pixels; a constant region of the scene
    that reaches into the hull of the others keeps its edges there.
    Interpolation blends the last pixel before the padding with it, so that
    pixel is not constant: the pixels next to those without data are counted
    without data too.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"The border mask needs a 2-D grey image; got shape {image.shape}.")
    # OpenCV's flood fill takes 8-bit and 32-bit float images; 16-bit counts are exact in float32
    values = image if image.dtype == np.uint8 else image.astype(np.float32)
    filled = np.zeros((image.shape[0] + 2, image.shape[1] + 2), np.uint8)  # the fill's mask has a 1 px frame
    flags = 4 | cv2.FLOODFILL_MASK_ONLY | cv2.FLOODFILL_FIXED_RANGE | (1 << 8)
    for row, column in _run_starts(values):
        if not filled[row + 1, column + 1]:
            cv2.floodFill(values, filled, (column, row), 0, 0, 0, flags)
    constant = filled[1:-1, 1:-1]
    if not constant.any():
        return None
    data = constant == 0
    rows = np.flatnonzero(data.any(axis=1))
    if rows.size == 0:
        return None  # a constant image: nothing to register, and the caller says so
    # the hull of the data is the hull of each row's first and last data pixel
    first = data[rows].argmax(axis=1)
    last = data.shape[1] - 1 - data[rows, ::-1].argmax(axis=1)
    points = np.concatenate([np.stack([first, rows], axis=1), np.stack([last, rows], axis=1)]).astype(np.int32)
    hull = np.zeros(image.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(points), 1)  # a single pixel or a line too
    without_data = ((constant == 1) & (hull == 0)).astype(np.uint8)
    if not without_data.any():
        return None
    # and the pixels next to them: a bilinear resampling blends the last pixel before the padding with it
    return cv2.dilate(without_data, np.ones((3, 3), np.uint8)) == 0

"""Calibration-board feature detection with automatic polarity and sub-pixel corner refinement."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from services.formats.board import BoardSpec, CharucoSpec, ChessboardSpec, CirclesSpec
from services.intensity import percentile_stretch

# Half-window of the saddle-point refinement as a fraction of the local corner spacing: the
# window then covers the four squares around a corner but never reaches a neighbouring corner.
# A calibration chooses its own fraction from its views (services.calibration.corner_window).
DEFAULT_WINDOW_FRACTION = 0.25
_MIN_HALF_WINDOW = 2
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
_WEAKEST_CORNER = 0.3  # every detected corner must be an X-junction this strong relative to the median
_UPSAMPLE_BELOW = 480  # frames smaller than this (shorter side) are also searched at twice the size
_DOWNSAMPLE_FROM = 960  # frames at least this large (shorter side) are also searched at half the size
_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
_SECTOR_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE


@dataclass(frozen=True)
class BoardDetection:
    """Board features found in one image.

    Attributes
    ----------
    image_points : (N, 2) float64 array
        Feature positions in pixels (pixel centres at integers).
    ids : (N,) int array
        Row-major indices of the features in ``board.object_points()``.
    polarity : {"normal", "inverted"}
        How the board appeared: dark features on light, or light on dark.
    """

    image_points: np.ndarray
    ids: np.ndarray
    polarity: str


def detect_board(image: np.ndarray, board: BoardSpec) -> BoardDetection | None:
    """Find a calibration board in a grey image and refine its features to sub-pixel accuracy.

    Parameters
    ----------
    image : (H, W) uint8 or uint16 array
        Grey frame; 16-bit frames (infrared) are stretched to their 0.5-99.5 percentile range.
    board : BoardSpec
        The board; its ``polarity`` says whether to look for dark-on-light ("normal"),
        light-on-dark ("inverted") features, or both ("auto", normal first).

    Returns
    -------
    detection : BoardDetection or None
        None when the whole board (a chessboard or circle grid) or fewer than six
        ChArUco corners are found.

    Notes
    -----
    Chessboards are located by OpenCV's sector-based detector [2]_, falling back to the quad
    detector (which finds boards whose quiet zone is cut by the image border but misplaces
    the outer corners of a board without a light frame, such as a hollowed infrared board)
    and, for frames under 480 pixels, to both on a twice-upsampled frame (for frames of 960 pixels
    or more, on a half-size frame: the sector detector misses large, dim, unevenly lit boards, such
    as SLStudio's calibration sequence 2, at full size). Each corner is
    refined as the saddle point of the intensity, the point q where
    sum_i (grad I(p_i) . (p_i - q)) = 0 over a window [1]_ (``cv2.cornerSubPix``). The half
    window is a quarter of the corner's distance to its nearest neighbour, so it adapts to
    the imaged square size and perspective instead of being tuned by hand: on OpenCV's own
    chessboard images this halves the reprojection error of the usual fixed 11x11 window.
    A detection is discarded when one of its corners is not an X-junction (a misplaced
    corner), and refused when X-junctions continue the grid beyond a side (the board is
    larger than its specification). Chessboard corners are put in a canonical order
    (right-handed in the image, the square between features 0, 1, cols and cols+1 dark in
    the image) so that a visible and an infrared camera viewing one board agree on which
    corner is which.

    References
    ----------
    .. [1] W. Foerstner, E. Guelch, "A fast operator for detection and precise location of
       distinct points, corners and centres of circular features", ISPRS Intercommission
       Workshop, Interlaken, 1987.
    .. [2] A. Duda, U. Frese, "Accurate detection and localization of checkerboard corners for
       calibration", BMVC 2018.
    """
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"The image must be a 2-D uint8 or uint16 array; got {image.dtype} {image.shape}.")
    levels = _grey_levels(image)
    grey = np.round(levels).astype(np.uint8)
    polarities = ("normal", "inverted") if board.polarity == "auto" else (board.polarity,)
    if isinstance(board, ChessboardSpec):
        return _detect_chessboard(grey, levels, board, polarities)
    for polarity in polarities:
        view = grey if polarity == "normal" else 255 - grey
        if isinstance(board, CharucoSpec):
            found = _detect_charuco(view, levels, board)
        else:
            found = _detect_circles(view, board)
        if found is not None:
            points, ids = found
            return BoardDetection(points.astype(np.float64), ids.astype(int), polarity)
    return None


def _grey_levels(image: np.ndarray) -> np.ndarray:
    """The frame as float32 on a 0..255 scale; 16-bit frames stretched, keeping their fine levels."""
    if image.dtype == np.uint8:
        return image.astype(np.float32)
    return percentile_stretch(image, 255.0)


def _detect_chessboard(grey: np.ndarray, levels: np.ndarray, board: ChessboardSpec,
                       polarities: tuple[str, ...]) -> BoardDetection | None:
    """Locate on the 8-bit ``grey`` (each locator with every polarity), refine and check on ``levels``."""
    size = board.pattern_size
    scales = (1, 2) if min(grey.shape) < _UPSAMPLE_BELOW else (1, 0.5) if min(grey.shape) >= _DOWNSAMPLE_FROM else (1,)
    for scale in scales:
        interpolation = cv2.INTER_CUBIC if scale > 1 else cv2.INTER_AREA
        frame = grey if scale == 1 else cv2.resize(grey, None, fx=scale, fy=scale, interpolation=interpolation)
        for locate in (_locate_by_sectors, _locate_by_quads):
            for polarity in polarities:
                corners = locate(frame if polarity == "normal" else 255 - frame, size)
                if corners is None:
                    continue
                corners = refine_corners(levels, (corners + 0.5) / scale - 0.5)
                grid = corners.reshape(size[1], size[0], 2)
                strength = _saddle_strength(levels, corners, grid)
                if strength.min() < _WEAKEST_CORNER * np.median(strength):
                    continue  # a misplaced corner: an outer corner of a board without a light frame
                if _grid_continues(levels, grid):
                    return None
                corners = _canonical_chessboard_order(levels, corners, size)
                return BoardDetection(corners, np.arange(len(corners)), polarity)
    return None


def _grid_continues(levels: np.ndarray, grid: np.ndarray) -> bool:
    """Whether the board has more corners than specified on some side (a spec/board mismatch).

    The corner row or column beyond each side is extrapolated and refined; a side continues
    when most of those points are X-junctions at least half as strong as the detected corners.
    """
    strength = np.median(_saddle_strength(levels, grid.reshape(-1, 2), grid))
    beyond = (2 * grid[0] - grid[1], 2 * grid[-1] - grid[-2], 2 * grid[:, 0] - grid[:, 1], 2 * grid[:, -1] - grid[:, -2])
    return any(np.mean(_saddle_strength(levels, _refine_inside(levels, side), grid) > 0.5 * strength) > 0.5
               for side in beyond)


def _refine_inside(levels: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Refine the points that lie inside the image; leave the others where they are."""
    height, width = levels.shape
    inside = (points[:, 0] >= 0) & (points[:, 0] <= width - 1) & (points[:, 1] >= 0) & (points[:, 1] <= height - 1)
    if inside.sum() < 2:
        return points
    refined = points.copy()
    refined[inside] = refine_corners(levels, points[inside])
    return refined


def _saddle_strength(levels: np.ndarray, points: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Second minus first angular harmonic amplitude of the intensity on a ring around each point.

    An X-junction (a chessboard corner) alternates four times around the ring: a strong second
    harmonic (2/pi of the contrast) and no first. The T-junctions where the outer squares meet
    the board's margin score below zero, edges, blobs and flat areas about zero. Points whose
    ring leaves the image get zero.
    """
    spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1))
    radius = 0.3 * spacing
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring_x = points[:, :1] + radius * np.cos(angles)
    ring_y = points[:, 1:] + radius * np.sin(angles)
    height, width = levels.shape
    inside = np.all((ring_x >= 0) & (ring_x <= width - 1) & (ring_y >= 0) & (ring_y <= height - 1), axis=1)
    values = cv2.remap(levels.astype(np.float32), ring_x.astype(np.float32), ring_y.astype(np.float32),
                       cv2.INTER_LINEAR)
    second = 2 * np.abs(values @ np.exp(-2j * angles)) / len(angles)
    first = 2 * np.abs(values @ np.exp(-1j * angles)) / len(angles)
    return np.where(inside, second - first, 0.0)


def _locate_by_quads(view: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    found, corners = cv2.findChessboardCorners(view, size, flags=_CLASSIC_FLAGS)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def _locate_by_sectors(view: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    found, corners = cv2.findChessboardCornersSB(view, size, flags=_SECTOR_FLAGS)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def _detect_charuco(grey: np.ndarray, levels: np.ndarray, board: CharucoSpec) -> tuple[np.ndarray, np.ndarray] | None:
    detector = cv2.aruco.CharucoDetector(board.opencv_board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) < 6:
        return None
    return refine_corners(levels, corners.reshape(-1, 2)), ids.ravel()


def _detect_circles(grey: np.ndarray, board: CirclesSpec) -> tuple[np.ndarray, np.ndarray] | None:
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if board.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    found, centres = cv2.findCirclesGrid(grey, board.pattern_size, flags=flags)
    if not found:
        return None
    return centres.reshape(-1, 2), np.arange(len(centres))


def refine_corners(image: np.ndarray, corners: np.ndarray,
                   window_fraction: float = DEFAULT_WINDOW_FRACTION) -> np.ndarray:
    """Refine chessboard corners to the intensity saddle point with a spacing-derived window.

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float32 array
        The image (16-bit frames are stretched as in ``detect_board``).
    corners : (N, 2) array, N >= 2
        Approximate corner positions in pixels.
    window_fraction : float, optional
        Half window as a fraction of each corner's distance to its nearest neighbour, in (0, 0.5).

    Returns
    -------
    refined : (N, 2) float64 array

    Notes
    -----
    Each corner gets its own half window, ``window_fraction`` (by default a quarter) of the
    distance to its nearest neighbouring corner (at least 2 pixels), then ``cv2.cornerSubPix``;
    see ``detect_board``.
    """
    corners = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
    if len(corners) < 2:
        raise ValueError(f"At least two corners are needed to derive the refinement window; got {len(corners)}.")
    if not 0 < window_fraction < 0.5:
        raise ValueError(f"The window fraction must lie between 0 and 0.5 of the corner spacing; got {window_fraction}.")
    spacing = cKDTree(corners).query(corners, k=2)[0][:, 1]
    half_windows = np.maximum(_MIN_HALF_WINDOW, np.floor(window_fraction * spacing)).astype(int)
    refined = corners.copy()
    image = np.asarray(image)
    image = _grey_levels(image) if image.dtype in (np.uint8, np.uint16) else image.astype(np.float32)
    for half in np.unique(half_windows):
        chosen = half_windows == half
        block = refined[chosen].reshape(-1, 1, 2).copy()
        refined[chosen] = cv2.cornerSubPix(image, block, (int(half), int(half)), (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2)
    return refined.astype(np.float64)


def _canonical_chessboard_order(levels: np.ndarray, corners: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    cols, rows = size
    grid = corners.reshape(rows, cols, 2)
    along_row, across_rows = grid[0, -1] - grid[0, 0], grid[-1, 0] - grid[0, 0]
    if along_row[0] * across_rows[1] - along_row[1] * across_rows[0] < 0:
        grid = grid[:, ::-1]
    if (cols + rows) % 2 == 1:
        if _square_brightness(levels, grid, 0) > _square_brightness(levels, grid, 1):
            grid = grid[::-1, ::-1]
    elif grid[-1, -1].sum() < grid[0, 0].sum():
        grid = grid[::-1, ::-1]
    return np.ascontiguousarray(grid).reshape(-1, 2)


def _square_brightness(levels: np.ndarray, grid: np.ndarray, column: int) -> float:
    """Mean intensity near the centre of the square between corners (0, column) and (1, column + 1)."""
    centre = grid[0:2, column:column + 2].reshape(-1, 2).mean(axis=0)
    patch = cv2.getRectSubPix(levels, (3, 3), (float(centre[0]), float(centre[1])))
    return float(patch.mean())

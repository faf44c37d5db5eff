"""Corner refinement in the board's own frame: the views rectified to a fronto-parallel board, refined there,
mapped back."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from services.calibration.camera import CameraCalibration, DistortionModel, calibrate_camera

FRONTAL_UPSAMPLING = 3.0  # frontal square = 3x the median imaged corner spacing ...
FRONTAL_SQUARE_PX = (24.0, 256.0)  # ... within these bounds (the cap bounds the cost; at 64 px it was coarser than large sharp views)
_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


def flatten_squares(frontal: np.ndarray, objects: np.ndarray, low: np.ndarray, per_mm: float,
                    square_mm: float) -> np.ndarray:
    """Normalise a fronto-parallel chessboard image so that its light squares are 1 and its dark squares 0.

    Parameters
    ----------
    frontal : (H, W) float array
        The view resampled on a board-aligned lattice (``refine_corners_frontal``).
    objects : (N, 3) array
        The corners' board coordinates (mm), multiples of ``square_mm``.
    low : (2,) array
        Board coordinates (mm) of the lattice's pixel (0, 0).
    per_mm : float
        Lattice pixels per board millimetre.
    square_mm : float
        The board's corner spacing in mm.

    Returns
    -------
    (H, W) float32 array
        ``(I - dark) / (light - dark)``.

    Notes
    -----
    The level of the light squares and that of the dark squares are each fitted by a quadratic surface over
    the board, from the median of the central half of every square around the corners (which squares are
    light is read from the two parities' mean levels). A hollowed board before a heater glows through its
    holes with the heater's fall-off, so the two light squares of a junction differ and a light square has a
    ramp inside: the saddle point (the point q with sum_i (grad I(p_i) . (p_i - q)) = 0 [1]_) moves, by a
    pattern fixed to the board, the same in every view, which no view resampling sees and which biased the
    focal length low on the simulated hollow boards. Flattening is the flat-field correction of photogrammetry
    for a target of known layout; on an evenly lit board it is an affine change of the grey levels, to which
    the saddle point is blind.

    References
    ----------
    .. [1] W. Foerstner, E. Guelch, "A fast operator for detection and precise location of distinct points,
       corners and centres of circular features", ISPRS Intercommission Workshop, Interlaken, 1987.
    """
    frontal = np.asarray(frontal, np.float32)
    if frontal.ndim != 2 or per_mm <= 0 or square_mm <= 0:
        raise ValueError(f"Flattening needs a grey (H, W) board image and positive scales; got shape {frontal.shape}, "
                         f"{per_mm} px/mm and a {square_mm} mm spacing.")
    cells = np.round(objects[:, :2] / square_mm).astype(int)
    columns = np.arange(cells[:, 0].min() - 1, cells[:, 0].max() + 1)
    rows = np.arange(cells[:, 1].min() - 1, cells[:, 1].max() + 1)
    side = square_mm * per_mm
    centres, levels, parity = [], [], []
    for j in rows:
        for i in columns:
            u, v = ((np.array([i, j]) + 0.5) * square_mm - low) * per_mm
            h = side / 4
            patch = frontal[int(round(v - h)):int(round(v + h)) + 1, int(round(u - h)):int(round(u + h)) + 1]
            if patch.size:
                centres.append((u, v)), levels.append(float(np.median(patch))), parity.append((i + j) % 2)
    centres, levels, parity = np.array(centres), np.array(levels), np.array(parity)
    light_parity = int(levels[parity == 1].mean() > levels[parity == 0].mean())
    height, width = frontal.shape
    scale = max(width, height)

    def surface(mask):
        x, y = centres[mask, 0] / scale, centres[mask, 1] / scale
        design = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
        coefficients = np.linalg.lstsq(design, levels[mask], rcond=None)[0]
        u, v = np.meshgrid(np.arange(width) / scale, np.arange(height) / scale)
        return sum(c * term for c, term in zip(coefficients, (1.0, u, v, u * u, u * v, v * v)))

    light, dark = surface(parity == light_parity), surface(parity != light_parity)
    contrast = light - dark
    contrast = np.where(np.abs(contrast) < 1e-6, 1e-6, contrast)
    return ((frontal - dark) / contrast).astype(np.float32)


def refine_corners_frontal(image: np.ndarray, object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray,
                           dist: np.ndarray, R: np.ndarray, t: np.ndarray, square_mm: float,
                           window_fraction: float, flatten: bool = True) -> np.ndarray:
    """Refine one view's chessboard corners on the image rectified to a fronto-parallel board.

    Parameters
    ----------
    image : (H, W) array
        The board view.
    object_points : (N, 3) array
        The corners' board coordinates (mm, z = 0).
    image_points : (N, 2) array
        Their current image positions (used for the imaged corner spacing).
    K, dist, R, t : arrays
        A calibration of the camera and this view's board pose (x_cam = R x_board + t).
    square_mm : float
        The board's corner spacing in mm.
    window_fraction : float
        Half window of the saddle-point refinement as a fraction of the corner spacing, in (0, 0.5).
    flatten : bool
        Normalise the squares' levels first (``flatten_squares``), so that an uneven glow or light does not
        move the saddle points.

    Returns
    -------
    (N, 2) float64 array
        The refined corners in the image.

    Notes
    -----
    The image is resampled on a board-aligned lattice (board point X -> pixel proj(K, dist, R, t, X), bicubic),
    where every corner is an orthogonal X-junction of squares of one size; the saddle point is found there
    (``cv2.cornerSubPix``) and the refined board point is projected back with the same model, so the round
    trip adds no model error at the corner. In the image, perspective, the lens's curvature and the blur
    across a foreshortened junction bias the saddle point the same way in every view, which biases the
    focal length; in the board frame the junction is symmetric and the bias goes [1]_. The squares' levels
    are flattened first (``flatten_squares``): an uneven glow (a hollow board's heater) otherwise leaves a
    bias fixed to the board.

    References
    ----------
    .. [1] A. Datta, J.-S. Kim, T. Kanade, "Accurate camera calibration using iterative refinement of control
       points", IEEE ICCV Workshops, 1201-1208 (2009).
    """
    objects = np.asarray(object_points, np.float64).reshape(-1, 3)
    points = np.asarray(image_points, np.float64).reshape(-1, 2)
    if len(objects) != len(points) or len(objects) < 2:
        raise ValueError(f"Frontal refinement needs at least 2 matching board and image points; got {len(objects)} "
                         f"and {len(points)}.")
    if not 0 < window_fraction < 0.5:
        raise ValueError(f"The window fraction must lie between 0 and 0.5 of the corner spacing; got {window_fraction}.")
    if square_mm <= 0:
        raise ValueError(f"The corner spacing must be positive; got {square_mm} mm.")
    nearest = np.sort(np.linalg.norm(points[:, None] - points[None], axis=-1), axis=1)[:, 1]
    square_px = float(np.clip(FRONTAL_UPSAMPLING * np.median(nearest), *FRONTAL_SQUARE_PX))
    per_mm = square_px / square_mm
    low = objects[:, :2].min(axis=0) - square_mm
    size = np.ceil((objects[:, :2].max(axis=0) + square_mm - low) * per_mm).astype(int) + 1
    u, v = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    lattice = np.column_stack([u.ravel() / per_mm + low[0], v.ravel() / per_mm + low[1], np.zeros(u.size)])
    rvec = cv2.Rodrigues(np.asarray(R, np.float64))[0]
    tvec = np.asarray(t, np.float64).reshape(3)
    K, dist = np.asarray(K, np.float64), np.asarray(dist, np.float64)
    maps = cv2.projectPoints(lattice, rvec, tvec, K, dist)[0].reshape(size[1], size[0], 2).astype(np.float32)
    frontal = cv2.remap(np.asarray(image, np.float32), maps[..., 0], maps[..., 1], cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REPLICATE)
    if flatten:
        frontal = flatten_squares(frontal, objects, low, per_mm, square_mm)
    start = ((objects[:, :2] - low) * per_mm).astype(np.float32).reshape(-1, 1, 2)
    half = max(2, int(round(window_fraction * square_px)))
    refined = cv2.cornerSubPix(frontal, start, (half, half), (-1, -1), _CRITERIA).reshape(-1, 2)
    board = np.column_stack([refined / per_mm + low, np.zeros(len(refined))])
    return cv2.projectPoints(board, rvec, tvec, K, dist)[0].reshape(-1, 2)


def calibrate_with_frontal_refinement(images: Sequence[np.ndarray], object_points: Sequence[np.ndarray],
                                      image_points: Sequence[np.ndarray], image_size: tuple[int, int],
                                      distortion: DistortionModel, square_mm: float,
                                      window_fraction: float,
                                      flatten: bool = True) -> tuple[CameraCalibration, list[np.ndarray]]:
    """Calibrate, refine the kept views' corners in the board frame with that calibration, calibrate again, and
    keep the board-frame corners only if they fit the camera better.

    Returns the calibration and every view's corners (rejected views keep theirs). The board-frame corners are
    kept when their reprojection RMS is not above the image corners' (same views, same lens model): on
    simulated hollow-board views they lower it and remove a focal length bias, on OpenCV's real sample images
    they raise it (0.176 -> 0.188 px) and are not used. One pass suffices: a second changed the focal length by
    under 0.002 % on the tuning cameras. ``flatten`` (``flatten_squares``) is for plain chessboards: a ChArUco
    board's light squares carry markers, whose level is no light square's.
    """
    first = calibrate_camera(list(object_points), list(image_points), image_size, distortion, jackknife=False)
    refined = [np.asarray(p, np.float64) for p in image_points]
    for position, view in enumerate(first.views):
        refined[view] = refine_corners_frontal(images[view], object_points[view], image_points[view], first.K,
                                               first.dist, first.rotations[position], first.translations[position],
                                               square_mm, window_fraction, flatten)
    second = calibrate_camera(list(object_points), refined, image_size, distortion)
    if second.rms <= first.rms:
        return second, refined
    return calibrate_camera(list(object_points), list(image_points), image_size, distortion), list(image_points)

"""Visible/infrared test pairs with a known infrared-to-visible matrix, for tests, experiments and benchmarks.

Two sources: :func:`render_scene_pair` draws an analytic scene of hot and cold
parts (ellipses and rotated boxes) in both bands, each with its own intensity
mapping; :func:`infrared_from_visible` turns a real visible photograph into an
infrared-like image (negative, nonlinear tone curve, heat blobs, blur,
down-sampling, noise). Both sample the scene at ``matrix @ u`` for every
infrared pixel ``u``, so ``matrix`` is the ground truth of the registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.registration.models import similarity_about_centres

INFRARED_LEVELS = 2**14 - 1  # a 14-bit radiometric sensor


@dataclass(frozen=True)
class Shape:
    """An ellipse or a rotated box (centre, half-axes, angle) with a visible grey level and a temperature."""

    kind: str
    centre: tuple[float, float]
    half_axes: tuple[float, float]
    angle: float
    grey: float
    temperature: float


def random_transform(
    rng: np.random.Generator,
    moving_size: tuple[int, int],
    fixed_size: tuple[int, int],
    nominal_scale: float,
    max_shift: float = 40.0,
    max_angle: float = 5.0,
    max_scale_change: float = 0.10,
) -> np.ndarray:
    """A random similarity moving-to-fixed matrix around the centred nominal one.

    The shift of the centres (fixed pixels, each axis), rotation (degrees) and
    relative scale change are uniform in +-``max_shift``, +-``max_angle`` and
    +-``max_scale_change``.
    """
    moving_centre = (np.asarray(moving_size, dtype=float) - 1.0) / 2.0
    fixed_centre = (np.asarray(fixed_size, dtype=float) - 1.0) / 2.0
    scale = nominal_scale * (1.0 + rng.uniform(-max_scale_change, max_scale_change))
    angle = np.deg2rad(rng.uniform(-max_angle, max_angle))
    shift = rng.uniform(-max_shift, max_shift, size=2)
    return similarity_about_centres(moving_centre, fixed_centre, scale, angle, shift)


def random_scene(rng: np.random.Generator, width: int, height: int, count: int = 14) -> list[Shape]:
    """Random parts on a plant floor: a few hot forgings among cold fixtures, in fixed-image pixels."""
    shapes = []
    for index in range(count):
        hot = index < 4
        size = rng.uniform(0.04, 0.16) * min(width, height) * (1.6 if hot else 1.0)
        shapes.append(Shape(
            kind="ellipse" if rng.random() < 0.5 else "box",
            centre=(rng.uniform(0.1, 0.9) * width, rng.uniform(0.1, 0.9) * height),
            half_axes=(size, size * rng.uniform(0.4, 1.0)),
            angle=rng.uniform(0.0, np.pi),
            grey=rng.uniform(0.55, 0.95) if hot else rng.uniform(0.05, 0.7),
            temperature=rng.uniform(700.0, 1100.0) if hot else rng.uniform(20.0, 200.0),
        ))
    return shapes


def _paint(shapes: list[Shape], x: np.ndarray, y: np.ndarray, background: np.ndarray, value: str) -> np.ndarray:
    """The ``value`` field ("grey" or "temperature") at scene points (x, y); later shapes cover earlier ones."""
    image = background.copy()
    for shape in shapes:
        c, s = np.cos(shape.angle), np.sin(shape.angle)
        u = ((x - shape.centre[0]) * c + (y - shape.centre[1]) * s) / shape.half_axes[0]
        v = (-(x - shape.centre[0]) * s + (y - shape.centre[1]) * c) / shape.half_axes[1]
        inside = u * u + v * v <= 1.0 if shape.kind == "ellipse" else (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
        level = getattr(shape, value)
        if value == "temperature":
            level = level * (1.0 - 0.15 * (u * u + v * v).clip(0.0, 1.0))  # cooler towards the rim
        image[inside] = level if np.ndim(level) == 0 else level[inside]
    return image


def _supersampled_grid(width: int, height: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
    offsets = (np.arange(factor) + 0.5) / factor - 0.5
    xs = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    ys = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    return np.meshgrid(xs, ys)


def _box_average(image: np.ndarray, factor: int) -> np.ndarray:
    height, width = image.shape[0] // factor, image.shape[1] // factor
    return image.reshape(height, factor, width, factor).mean(axis=(1, 3))


def _to_counts(image: np.ndarray, low: float, high: float) -> np.ndarray:
    return np.rint(np.clip((image - low) / (high - low), 0.0, 1.0) * INFRARED_LEVELS).astype(np.uint16)


def render_scene_pair(
    rng: np.random.Generator,
    matrix: np.ndarray,
    fixed_size: tuple[int, int] = (1024, 768),
    moving_size: tuple[int, int] = (320, 256),
    noise: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Render one random scene as a uint8 visible image and a 14-bit uint16 infrared image.

    The visible image shows grey levels with mild texture and noise
    (``noise`` of full scale); the infrared image shows temperature, through
    a 3x3 supersampled pixel footprint, a 0.8 pixel optical blur and 50 mK
    equivalent noise, of the scene points ``matrix @ u``.
    """
    fixed_width, fixed_height = fixed_size
    moving_width, moving_height = moving_size
    shapes = random_scene(rng, fixed_width, fixed_height)
    xs, ys = np.meshgrid(np.arange(fixed_width, dtype=float), np.arange(fixed_height, dtype=float))
    floor = 0.35 + 0.25 * xs / fixed_width
    visible = _paint(shapes, xs, ys, floor, "grey")
    visible = cv2.GaussianBlur(visible.astype(np.float32), (0, 0), 0.7)
    visible += noise * rng.standard_normal(visible.shape).astype(np.float32)
    visible = np.rint(np.clip(visible, 0.0, 1.0) * 255.0).astype(np.uint8)

    grid_x, grid_y = _supersampled_grid(moving_width, moving_height, 3)
    points = np.stack([grid_x.ravel(), grid_y.ravel(), np.ones(grid_x.size)])
    scene = matrix @ points
    scene_x = (scene[0] / scene[2]).reshape(grid_x.shape)
    scene_y = (scene[1] / scene[2]).reshape(grid_x.shape)
    ambient = 25.0 + 30.0 * np.exp(-((scene_y - 0.8 * fixed_height) / (0.3 * fixed_height)) ** 2)
    temperature = _box_average(_paint(shapes, scene_x, scene_y, ambient, "temperature"), 3)
    temperature = cv2.GaussianBlur(temperature.astype(np.float32), (0, 0), 0.8)
    temperature += 0.05 * rng.standard_normal(temperature.shape).astype(np.float32)
    return visible, _to_counts(temperature, 0.0, 1200.0)


def infrared_from_visible(
    rng: np.random.Generator,
    visible: np.ndarray,
    matrix: np.ndarray,
    moving_size: tuple[int, int] = (320, 256),
    blobs: int = 2,
    noise: float = 0.01,
) -> np.ndarray:
    """An infrared-like 14-bit image of a real visible photograph, seen through ``matrix``.

    Modality change: negative image, gamma tone curve (gamma 0.6), ``blobs``
    Gaussian heat blobs unrelated to the visible content, 0.8 pixel optical
    blur, Gaussian noise (``noise`` of full scale); scene outside the visible
    frame is a flat warm background.
    """
    moving_width, moving_height = moving_size
    grey = np.asarray(visible, dtype=np.float32) / 255.0
    scale = float(np.sqrt(abs(np.linalg.det(matrix[:2, :2]))))
    if scale > 1.0:
        grey = cv2.GaussianBlur(grey, (0, 0), 0.5 * np.sqrt(scale**2 - 1.0))
    sampled = cv2.warpPerspective(grey, matrix, (moving_width, moving_height),
                                  flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0.5)
    infrared = (1.0 - np.clip(sampled, 0.0, 1.0)) ** 0.6
    ys, xs = np.mgrid[0:moving_height, 0:moving_width].astype(np.float32)
    for _ in range(blobs):
        cx, cy = rng.uniform(0.2, 0.8) * moving_width, rng.uniform(0.2, 0.8) * moving_height
        sigma = rng.uniform(0.08, 0.15) * moving_width
        infrared += rng.uniform(0.2, 0.4) * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2.0 * sigma**2))
    infrared = cv2.GaussianBlur(infrared, (0, 0), 0.8)
    infrared += noise * rng.standard_normal(infrared.shape).astype(np.float32)
    return _to_counts(infrared, 0.0, 1.6)


def _random_move(
    rng: np.random.Generator, max_shift: float, max_angle: float, scale_range: tuple[float, float]
) -> tuple[float, float, np.ndarray]:
    """Scale, rotation (radians) and shift (pixels) of a random similarity, drawn in this order."""
    scale = rng.uniform(*scale_range)
    angle = np.deg2rad(rng.uniform(-max_angle, max_angle))
    return scale, angle, rng.uniform(-max_shift, max_shift, size=2)


def moved_image(
    rng: np.random.Generator,
    image: np.ndarray,
    max_shift: float = 30.0,
    max_angle: float = 4.0,
    scale_range: tuple[float, float] = (0.93, 1.07),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image moved by a random similarity on a canvas of its own size, with the mask of what is known.

    The similarity S maps original pixels to moved pixels about the image
    centre: S(x) = c + d + s R(theta) (x - c), with each component of d
    uniform in +-``max_shift`` pixels, theta uniform in +-``max_angle``
    degrees and s uniform in ``scale_range`` (the draws of
    :func:`moved_view`). What the move brings in from outside the original is
    not invented: it is 0 and left out of the mask.

    Returns
    -------
    moved : 2-D array
        The moved image, of the image's shape and dtype (bilinear resampling).
    valid : 2-D bool array
        True where the moved pixel's bilinear support lies inside the original.
    moved_to_original : (3, 3) array
        S^-1: moved pixel coordinates to original pixel coordinates, so a
        registration H of the original becomes H @ S^-1 for the moved image.
    """
    image = np.asarray(image)
    height, width = image.shape[:2]
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    moved_to_original = np.linalg.inv(similarity_about_centres(centre, centre, *_random_move(
        rng, max_shift, max_angle, scale_range)))
    moved = cv2.warpAffine(image, moved_to_original[:2], (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    source_x = moved_to_original[0, 0] * xs + moved_to_original[0, 1] * ys + moved_to_original[0, 2]
    source_y = moved_to_original[1, 0] * xs + moved_to_original[1, 1] * ys + moved_to_original[1, 2]
    valid = (source_x >= 0.0) & (source_x <= width - 1.0) & (source_y >= 0.0) & (source_y <= height - 1.0)
    return moved, valid, moved_to_original


def moved_view(
    rng: np.random.Generator,
    image: np.ndarray,
    max_shift: float = 30.0,
    max_angle: float = 4.0,
    scale_range: tuple[float, float] = (0.93, 1.07),
    largest_fraction: float = 0.9,
) -> tuple[np.ndarray, np.ndarray]:
    """The image moved by a random similarity and cut to a view that lies wholly inside the original.

    The similarity S is drawn as by :func:`moved_image` and maps original
    pixels to moved pixels about the image and view centres: S(x) = c' + d +
    s R(theta) (x - c). The view keeps the original aspect ratio at the
    largest fraction (at most ``largest_fraction``) of its size whose every
    pixel comes from inside the original, so that no pixel is invented; it
    loses at least 19 % of the image's area to the cut, more than the move
    itself.

    Returns
    -------
    moved : 2-D array
        The moved view, of the image's dtype (bilinear resampling).
    view_to_original : (3, 3) array
        S^-1: moved-view pixel coordinates to original pixel coordinates, so
        a registration H of the original becomes H @ S^-1 for the view.
    """
    image = np.asarray(image)
    height, width = image.shape[:2]
    scale, angle, shift = _random_move(rng, max_shift, max_angle, scale_range)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    for fraction in np.arange(largest_fraction, 0.2, -0.01):
        size = (int(fraction * width), int(fraction * height))
        view_centre = (np.asarray(size, dtype=float) - 1.0) / 2.0
        forward = similarity_about_centres(centre, view_centre, scale, angle, shift)
        view_to_original = np.linalg.inv(forward)
        corners = np.array([[0.0, 0.0, 1.0], [size[0] - 1.0, 0.0, 1.0], [0.0, size[1] - 1.0, 1.0],
                            [size[0] - 1.0, size[1] - 1.0, 1.0]]) @ view_to_original.T
        if (corners[:, :2].min() >= 1.0 and corners[:, 0].max() <= width - 2.0
                and corners[:, 1].max() <= height - 2.0):
            break
    else:
        raise ValueError(f"No view of a {width}x{height} image stays inside it under a shift of {max_shift} px.")
    moved = cv2.warpAffine(image, view_to_original[:2], size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    return moved, view_to_original

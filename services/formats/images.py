"""Reading and writing camera frames (8- or 16-bit PNG, BMP, TIFF) with errors that name the file."""

from __future__ import annotations

import io
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from services.errors import InputError
from services.formats.files import atomic_output
from services.formats.limits import DEFAULT_MAX_PIXELS, check_image

FRAME_SUFFIXES = (".png", ".bmp", ".tif", ".tiff")


def read_frame(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read one frame as a 2-D grey array, keeping its bit depth (uint8 or uint16).

    Colour frames are converted to grey with OpenCV's luma weights. The header is checked before the
    pixels are decoded (:func:`services.formats.limits.check_image`): at most ``max_pixels``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: frame file is missing")
    try:
        content = path.read_bytes()
    except OSError as error:
        raise InputError(f"{path}: cannot read the frame ({error.strerror or error})") from None
    return decode_image(content, str(path), max_pixels=max_pixels)


def decode_image(content: bytes, source: str, *, max_pixels: int = DEFAULT_MAX_PIXELS,
                 size: tuple[int, int] | None = None, max_bytes: int | None = None) -> np.ndarray:
    """:func:`read_frame` of an image file's bytes (an upload); errors name ``source``.

    The header is checked first (:func:`services.formats.limits.check_image`: ``max_pixels``, the device's
    ``size`` and the ``max_bytes`` of memory when given); an error of the decoder (``cv2.error``, a failed
    allocation) is an ``InputError`` naming ``source``.
    """
    check_image(content, source, max_pixels=max_pixels, size=size, max_bytes=max_bytes)
    try:
        image = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
    except (cv2.error, MemoryError) as error:
        raise InputError(f"{source}: cannot decode the image ({type(error).__name__}: "
                         f"{str(error).strip().splitlines()[-1] if str(error).strip() else 'out of memory'})") from None
    return _grey_frame(image, source)


def _grey_frame(image: np.ndarray | None, source: str) -> np.ndarray:
    if image is None:
        raise InputError(f"{source}: cannot read the frame (not a readable PNG, BMP, TIFF or JPEG image, or corrupt)")
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{source}: frames must be 8- or 16-bit integers; this one is {image.dtype}")
    return image


def encode_frame(frame: np.ndarray, suffix: str) -> bytes:
    """One raw frame as an image file: ``png`` (a camera frame, its bit depth kept) or ``tiff`` (float32, for
    thermal frames in degrees Celsius)."""
    if suffix == "png":
        return png_bytes(frame)
    if suffix != "tiff":
        raise ValueError(f"Frames are encoded as png or tiff, not {suffix!r}.")
    import tifffile

    buffer = io.BytesIO()
    tifffile.imwrite(buffer, frame.astype(np.float32))
    return buffer.getvalue()


def png_bytes(image: np.ndarray) -> bytes:
    """An 8- or 16-bit grey or BGR image encoded as PNG."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.dtype} image of shape {image.shape} as PNG.")
    return encoded.tobytes()


def read_frame_stack(paths: list[Path]) -> np.ndarray:
    """Read frames into one (F, H, W) array; all must share size and bit depth.

    The files are decoded on one thread per CPU (OpenCV releases the GIL while it decodes).
    """
    if not paths:
        raise InputError("no frames to read")
    with ThreadPoolExecutor(max_workers=min(len(paths), os.cpu_count() or 1)) as pool:
        frames = pool.map(read_frame, paths)
        first = next(frames)
        stack = np.empty((len(paths),) + first.shape, dtype=first.dtype)
        stack[0] = first
        for index, (path, frame) in enumerate(zip(paths[1:], frames), start=1):
            _check_like_first(frame, path, first, paths[0])
            stack[index] = frame
    return stack


def _check_like_first(frame: np.ndarray, path: Path, first: np.ndarray, first_path: Path) -> None:
    if frame.shape != first.shape:
        raise InputError(
            f"{path}: frame is {frame.shape[1]}x{frame.shape[0]} but {first_path.name} is "
            f"{first.shape[1]}x{first.shape[0]}; all frames of a capture must have one size"
        )
    if frame.dtype != first.dtype:
        raise InputError(f"{path}: frame is {frame.dtype} but {first_path.name} is {first.dtype}")


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an 8- or 16-bit grey or BGR image as PNG, atomically."""
    write_image(path, image)


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an image in the format its suffix names (PNG, BMP, TIFF), atomically.

    Encoded in memory and written by Python, so that a full disk is reported as such
    (``cv2.imwrite`` only returns False).
    """
    path = Path(path)
    ok, encoded = cv2.imencode(path.suffix, image)
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode a {image.dtype} {image.shape} image as {path.suffix}.")
    with atomic_output(path) as temporary:
        temporary.write_bytes(encoded.tobytes())

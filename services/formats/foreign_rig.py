"""Calibrations written by other software, read into a rig (two devices, the first at the world origin).

Two formats, both OpenCV FileStorage files (XML or YAML, read with ``cv2.FileStorage``):

- ``slstudio``: SLStudio's ``calibration.xml``. ``Kc``, ``kc`` camera intrinsics and distortion,
  ``Kp``, ``kp`` the projector's, ``Rp``, ``Tp`` the projector pose in the camera frame
  (x_p = Rp x_c + Tp, mm), ``frameWidth``/``frameHeight`` the camera size and
  ``screenResX``/``screenResY`` the projector size.
- ``opencv-stereo``: the result of ``cv2.stereoCalibrate``: ``K1``, ``D1``, ``K2``, ``D2``
  (``M1``/``M2`` as in OpenCV's stereo sample are accepted for ``K1``/``K2``) and ``R``, ``T``
  with x_2 = R x_1 + T; the image sizes from ``imageSize1``/``imageSize2``, a shared
  ``imageSize`` (or ``image_size``), or the caller.

The world frame of the rig is the first device's frame. Conventions and error messages are
documented in docs/rig-file.md.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.errors import InputError
from services.formats.rig import Rig
from services.geometry.camera_model import VALID_DISTORTION_LENGTHS, CameraModel, DeviceKind

FOREIGN_FORMATS = ("slstudio", "opencv-stereo")
# Files store float32 matrices (SLStudio's have 9 significant digits): a rotation is accepted
# this far from orthonormal and then projected onto the nearest rotation.
_FILE_ROTATION_TOLERANCE = 1e-4


def import_rig(
    path: str | Path,
    file_format: str,
    *,
    names: tuple[str, str] = ("camera", "projector"),
    kinds: tuple[DeviceKind, DeviceKind] = ("camera", "projector"),
    sizes: tuple[tuple[int, int] | None, tuple[int, int] | None] = (None, None),
) -> Rig:
    """Read a foreign two-device calibration into a rig.

    Parameters
    ----------
    path : path
        The OpenCV FileStorage file (XML or YAML).
    file_format : {"slstudio", "opencv-stereo"}
    names, kinds : pairs of str
        Rig name and kind of the first device (the world frame) and of the second.
    sizes : pair of (width, height) or None
        Image sizes, needed for ``opencv-stereo`` files that do not store them; a size
        given here overrides the file's.

    Returns
    -------
    Rig
        The first device at the world origin (R = I, t = 0), the second at the file's pose.

    Raises
    ------
    InputError
        One line naming the file and the key: unreadable file, missing key, wrong shape,
        a non-finite value, not a rotation, an impossible intrinsic matrix.
    """
    if file_format not in FOREIGN_FORMATS:
        raise InputError(f"unknown calibration format {file_format!r}; expected one of {', '.join(FOREIGN_FORMATS)}")
    if names[0] == names[1]:
        raise InputError(f"the two devices need different names; both are {names[0]!r}")
    path = Path(path)
    storage = _open(path)
    try:
        reader = _Reader(storage, path)
        if file_format == "slstudio":
            keys = ("Kc", "kc", "Kp", "kp", "Rp", "Tp")
        else:
            keys = (reader.first_present("K1", "M1"), "D1", reader.first_present("K2", "M2"), "D2", "R", "T")
        K1, d1, K2, d2 = reader.intrinsics(keys[0]), reader.distortion(keys[1]), reader.intrinsics(keys[2]), \
            reader.distortion(keys[3])
        R, t = reader.rotation(keys[4]), reader.matrix(keys[5], (3, 1)).ravel()
        if file_format == "slstudio":
            file_sizes = ((reader.integer("frameWidth"), reader.integer("frameHeight")),
                          (reader.integer("screenResX"), reader.integer("screenResY")))
        else:
            file_sizes = reader.stereo_sizes()
    finally:
        storage.release()
    chosen = [given or found for given, found in zip(sizes, file_sizes)]
    for index, size in enumerate(chosen):
        if size is None:
            raise InputError(f"{path}: no image size for {names[index]} (keys imageSize{index + 1} or imageSize); "
                             f"pass it as WIDTHxHEIGHT")
        if min(size) <= 0:
            raise InputError(f"{path}: the image size of {names[index]} must be positive; got {size[0]}x{size[1]}")
    first = _device(path, keys[0], kinds[0], chosen[0], K1, d1, np.eye(3), np.zeros(3))
    second = _device(path, keys[2], kinds[1], chosen[1], K2, d2, R, t)
    return Rig(devices={names[0]: first, names[1]: second})


def _open(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise InputError(f"{path}: calibration file does not exist")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as error:  # cv2 reports a parse error as either
        cause = error.__cause__ or error
        lines = str(cause).strip().splitlines()
        reason = lines[-1].strip() if lines else "parse error"
        raise InputError(f"{path}: not an OpenCV FileStorage XML/YAML file ({reason})") from None
    if not storage.isOpened():
        raise InputError(f"{path}: not an OpenCV FileStorage XML/YAML file")
    return storage


class _Reader:
    """Typed access to the keys of an open FileStorage; every error names the file and the key."""

    def __init__(self, storage: cv2.FileStorage, path: Path) -> None:
        self._storage, self._path = storage, path

    def _node(self, key: str) -> cv2.FileNode:
        node = self._storage.getNode(key)
        if node.empty() or node.isNone():
            raise InputError(f"{self._path}: {key}: missing")
        return node

    def has(self, key: str) -> bool:
        node = self._storage.getNode(key)
        return not (node.empty() or node.isNone())

    def first_present(self, *keys: str) -> str:
        return next((key for key in keys if self.has(key)), keys[0])

    def array(self, key: str) -> np.ndarray:
        node = self._node(key)
        if node.isSeq():
            values = np.array([node.at(i).real() for i in range(node.size())], np.float64)
        else:
            values = node.mat()
            if values is None:
                raise InputError(f"{self._path}: {key}: not a matrix (an opencv-matrix or a list of numbers)")
            values = np.asarray(values, np.float64)
        if not np.all(np.isfinite(values)):
            raise InputError(f"{self._path}: {key}: contains a non-finite value")
        return values

    def matrix(self, key: str, shape: tuple[int, int]) -> np.ndarray:
        values = self.array(key)
        if values.size != shape[0] * shape[1] or (values.ndim == 2 and shape[1] > 1 and values.shape != shape):
            found = "x".join(str(n) for n in values.shape)
            raise InputError(f"{self._path}: {key}: must be a {shape[0]}x{shape[1]} matrix; got {found}")
        return values.reshape(shape)

    def intrinsics(self, key: str) -> np.ndarray:
        return self.matrix(key, (3, 3))

    def distortion(self, key: str) -> np.ndarray:
        values = self.array(key)
        if values.ndim == 2 and min(values.shape) != 1 or values.size not in VALID_DISTORTION_LENGTHS:
            found = "x".join(str(n) for n in values.shape)
            raise InputError(f"{self._path}: {key}: must be a vector of {', '.join(map(str, VALID_DISTORTION_LENGTHS[1:]))} "
                             f"distortion coefficients; got {found}")
        return values.ravel()

    def rotation(self, key: str) -> np.ndarray:
        R = self.matrix(key, (3, 3))
        orthogonality = float(np.abs(R @ R.T - np.eye(3)).max())
        determinant = float(np.linalg.det(R))
        if orthogonality > _FILE_ROTATION_TOLERANCE or determinant < 0:
            raise InputError(f"{self._path}: {key}: not a rotation matrix (max |R R^T - I| = {orthogonality:.2g}, "
                             f"det = {determinant:.4g})")
        u, _, vt = np.linalg.svd(R)
        return u @ vt  # the nearest rotation: the file's float32 rounding removed

    def integer(self, key: str) -> int:
        node = self._node(key)
        if not node.isInt() and not node.isReal():
            raise InputError(f"{self._path}: {key}: must be a number")
        value = node.real()
        if value != int(value):
            raise InputError(f"{self._path}: {key}: must be a whole number of pixels; got {value:g}")
        return int(value)

    def size(self, key: str) -> tuple[int, int]:
        values = self.array(key).ravel()
        if values.size != 2 or np.any(values != np.round(values)):
            raise InputError(f"{self._path}: {key}: must be two whole numbers, width and height")
        return int(values[0]), int(values[1])

    def stereo_sizes(self) -> tuple[tuple[int, int] | None, tuple[int, int] | None]:
        shared = next((self.size(key) for key in ("imageSize", "image_size") if self.has(key)), None)
        return tuple(self.size(f"imageSize{i}") if self.has(f"imageSize{i}") else shared for i in (1, 2))


def _device(path: Path, key: str, kind: DeviceKind, size: tuple[int, int], K: np.ndarray, dist: np.ndarray,
            R: np.ndarray, t: np.ndarray) -> CameraModel:
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{path}: {key}: focal lengths must be positive; got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise InputError(f"{path}: {key}: must be upper triangular with last row [0, 0, 1]")
    if K[0, 1] != 0:
        raise InputError(f"{path}: {key}: has skew K[0][1] = {K[0, 1]:g}; OpenCV's camera model has none")
    return CameraModel(kind=kind, width=size[0], height=size[1], K=K.tolist(), dist=dist.tolist(), R=R.tolist(),
                  t=t.tolist())

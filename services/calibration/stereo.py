"""The pose of a second calibrated device relative to a reference camera, from shared board views."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class StereoCalibration:
    """The result of ``calibrate_stereo``.

    Attributes
    ----------
    R, t : (3, 3) and (3,) arrays
        Reference-to-device transform, x_dev = R x_ref + t (millimetres).
    rms : float
        RMS reprojection error over both devices' features, in pixels.
    per_view_rms : (V, 2) array
        RMS of each view in the reference and in the device.
    baseline_mm : float
        Distance between the two optical centres, |t|.
    pose_std : (6,) array
        Standard deviations of the Rodrigues vector of R (rad) and of t (mm).
    """

    R: np.ndarray
    t: np.ndarray
    rms: float
    per_view_rms: np.ndarray
    baseline_mm: float
    pose_std: np.ndarray


def calibrate_stereo(
    object_points: list[np.ndarray],
    reference_points: list[np.ndarray],
    device_points: list[np.ndarray],
    reference_intrinsics: tuple[np.ndarray, np.ndarray],
    device_intrinsics: tuple[np.ndarray, np.ndarray],
    image_size: tuple[int, int],
) -> StereoCalibration:
    """Estimate the rigid transform between two calibrated devices that watched the same board.

    Parameters
    ----------
    object_points : list of (N_i, 3) arrays
        Board features seen by both devices in view i (board millimetres).
    reference_points, device_points : lists of (N_i, 2) arrays
        Their pixel positions in the reference camera and in the other device.
    reference_intrinsics, device_intrinsics : (K, dist) pairs
        Fixed intrinsics of both devices (from their own calibrations).
    image_size : (width, height)
        Image size of the reference camera.

    Returns
    -------
    StereoCalibration

    Notes
    -----
    With both intrinsics fixed, ``cv2.stereoCalibrate`` minimises the reprojection error in
    both images over the board poses B_i seen by the reference and one shared transform
    (R, t), the device seeing B_i through x_dev = R x_ref + t [1]_. The standard deviations
    of (R, t) are sqrt(diag((J^T J)^-1) sigma^2) over all the estimated poses, J the Jacobian
    of both images' residuals (``cv2.projectPoints`` chained with ``cv2.composeRT``) and
    sigma^2 the residual variance per coordinate.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000;
       G. Bradski, A. Kaehler, "Learning OpenCV", O'Reilly 2008, chapter 12 (stereo calibration).
    """
    views = len(object_points)
    if not views == len(reference_points) == len(device_points):
        raise ValueError("object_points, reference_points and device_points must list the same views.")
    if views < 1:
        raise ValueError("Stereo calibration needs at least one view of the board seen by both devices.")
    objects = [np.asarray(p, np.float32).reshape(-1, 3) for p in object_points]
    first = [np.asarray(p, np.float32).reshape(-1, 2) for p in reference_points]
    second = [np.asarray(p, np.float32).reshape(-1, 2) for p in device_points]
    (K1, d1), (K2, d2) = reference_intrinsics, device_intrinsics
    # copies: OpenCV writes to the intrinsics it is given (input-output arrays), even when they are fixed
    K1, K2 = np.array(K1, np.float64), np.array(K2, np.float64)
    d1, d2 = np.array(d1, np.float64).ravel(), np.array(d2, np.float64).ravel()
    rms, _, _, _, _, R, t, _, _, rvecs, tvecs, per_view = cv2.stereoCalibrateExtended(
        objects, first, second, K1, d1, K2, d2, tuple(int(s) for s in image_size), None, None,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=_CRITERIA,
    )
    t = t.ravel()
    pose_std = _pose_std(objects, first, second, (K1, d1), (K2, d2), R, t, rvecs, tvecs)
    return StereoCalibration(R=R, t=t, rms=float(rms), per_view_rms=np.asarray(per_view).reshape(-1, 2),
                             baseline_mm=float(np.linalg.norm(t)), pose_std=pose_std)


def _pose_std(objects, first, second, reference_intrinsics, device_intrinsics, R, t, rvecs, tvecs) -> np.ndarray:
    """Standard deviations of the stereo pose (Rodrigues vector, t) from the Jacobian of all residuals."""
    views = len(objects)
    rvec = cv2.Rodrigues(R)[0]
    tvec = t.reshape(3, 1)
    blocks, residuals = [], []
    for index, (obj, seen_first, seen_second) in enumerate(zip(objects, first, second)):
        board_r, board_t = np.asarray(rvecs[index], np.float64), np.asarray(tvecs[index], np.float64)
        columns = slice(6 + 6 * index, 12 + 6 * index)
        projected, jacobian = cv2.projectPoints(obj, board_r, board_t, *reference_intrinsics)
        block = np.zeros((2 * len(obj), 6 + 6 * views))
        block[:, columns] = jacobian[:, :6]
        blocks.append(block)
        residuals.append(seen_first.reshape(-1) - projected.reshape(-1))
        r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            board_r, board_t, rvec, tvec)
        projected, jacobian = cv2.projectPoints(obj, r3, t3, *device_intrinsics)
        d_pose = jacobian[:, :6]  # d projection / d (r3, t3)
        block = np.zeros((2 * len(obj), 6 + 6 * views))
        block[:, :6] = d_pose @ np.block([[dr3dr2, dr3dt2], [dt3dr2, dt3dt2]])
        block[:, columns] = d_pose @ np.block([[dr3dr1, dr3dt1], [dt3dr1, dt3dt1]])
        blocks.append(block)
        residuals.append(seen_second.reshape(-1) - projected.reshape(-1))
    J, r = np.vstack(blocks), np.concatenate(residuals)
    variance = float(r @ r) / max(1, len(r) - J.shape[1])
    covariance = np.linalg.pinv(J.T @ J) * variance
    return np.sqrt(np.diag(covariance)[:6])

"""Zhang's planar camera calibration with automatic outlier-view rejection and parameter uncertainties."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from services.calibration.model_selection import ModelFit, ModelSelection, bayesian_information_criterion, select_model
from services.formats.board import MIN_VIEWS

DistortionModel = Literal["none", "radial", "standard", "rational", "auto"]
#: The lens models ``distortion="auto"`` chooses from, simplest first; each contains the previous one.
AUTO_CANDIDATES = ("none", "radial", "standard", "rational")
PINHOLE_NAMES = ("fx", "fy", "cx", "cy")
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                   "s1", "s2", "s3", "s4", "tau_x", "tau_y")
_ESTIMATED = {
    "none": ("fx", "fy", "cx", "cy"),
    "radial": ("fx", "fy", "cx", "cy", "k1", "k2"),
    "standard": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
    "rational": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
_FLAGS = {
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "radial": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "standard": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}
_DISTORTION_LENGTH = {"none": 5, "radial": 5, "standard": 5, "rational": 8}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
# A view is an outlier when its RMS exceeds both the median plus OUTLIER_MADS robust standard
# deviations of the per-view RMS and OUTLIER_RATIO times the median (the latter keeps a set of
# uniformly good views, whose spread is tiny, from losing its worst member).
OUTLIER_MADS = 4.0
OUTLIER_RATIO = 2.0


@dataclass(frozen=True)
class CameraCalibration:
    """The result of ``calibrate_camera``.

    Attributes
    ----------
    image_size : (width, height)
    K : (3, 3) array
    dist : (D,) array
        OpenCV-order distortion coefficients.
    rms : float
        Root-mean-square reprojection error over all kept features, in pixels.
    std : dict of str to float
        One standard deviation of each estimated intrinsic parameter: the jackknife over views (see
        ``view_jackknife``) times ``student_predictive_factor`` (the jackknife's own noise); when
        ``distortion="auto"`` chose a model simpler than the standard one, fx, fy, cx and cy never less than
        the standard model's (the same way); and when it chose any model but the standard one, every parameter
        also carries the choice's uncertainty (``std_model_choice``). Without the jackknife
        (``jackknife=False``, or three views), the Jacobian's.
    views : (V,) int array
        Indices (into the input lists) of the views kept.
    per_view_rms : (V,) array
    rotations, translations : (V, 3, 3) and (V, 3) arrays
        Board-to-camera pose of each kept view, x_cam = R x_board + t.
    pose_std : (V, 6) array
        Standard deviations of each view's Rodrigues vector (rad) and translation (mm).
    residuals : list of (N_v, 2) arrays
        Observed minus reprojected pixel position of every feature of each kept view.
    rejected : list of (int, str)
        Input index and reason of every view rejected as an outlier.
    distortion_model : str
        The lens model of ``dist`` (the chosen one when ``distortion="auto"``).
    model_selection : ModelSelection or None
        With ``distortion="auto"``: every candidate's fit (RSS, parameters, BIC, RMS) and why the
        chosen one won.
    std_jacobian : dict of str to float or None
        The Jacobian's standard deviations sqrt(diag((J^T J)^-1) sigma^2), which assume independent
        residuals.
    correlation : (P, P) array or None
        Correlation matrix of the estimated intrinsics (the order of ``std``) from the jackknife.
    std_model_choice : dict of str to float or None
        When ``distortion="auto"`` chose a model other than the standard one: the uncertainty of the choice
        (``model_choice_spread``), added to each parameter's ``std`` in quadrature: |theta_standard -
        theta_chosen| of fx, fy, cx, cy, and of a distortion coefficient that squared difference less its own
        jackknife variance (Hausman's form; zero in the standard model for k4, k5, k6).
    """

    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    rms: float
    std: dict[str, float]
    views: np.ndarray
    per_view_rms: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    pose_std: np.ndarray
    residuals: list[np.ndarray]
    rejected: list[tuple[int, str]]
    distortion_model: str = "standard"
    model_selection: ModelSelection | None = None
    std_jacobian: dict[str, float] | None = None
    correlation: np.ndarray | None = None
    std_model_choice: dict[str, float] | None = None


def calibrate_camera(
    object_points: list[np.ndarray],
    image_points: list[np.ndarray],
    image_size: tuple[int, int],
    distortion: DistortionModel = "standard",
    reject_outliers: bool = True,
    jackknife: bool = True,
) -> CameraCalibration:
    """Calibrate a camera from views of a planar board, rejecting outlier views automatically.

    Parameters
    ----------
    object_points : list of (N_i, 3) arrays
        Board feature positions of each view in board millimetres (z = 0).
    image_points : list of (N_i, 2) arrays
        Their observed pixel positions.
    image_size : (width, height)
    distortion : {"none", "radial", "standard", "rational", "auto"}
        Lens model: none (ideal pinhole), k1 k2, k1 k2 p1 p2 k3, the 8-coefficient
        rational model, or "auto": the one of these the data support best (see Notes).
    reject_outliers : bool
        Drop views whose RMS is far above the others (see Notes), one at a time.
    jackknife : bool
        Standard deviations from the view jackknife (``view_jackknife``, one more calibration per view);
        False keeps the Jacobian's (for the many trial calibrations of a cross-validation).

    Returns
    -------
    CameraCalibration

    Notes
    -----
    Zhang's method [1]_ as implemented by ``cv2.calibrateCameraExtended``: closed-form
    intrinsics from the homographies h_i of each view through the image of the absolute
    conic, h_1^T K^-T K^-1 h_2 = 0 and h_1^T K^-T K^-1 h_1 = h_2^T K^-T K^-1 h_2, then
    Levenberg-Marquardt minimisation of sum ||m_ij - proj(K, dist, R_i, t_i, M_j)||^2.
    Standard deviations: the Jacobian's sqrt(diag((J^T J)^-1) sigma^2), sigma^2 the residual variance
    per coordinate, assumes independent corner errors; blur and a bent or unevenly lit board make the
    errors of a view's corners shared, so the delete-one-view jackknife (``view_jackknife``) is reported,
    times sqrt(nu / (nu - 2)), nu = V - 1 (``student_predictive_factor``): the standard deviation of Student's t,
    since the jackknife's variance is itself estimated from V views. (The larger of the jackknife's and the
    Jacobian's sigma, reported before, is biased upward when the two agree.) When ``distortion="auto"`` chose a
    model other than the standard one, every parameter's variance adds the squared bias of the choice, estimated
    from the difference to the standard model's estimate (``model_choice_spread``), and a simpler model's
    focal lengths and principal point are never less uncertain than the standard model's: the sigmas are
    unconditional on the choice. (A simpler model's distortion coefficients are not floored by the standard
    model's: those trade against k3 there, a noise that is no error of the simpler model.) Outlier views replace
    the paper's removal of gross errors by hand: while the worst view's RMS exceeds both median + 4 * 1.4826 * MAD and twice the
    median of the per-view RMS, it is dropped and the calibration repeated, never going
    below three views.

    With ``distortion="auto"`` the outlier views are found with the standard model, then every
    model of ``AUTO_CANDIDATES`` is fitted to the kept views and the one of lowest Bayesian
    information criterion ``n ln(RSS / n) + k ln n`` wins (n residual coordinates, k parameters
    including six per view) [2]_. Few, blurry views of a small sensor cannot separate k2 and k3 from
    the focal length, and the criterion then drops the coefficients whose residual gain is noise;
    many sharp views of a strongly distorted lens keep the full model.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11),
       1330-1334, 2000.
    .. [2] G. Schwarz, "Estimating the dimension of a model", Annals of Statistics 6(2), 461-464 (1978).
    """
    if len(object_points) != len(image_points):
        raise ValueError(
            f"object_points and image_points must list the same views; got {len(object_points)} and {len(image_points)}."
        )
    if len(object_points) < MIN_VIEWS:
        raise ValueError(f"Calibration needs at least {MIN_VIEWS} views of the board; got {len(object_points)}.")
    if distortion not in (*_FLAGS, "auto"):
        raise ValueError(f"distortion must be one of {sorted((*_FLAGS, 'auto'))}; got {distortion!r}.")
    objects = [np.asarray(p, dtype=np.float32).reshape(-1, 3) for p in object_points]
    images = [np.asarray(p, dtype=np.float32).reshape(-1, 2) for p in image_points]
    for index, (obj, img) in enumerate(zip(objects, images)):
        if len(obj) != len(img) or len(obj) < 4:
            raise ValueError(f"View {index} must have at least 4 matching object and image points; "
                             f"got {len(obj)} and {len(img)}.")
    kept = list(range(len(objects)))
    rejected: list[tuple[int, str]] = []
    fitted = "standard" if distortion == "auto" else distortion
    while True:
        result = _calibrate_views([objects[i] for i in kept], [images[i] for i in kept], image_size, fitted)
        worst, reason = _worst_outlier(result["per_view_rms"]) if reject_outliers else (None, "")
        if worst is None or len(kept) <= MIN_VIEWS:
            break
        rejected.append((kept[worst], reason))
        del kept[worst]
    selection, candidates = None, {}
    if distortion == "auto":
        selection, candidates = _select_distortion([objects[i] for i in kept], [images[i] for i in kept], image_size,
                                                   {fitted: result})
        fitted = selection.chosen
        result = candidates[fitted]
    distortion = fitted
    std_jacobian = {name: float(value) for name, value in zip(INTRINSIC_NAMES, result["std_intrinsics"])
                    if name in _ESTIMATED[distortion]}
    std, correlation, model_choice = dict(std_jacobian), None, None
    if jackknife and len(kept) > MIN_VIEWS:
        kept_objects, kept_images = [objects[i] for i in kept], [images[i] for i in kept]
        replicates = jackknife_replicates(kept_objects, kept_images, image_size, distortion, result)
        covariance = _jackknife_covariance(replicates)
        jackknife = np.sqrt(np.diag(covariance))
        predictive = student_predictive_factor(len(kept))  # the jackknife's own noise (V - 1 degrees of freedom)
        std = {name: predictive * float(value) for name, value in zip(_ESTIMATED[distortion], jackknife)}
        if candidates and distortion != "standard":  # chosen by "auto": the choice is uncertain too
            general = jackknife_replicates(kept_objects, kept_images, image_size, "standard", candidates["standard"])
            model_choice = model_choice_spread(result, candidates["standard"], _ESTIMATED[distortion], replicates,
                                               general)
            if distortion in ("none", "radial"):  # not conditional on the simpler model being right
                for name, value in zip(_ESTIMATED["standard"], np.sqrt(np.diag(_jackknife_covariance(general)))):
                    if name in PINHOLE_NAMES and name in std:
                        std[name] = max(std[name], predictive * float(value))
            std.update({name: float(np.hypot(std[name], value)) for name, value in model_choice.items()})
        with np.errstate(divide="ignore", invalid="ignore"):
            correlation = np.nan_to_num(covariance / np.outer(jackknife, jackknife))
    return CameraCalibration(
        image_size=(int(image_size[0]), int(image_size[1])),
        K=result["K"],
        dist=result["dist"][: _DISTORTION_LENGTH[distortion]],
        rms=result["rms"],
        std=std,
        views=np.asarray(kept),
        per_view_rms=result["per_view_rms"],
        rotations=result["rotations"],
        translations=result["translations"],
        pose_std=result["pose_std"],
        residuals=result["residuals"],
        rejected=rejected,
        distortion_model=distortion,
        model_selection=selection,
        std_jacobian=std_jacobian,
        correlation=correlation,
        std_model_choice=model_choice,
    )


def student_predictive_factor(views: int) -> float:
    """The factor from a delete-one-view jackknife's standard deviation to the predictive one: sqrt(nu / (nu - 2)).

    Parameters
    ----------
    views : int
        The number of views V the jackknife left out in turn (at least 4); nu = V - 1.

    Returns
    -------
    float

    Notes
    -----
    The jackknife's variance is itself an estimate from V pseudo-values, with about nu = V - 1 degrees of
    freedom [1]_; an error divided by it follows Student's t with nu degrees of freedom rather than the normal
    law, whose standard deviation is sqrt(nu / (nu - 2)) [2]_. Multiplying the jackknife's sigma by this
    factor gives the standard deviation of the error that the sigma predicts, with the right expectation;
    the larger of the jackknife's and the Jacobian's sigma, used before, is biased upward whenever the two
    estimate the same variance (each has its sampling noise and the larger is kept), and the Jacobian's
    sigma is only a lower bound when a view's corners share their errors.

    References
    ----------
    .. [1] J. W. Tukey, "Bias and confidence in not-quite large samples" (abstract), Annals of Mathematical
       Statistics 29(2), 614 (1958).
    .. [2] Student, "The probable error of a mean", Biometrika 6(1), 1-25 (1908).
    """
    if views < 4:
        raise ValueError(f"The predictive factor needs at least 4 views (3 degrees of freedom); got {views}.")
    freedom = views - 1
    return float(np.sqrt(freedom / (freedom - 2)))


def model_choice_spread(chosen: dict, general: dict, names: tuple[str, ...] = ("fx", "fy", "cx", "cy"),
                        chosen_replicates: np.ndarray | None = None,
                        general_replicates: np.ndarray | None = None) -> dict[str, float]:
    """The uncertainty of the lens model's choice: how far the standard model's estimates lie from the chosen one's.

    Parameters
    ----------
    chosen, general : dict
        The calibration with the chosen lens model and with the standard one (``K`` and ``dist``).
    names : tuple of str
        The chosen model's parameters (its order of ``INTRINSIC_NAMES``); a coefficient the standard model does
        not estimate (k4, k5, k6 of the rational model) is zero there.
    chosen_replicates, general_replicates : (V, P_chosen) and (V, 9) arrays, optional
        The delete-one-view replicates of both models over the same views (``jackknife_replicates``); needed
        for the distortion coefficients in ``names``.

    Returns
    -------
    dict of str to float
        For fx, fy, cx, cy: ``|d|``, d = theta_standard - theta_chosen. For a distortion coefficient:
        ``sqrt(max(0, d^2 - var(d)))``, var(d) the delete-one-view jackknife variance of the difference.

    Notes
    -----
    A model chosen by a criterion gives estimates conditional on the choice being right; the reported
    variance must also carry the uncertainty of the choice [1]_. With the standard model as the reference, the
    unconditional variance of a chosen estimate is taken as ``sigma^2 + b^2``, b^2 an estimate of the chosen
    model's squared bias, which the difference to the standard model measures when the omitted terms are not
    zero [2]_. For the pinhole parameters b^2 = d^2. The principal point needs the term most: a decentred lens
    (tangential p1, p2) moves the image almost as a shift of the principal point does, so the criterion cannot
    see the tangential terms while the simpler model's principal point absorbs them.

    The distortion coefficients get the term too, since the candidate models are nested (a coefficient is the
    same coefficient of the same lens function in every model). A rational model chosen on few views can trade
    k1 against k4 (numerator against denominator) far from the truth, with every delete-one-view refit
    staying in the same valley; the standard model's k1 shows it. But the standard model's coefficients are
    also much noisier than a simpler model's (k1 and k2 trade against k3), so d^2 there is mostly that noise,
    not the chosen model's error: its expectation is b^2 + var(d). Hausman's form b^2 = max(0, d^2 - var(d))
    [2]_ removes it, var(d) taken from the paired view jackknife of the difference (both models refitted
    without the same view), which needs no assumption about which model is efficient.

    References
    ----------
    .. [1] S. T. Buckland, K. P. Burnham, N. H. Augustin, "Model selection: an integral part of inference",
       Biometrics 53(2), 603-618 (1997).
    .. [2] J. A. Hausman, "Specification tests in econometrics", Econometrica 46(6), 1251-1271 (1978).
    """
    indices = [INTRINSIC_NAMES.index(name) for name in names]
    difference = _intrinsic_values(general)[indices] - _intrinsic_values(chosen)[indices]
    spread = {}
    for position, (name, value) in enumerate(zip(names, difference)):
        if name in PINHOLE_NAMES:
            spread[name] = float(abs(value))
            continue
        if chosen_replicates is None or general_replicates is None:
            raise ValueError(f"The spread of the distortion coefficient {name} needs both models' jackknife "
                             "replicates.")
        general_values = np.zeros(len(general_replicates))
        if name in _ESTIMATED["standard"]:
            general_values = np.asarray(general_replicates)[:, _ESTIMATED["standard"].index(name)]
        paired = general_values - np.asarray(chosen_replicates)[:, position]
        variance = float(_jackknife_covariance(paired[:, None])[0, 0])
        spread[name] = float(np.sqrt(max(0.0, value**2 - variance)))
    return spread


def _jackknife_covariance(replicates: np.ndarray) -> np.ndarray:
    """(V - 1) / V sum_i (theta_(i) - theta_(.)) (theta_(i) - theta_(.))^T of (V, P) delete-one replicates."""
    deviations = replicates - replicates.mean(axis=0)
    return (len(replicates) - 1) / len(replicates) * deviations.T @ deviations


def _intrinsic_values(result: dict) -> np.ndarray:
    """fx, fy, cx, cy and the distortion coefficients in the order of ``INTRINSIC_NAMES`` (zeros beyond ``dist``)."""
    K, dist = result["K"], np.asarray(result["dist"], np.float64).ravel()[:14]
    values = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.zeros(14)])
    values[4:4 + dist.size] = dist
    return values


def view_jackknife(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int],
                   distortion: str, full: dict | None = None) -> np.ndarray:
    """Delete-one-view jackknife covariance of the estimated intrinsics.

    Parameters
    ----------
    objects, images : lists of (N_i, 3) and (N_i, 2) arrays
        The kept views' board points and corners.
    image_size : (width, height)
    distortion : {"none", "radial", "standard", "rational"}
    full : dict, optional
        The calibration on all views (its intrinsics start every refit).

    Returns
    -------
    (P, P) array
        Covariance of the parameters named by the model (fx, fy, cx, cy, then its distortion terms).

    Notes
    -----
    With theta_(i) the estimate without view i of V and theta_(.) their mean, the covariance is
    ``(V - 1) / V * sum_i (theta_(i) - theta_(.)) (theta_(i) - theta_(.))^T`` [1]_. Unlike the Jacobian's
    ``(J^T J)^-1 sigma^2`` it does not assume independent corner errors: a blurred corner's error is shared
    by its neighbours, a view's pose and board errors by all its corners, and resampling whole views keeps
    those correlations (the views are the independent units) [2]_.

    References
    ----------
    .. [1] B. Efron, C. Stein, "The jackknife estimate of variance", Annals of Statistics 9(3), 586-596 (1981).
    .. [2] B. Efron, "The jackknife, the bootstrap and other resampling plans", SIAM CBMS-NSF 38 (1982), ch. 3.
    """
    return _jackknife_covariance(jackknife_replicates(objects, images, image_size, distortion, full))


def jackknife_replicates(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int],
                         distortion: str, full: dict | None = None) -> np.ndarray:
    """The intrinsics estimated without each view in turn (the replicates of ``view_jackknife``).

    Parameters
    ----------
    objects, images, image_size, distortion, full
        As ``view_jackknife``.

    Returns
    -------
    (V, P) array
        Row i: the parameters named by the model (fx, fy, cx, cy, then its distortion terms) without view i.
    """
    if len(objects) < MIN_VIEWS + 1:
        raise ValueError(f"The view jackknife needs at least {MIN_VIEWS + 1} views; got {len(objects)}.")
    names = _ESTIMATED[distortion]
    indices = [INTRINSIC_NAMES.index(name) for name in names]
    objects = [np.asarray(p, np.float32).reshape(-1, 3) for p in objects]
    images = [np.asarray(p, np.float32).reshape(-1, 2) for p in images]
    estimates = []
    for left_out in range(len(objects)):
        kept = [i for i in range(len(objects)) if i != left_out]
        flags = _FLAGS[distortion]
        K0, dist0 = None, None
        if full is not None:
            flags |= cv2.CALIB_USE_INTRINSIC_GUESS
            K0, dist0 = full["K"].copy(), np.asarray(full["dist"], np.float64).copy()
        _, K, dist, _, _ = cv2.calibrateCamera([objects[i] for i in kept], [images[i] for i in kept],
                                               tuple(int(s) for s in image_size), K0, dist0, flags=flags,
                                               criteria=_CRITERIA)
        estimates.append(_intrinsic_values({"K": K, "dist": dist})[indices])
    return np.array(estimates)


def _select_distortion(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int],
                       known: dict[str, dict]) -> tuple[ModelSelection, dict[str, dict]]:
    """Fit every candidate lens model (reusing those in ``known``) and pick the lowest BIC; every candidate's fit."""
    results = {model: known.get(model) or _calibrate_views(objects, images, image_size, model)
               for model in AUTO_CANDIDATES}
    observations = 2 * sum(len(points) for points in images)
    fits = []
    for model, result in results.items():
        residual_sum = float(sum(np.sum(r**2) for r in result["residuals"]))
        parameters = len(_ESTIMATED[model]) + 6 * len(images)
        fits.append(ModelFit(model=model, residual_sum=residual_sum, observations=observations, parameters=parameters,
                             bic=bayesian_information_criterion(residual_sum, observations, parameters),
                             rms=result["rms"]))
    selection = select_model(fits)
    return selection, results


def _calibrate_views(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int],
                     distortion: DistortionModel) -> dict:
    rms, K, dist, rvecs, tvecs, std_intrinsics, std_extrinsics, _ = cv2.calibrateCameraExtended(
        objects, images, tuple(int(s) for s in image_size), None, None, flags=_FLAGS[distortion], criteria=_CRITERIA
    )
    dist = dist.ravel()
    residuals = [
        img - cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        for obj, img, rvec, tvec in zip(objects, images, rvecs, tvecs)
    ]
    return {
        "rms": float(rms),
        "K": K,
        "dist": dist,
        "std_intrinsics": std_intrinsics.ravel(),
        "per_view_rms": np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in residuals]),
        "rotations": np.array([cv2.Rodrigues(r)[0] for r in rvecs]),
        "translations": np.array([t.ravel() for t in tvecs]),
        "pose_std": std_extrinsics.reshape(-1, 6),
        "residuals": [r.astype(np.float64) for r in residuals],
    }


def _worst_outlier(per_view_rms: np.ndarray) -> tuple[int | None, str]:
    median = float(np.median(per_view_rms))
    mad = 1.4826 * float(np.median(np.abs(per_view_rms - median)))
    limit = max(median + OUTLIER_MADS * mad, OUTLIER_RATIO * median)
    worst = int(np.argmax(per_view_rms))
    if per_view_rms[worst] <= limit:
        return None, ""
    return worst, (f"reprojection RMS {per_view_rms[worst]:.3f} px exceeds the outlier limit {limit:.3f} px "
                   f"(median {median:.3f} px of the views)")


def locate_camera(world_points: np.ndarray, image_points: np.ndarray, K: np.ndarray,
                  dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of a calibrated camera in the world from features at known world positions.

    Parameters
    ----------
    world_points : (N, 3) array
        Feature positions in world millimetres, e.g. a board placed at several known stage
        positions (non-coplanar points decouple rotation from translation far better than
        one plane).
    image_points : (N, 2) array
        Their observed pixel positions.
    K, dist : arrays
        The camera's calibrated intrinsics.

    Returns
    -------
    R, t : (3, 3) and (3,) arrays
        World-to-camera pose, x_cam = R x_world + t.

    Notes
    -----
    Minimises sum ||m_j - proj(K, dist, R, t, X_j)||^2 by Levenberg-Marquardt from the
    closed-form start of ``cv2.solvePnP`` (perspective-n-point).
    """
    world_points = np.asarray(world_points, np.float64).reshape(-1, 3)
    image_points = np.asarray(image_points, np.float64).reshape(-1, 2)
    if len(world_points) != len(image_points) or len(world_points) < 6:
        raise ValueError(f"locate_camera needs at least 6 matching world and image points; got "
                         f"{len(world_points)} and {len(image_points)}.")
    found, rvec, tvec = cv2.solvePnP(world_points, image_points, np.asarray(K, np.float64),
                                     np.asarray(dist, np.float64), flags=cv2.SOLVEPNP_ITERATIVE)
    if not found:
        raise ValueError("The camera pose could not be estimated from these points.")
    rvec, tvec = cv2.solvePnPRefineLM(world_points, image_points, np.asarray(K, np.float64),
                                      np.asarray(dist, np.float64), rvec, tvec, criteria=_CRITERIA)
    return cv2.Rodrigues(rvec)[0], tvec.ravel()

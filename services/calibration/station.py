"""Station calibration: every camera of a multi-head station in one world frame, by bundle adjustment."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.transform import Rotation
from scipy.sparse import coo_matrix

from services.calibration.camera import INTRINSIC_NAMES
from services.geometry.camera import normalized_coordinates

POSE_NAMES = ("rx", "ry", "rz", "x", "y", "z")
"""The six degrees of freedom of a device's pose in the world: the small rotation (degrees, about world axes)
from the estimate to another orientation, and the device centre's world coordinates (mm)."""
_TOLERANCE = 1e-12
_STEP = (1e-7, 1e-4)  # central-difference steps of a pose's Rodrigues vector (rad) and translation (mm)


@dataclass(frozen=True)
class BoardObservation:
    """Board features one camera found in one board view (a board pose that several cameras may film).

    Attributes
    ----------
    camera, view : int
        Indices of the camera and of the board view.
    object_points : (N, 3) array
        The features' board coordinates (mm, z = 0).
    image_points : (N, 2) array
        Their pixel positions in the camera.
    """

    camera: int
    view: int
    object_points: np.ndarray
    image_points: np.ndarray


@dataclass(frozen=True)
class StationBundle:
    """The result of :func:`adjust_station`.

    Attributes
    ----------
    rotations, translations : (C, 3, 3) and (C, 3) arrays
        Each camera's world-to-camera pose, x_cam = R x_world + t (mm); the reference camera's is the one given.
    K, dist : lists of C arrays
        Each camera's intrinsics after the adjustment (the given ones where not refined).
    board_rotations, board_translations : (V, 3, 3) and (V, 3) arrays
        Each board view's board-to-world pose, x_world = R x_board + t.
    rms_px : float
        Reprojection RMS over every feature of every observation.
    observation_rms_px, observation_rms_mm : (O,) arrays
        Reprojection RMS of each observation, in the input order, and the RMS distance on the board (mm) between
        its features and where their observed pixels' rays meet the adjusted board.
    overlap_rms_px, overlap_rms_mm : float
        Over the observations of views seen by two cameras or more: the reprojection RMS, and the RMS distance on
        the board between each feature and where its observed pixel's ray meets the adjusted board (mm).
    pose_std : (C, 6) array
        Reported one-sigma uncertainty of each camera's pose in the world (:data:`POSE_NAMES`: rotation in
        degrees, centre in mm): the larger of the Jacobian's and the view jackknife's; zeros for the reference.
    pose_std_jacobian, pose_std_jackknife : (C, 6) arrays
        The two estimates (the jackknife's zeros when it was not run).
    """

    rotations: np.ndarray
    translations: np.ndarray
    K: list[np.ndarray]
    dist: list[np.ndarray]
    board_rotations: np.ndarray
    board_translations: np.ndarray
    rms_px: float
    observation_rms_px: np.ndarray
    observation_rms_mm: np.ndarray
    overlap_rms_px: float
    overlap_rms_mm: float
    pose_std: np.ndarray
    pose_std_jacobian: np.ndarray
    pose_std_jackknife: np.ndarray


def adjust_station(
    observations: Sequence[BoardObservation],
    intrinsics: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    reference: int = 0,
    reference_pose: tuple[np.ndarray, np.ndarray] | None = None,
    refined_intrinsics: Sequence[Sequence[str]] | None = None,
    jackknife: bool = True,
) -> StationBundle:
    """Place every camera of a station in one world frame from board views some of them share.

    Parameters
    ----------
    observations : sequence of BoardObservation
        The board features each camera found in each view; a view seen by two cameras ties them.
    intrinsics : sequence of (K, dist)
        Each camera's calibrated intrinsics (from its own calibration), indexed by ``BoardObservation.camera``.
    reference : int
        The camera that fixes the world frame.
    reference_pose : (R, t), optional
        The reference camera's world-to-camera pose (default identity: the world is the reference's frame).
    refined_intrinsics : sequence of sequences of str, optional
        Per camera, the intrinsics (names of ``services.calibration.camera.INTRINSIC_NAMES``, e.g. ``("fx", "fy",
        "cx", "cy", "k1", "k2")``) refined with the poses; None keeps every camera's intrinsics fixed.
    jackknife : bool
        Also estimate the pose uncertainty by the delete-one-view jackknife.

    Returns
    -------
    StationBundle

    Notes
    -----
    Unknowns: each camera's world-to-camera pose (R_c, t_c) but the reference's, each view's board-to-world pose
    (B_v, b_v) and the refined intrinsics. Start: each observation's pose by ``cv2.solvePnP``, the cameras chained
    from the reference through shared views (breadth first), each view placed by the first placed camera that sees
    it. Bundle adjustment [1]_ minimises

        sum_(c, v) sum_j || m_cvj - proj(K_c, d_c, R_c (B_v X_j + b_v) + t_c) ||^2

    by Levenberg-Marquardt on the normal equations of the sparse Jacobian assembled from
    ``cv2.projectPoints`` and ``cv2.composeRT``. A pose's six degrees of freedom are reported in the world: the
    rotation vector omega of E = R_e^T R (degrees, about world axes) and the centre C = -R^T t (mm). Their
    covariance is G (J^T J)^-1 G^T s^2 (G the derivatives of (omega, C) with respect to the camera's parameters,
    s^2 the residual variance), which assumes independent feature errors; the delete-one-view jackknife
    (V - 1) / V sum_i (g_(i) - g_(.))^2 over the adjustments without one view each [2]_ keeps errors shared by a
    view's features (blur, a bent board). Each replicate is one Gauss-Newton step from the full solution without
    the view's rows (a one-step jackknife: on a simulated station its sigmas were within 0.2 % of fully iterated
    replicates', 37 times faster). The larger of the two is reported, as for a single camera
    (``services.calibration.camera.view_jackknife``).

    References
    ----------
    .. [1] B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment -- a modern synthesis", Vision
       Algorithms: Theory and Practice, LNCS 1883, 298-372 (2000).
    .. [2] B. Efron, C. Stein, "The jackknife estimate of variance", Annals of Statistics 9(3), 586-596 (1981).
    """
    cameras = len(intrinsics)
    if cameras < 2:
        raise ValueError(f"A station calibration needs at least two cameras; got {cameras}.")
    if not 0 <= reference < cameras:
        raise ValueError(f"reference must index one of the {cameras} cameras; got {reference}.")
    observations = [_checked(o, cameras) for o in observations]
    views = sorted({o.view for o in observations})
    if views != list(range(len(views))):
        raise ValueError(f"Board views must be numbered 0..V-1 with every one observed; got {views}.")
    if refined_intrinsics is not None and len(refined_intrinsics) != cameras:
        raise ValueError(f"refined_intrinsics must list {cameras} cameras; got {len(refined_intrinsics)}.")
    problem = _Problem(observations, intrinsics, reference, refined_intrinsics)
    R0, t0 = (np.eye(3), np.zeros(3)) if reference_pose is None else reference_pose
    start = problem.start(np.asarray(R0, np.float64), np.asarray(t0, np.float64).ravel())
    solution = problem.solve(start)
    jacobian_std = problem.pose_std_jacobian(solution)
    jackknife_std = np.zeros_like(jacobian_std)
    if jackknife:
        jackknife_std = problem.pose_std_jackknife(solution)
    return problem.result(solution, jacobian_std, jackknife_std)


def _checked(observation: BoardObservation, cameras: int) -> BoardObservation:
    objects = np.asarray(observation.object_points, np.float64).reshape(-1, 3)
    images = np.asarray(observation.image_points, np.float64).reshape(-1, 2)
    if not 0 <= observation.camera < cameras:
        raise ValueError(f"An observation names camera {observation.camera}; there are {cameras} cameras.")
    if len(objects) != len(images) or len(objects) < 4:
        raise ValueError(f"The observation of view {observation.view} by camera {observation.camera} needs at least "
                         f"4 matching object and image points; got {len(objects)} and {len(images)}.")
    return BoardObservation(observation.camera, observation.view, objects, images)


def rotation_error(R_estimate: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The rotation vector (rad, world axes) of E = R_estimate^T R, for world-to-device rotations: how far the
    device's orientation ``R`` is turned from ``R_estimate`` in the world frame."""
    # scipy, not cv2.Rodrigues: OpenCV returns a zero vector for rotations below about 1e-5 rad
    return Rotation.from_matrix(np.asarray(R_estimate, np.float64).T @ np.asarray(R, np.float64)).as_rotvec()


def pose_difference(R_estimate: np.ndarray, t_estimate: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The six degrees of freedom (:data:`POSE_NAMES`) from the pose (R_estimate, t_estimate) to (R, t), both
    world-to-device: the rotation vector (degrees, world axes) and the difference of the device centres (mm)."""
    centre = -np.asarray(R, np.float64).T @ np.asarray(t, np.float64).ravel()
    centre_estimate = -np.asarray(R_estimate, np.float64).T @ np.asarray(t_estimate, np.float64).ravel()
    return np.concatenate([np.degrees(rotation_error(R_estimate, R)), centre - centre_estimate])


class _Problem:
    """The parameter layout, residuals and Jacobian of one station's bundle adjustment."""

    def __init__(self, observations, intrinsics, reference, refined):
        self.observations = observations
        self.reference = reference
        self.cameras = len(intrinsics)
        self.views = 1 + max(o.view for o in observations)
        self.K = [np.array(K, np.float64) for K, _ in intrinsics]
        # projectPoints needs a distortion vector; an empty one is the ideal pinhole (5 zeros)
        self.dist = [np.array(d, np.float64).ravel() if np.size(d) else np.zeros(5) for _, d in intrinsics]
        self.refined = [[] for _ in range(self.cameras)]
        for camera, names in enumerate(refined or [() for _ in range(self.cameras)]):
            for name in names:
                if name not in INTRINSIC_NAMES or INTRINSIC_NAMES.index(name) >= 4 + self.dist[camera].size:
                    raise ValueError(f"Camera {camera}: cannot refine {name!r}; its model has "
                                     f"{INTRINSIC_NAMES[:4 + self.dist[camera].size]}.")
                self.refined[camera].append(INTRINSIC_NAMES.index(name))
        self.placed = [c for c in range(self.cameras) if c != reference]
        offset = 6 * len(self.placed)
        self.camera_columns = {c: 6 * i for i, c in enumerate(self.placed)}
        self.view_offset = offset
        offset += 6 * self.views
        self.intrinsic_columns = {}
        for camera in range(self.cameras):
            self.intrinsic_columns[camera] = offset
            offset += len(self.refined[camera])
        self.parameters = offset
        self.reference_pose = None

    # parameters <-> poses and intrinsics
    def camera_pose(self, x, camera):
        if camera == self.reference:
            return self.reference_pose
        column = self.camera_columns[camera]
        return x[column:column + 3], x[column + 3:column + 6]

    def view_pose(self, x, view):
        column = self.view_offset + 6 * view
        return x[column:column + 3], x[column + 3:column + 6]

    def intrinsics(self, x, camera):
        K, dist = self.K[camera].copy(), self.dist[camera].copy()
        values = x[self.intrinsic_columns[camera]:self.intrinsic_columns[camera] + len(self.refined[camera])]
        for index, value in zip(self.refined[camera], values):
            if index < 4:
                K[(0, 1, 0, 1)[index], (0, 1, 2, 2)[index]] = value
            else:
                dist[index - 4] = value
        return K, dist

    def start(self, R0, t0):
        self.reference_pose = (cv2.Rodrigues(R0)[0].ravel(), t0)
        board_in_camera = {}
        for o in self.observations:
            found, rvec, tvec = cv2.solvePnP(o.object_points, o.image_points, self.K[o.camera], self.dist[o.camera])
            if not found:
                raise ValueError(f"The board pose of view {o.view} in camera {o.camera} could not be estimated.")
            board_in_camera[o.camera, o.view] = _matrix(rvec, tvec)
        world_to_camera = {self.reference: _matrix(*self.reference_pose)}
        frontier = [self.reference]
        while frontier:  # breadth first through shared views
            known = frontier.pop(0)
            for (camera, view), pose in board_in_camera.items():
                if camera != known:
                    continue
                for (other, other_view), other_pose in board_in_camera.items():
                    if other_view == view and other not in world_to_camera:
                        world_to_camera[other] = other_pose @ np.linalg.inv(pose) @ world_to_camera[known]
                        frontier.append(other)
        missing = [c for c in range(self.cameras) if c not in world_to_camera]
        if missing:
            raise ValueError(f"Cameras {missing} share no chain of board views with camera {self.reference}; "
                             "add views that neighbouring cameras see together.")
        x = np.zeros(self.parameters)
        for camera in self.placed:
            column = self.camera_columns[camera]
            x[column:column + 6] = _vector(world_to_camera[camera])
        for view in range(self.views):
            camera = next(c for c, v in board_in_camera if v == view)
            column = self.view_offset + 6 * view
            x[column:column + 6] = _vector(np.linalg.inv(world_to_camera[camera]) @ board_in_camera[camera, view])
        for camera in range(self.cameras):
            column = self.intrinsic_columns[camera]
            K, dist = self.K[camera], self.dist[camera]
            for i, index in enumerate(self.refined[camera]):
                x[column + i] = K[(0, 1, 0, 1)[index], (0, 1, 2, 2)[index]] if index < 4 else dist[index - 4]
        return x

    def residuals_and_jacobian(self, x, observations, jacobian=True):
        residuals, rows, columns, values, row = [], [], [], [], 0
        for o in observations:
            r_view, t_view = self.view_pose(x, o.view)
            r_camera, t_camera = self.camera_pose(x, o.camera)
            r, t, dr_dview_r, dr_dview_t, dr_dcam_r, dr_dcam_t, dt_dview_r, dt_dview_t, dt_dcam_r, dt_dcam_t = \
                cv2.composeRT(r_view, t_view, r_camera, t_camera)
            K, dist = self.intrinsics(x, o.camera)
            projected, d = cv2.projectPoints(o.object_points, r, t, K, dist)
            residuals.append((projected.reshape(-1, 2) - o.image_points).ravel())
            n = 2 * len(o.object_points)
            if jacobian:
                d_pose = d[:, :6]
                chain = np.empty((6, 6))
                chain[:3, :3], chain[:3, 3:], chain[3:, :3], chain[3:, 3:] = dr_dview_r, dr_dview_t, dt_dview_r, dt_dview_t
                blocks = [(self.view_offset + 6 * o.view, d_pose @ chain)]
                if o.camera != self.reference:
                    chain = np.empty((6, 6))
                    chain[:3, :3], chain[:3, 3:], chain[3:, :3], chain[3:, 3:] = dr_dcam_r, dr_dcam_t, dt_dcam_r, dt_dcam_t
                    blocks.append((self.camera_columns[o.camera], d_pose @ chain))
                if self.refined[o.camera]:
                    blocks.append((self.intrinsic_columns[o.camera], d[:, [6 + i for i in self.refined[o.camera]]]))
                for column, block in blocks:
                    width = block.shape[1]
                    rows.append(np.repeat(np.arange(row, row + n), width))
                    columns.append(np.tile(np.arange(column, column + width), n))
                    values.append(block.ravel())
            row += n
        residual = np.concatenate(residuals)
        if not jacobian:
            return residual, None
        J = coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(columns))),
                       shape=(row, self.parameters)).tocsr()
        return residual, J

    def solve(self, x0, observations=None):
        """Levenberg-Marquardt from ``x0`` on ``observations`` (default all; a view without observations keeps
        its parameters).

        By hand on the normal equations, the board views eliminated by their Schur complement (6 x 6 blocks):
        ``scipy.optimize.least_squares``'s sparse trust region (LSMR) took 98 iterations and 80 s on a four-head
        station without reaching the optimum, while the reduced system here has a few dozen unknowns and converges
        in a handful of steps.
        """
        observations = self.observations if observations is None else observations
        x = x0.copy()
        residual, J = self.residuals_and_jacobian(x, observations)
        cost, damping = float(residual @ residual), 1e-3
        for _ in range(100):
            H, g = (J.T @ J).toarray(), J.T @ residual
            scale = np.sqrt(np.diag(H))
            scale[scale == 0] = 1.0  # parameters no observation touches (a view left out) keep their value
            normal, gradient = H / np.outer(scale, scale), g / scale
            while True:
                step = self._damped_step(normal, gradient, damping) / scale
                trial = x + step
                trial_residual, trial_J = self.residuals_and_jacobian(trial, observations)
                trial_cost = float(trial_residual @ trial_residual)
                if trial_cost <= cost:
                    break
                damping *= 10
                if damping > 1e12:
                    return x
            converged = cost - trial_cost <= _TOLERANCE * cost or np.max(np.abs(step * scale)) < 1e-10
            x, residual, J, cost = trial, trial_residual, trial_J, trial_cost
            damping = max(damping / 10, 1e-12)
            if converged:
                break
        return x

    def _split(self):
        views = np.arange(self.view_offset, self.view_offset + 6 * self.views)
        cameras = np.setdiff1d(np.arange(self.parameters), views)
        return cameras, views

    def _damped_step(self, normal, gradient, damping):
        """Solve (N + damping I) step = -gradient with the views' 6 x 6 blocks eliminated (Schur complement)."""
        cameras, views = self._split()
        A = normal[np.ix_(cameras, cameras)] + damping * np.eye(len(cameras))
        B = normal[np.ix_(cameras, views)].reshape(len(cameras), self.views, 6)
        blocks = normal[np.ix_(views, views)].reshape(self.views, 6, self.views, 6)
        C = blocks[np.arange(self.views), :, np.arange(self.views), :] + damping * np.eye(6)
        C_inverse = np.linalg.inv(C)
        g_views = gradient[views].reshape(self.views, 6)
        B_C = np.einsum("pvi,vij->pvj", B, C_inverse)
        S = A - np.einsum("pvj,qvj->pq", B_C, B)
        rhs = -gradient[cameras] + np.einsum("pvj,vj->p", B_C, g_views)
        step_cameras = cho_solve(cho_factor(S), rhs)
        step_views = np.einsum("vij,vj->vi", C_inverse, -g_views - np.einsum("pvi,p->vi", B, step_cameras))
        step = np.zeros(self.parameters)
        step[cameras], step[views] = step_cameras, step_views.ravel()
        return step

    def _pose_parameters(self, camera):
        column = self.camera_columns[camera]
        return np.arange(column, column + 6)

    def pose_std_jacobian(self, x):
        residual, J = self.residuals_and_jacobian(x, self.observations)
        variance = float(residual @ residual) / max(1, len(residual) - self.parameters)
        H = (J.T @ J).toarray()
        scale = np.sqrt(np.diag(H))
        normal = H / np.outer(scale, scale)
        # the cameras' block of the inverse is the inverse of the views' Schur complement
        cameras, views = self._split()
        B = normal[np.ix_(cameras, views)].reshape(len(cameras), self.views, 6)
        blocks = normal[np.ix_(views, views)].reshape(self.views, 6, self.views, 6)
        C_inverse = np.linalg.inv(blocks[np.arange(self.views), :, np.arange(self.views), :])
        S = normal[np.ix_(cameras, cameras)] - np.einsum("pvi,vij,qvj->pq", B, C_inverse, B)
        covariance = np.linalg.inv(S) / np.outer(scale[cameras], scale[cameras]) * variance
        std = np.zeros((self.cameras, 6))
        for camera in self.placed:
            columns = np.searchsorted(cameras, self._pose_parameters(camera))
            G = self._pose_derivatives(x[self._pose_parameters(camera)])
            std[camera] = np.sqrt(np.diag(G @ covariance[np.ix_(columns, columns)] @ G.T))
        return std

    def _pose_derivatives(self, pose):
        """d (omega in degrees, C) / d (Rodrigues vector, t) at ``pose``, by central differences."""
        R, t = cv2.Rodrigues(pose[:3])[0], pose[3:]
        G = np.zeros((6, 6))
        for i in range(6):
            step = np.zeros(6)
            step[i] = _STEP[i // 3]
            plus, minus = pose + step, pose - step
            G[:, i] = (pose_difference(R, t, cv2.Rodrigues(plus[:3])[0], plus[3:])
                       - pose_difference(R, t, cv2.Rodrigues(minus[:3])[0], minus[3:])) / (2 * step[i])
        return G

    def pose_std_jackknife(self, x):
        """The delete-one-view jackknife, each replicate one Gauss-Newton step from the full solution without the
        view's rows (a one-step jackknife, exact to first order): one Jacobian for all the replicates."""
        residual, J = self.residuals_and_jacobian(x, self.observations)
        H, g = (J.T @ J).toarray(), J.T @ residual
        scale = np.sqrt(np.diag(H))
        starts = np.cumsum([0] + [2 * len(o.object_points) for o in self.observations])
        estimates = []
        for left_out in range(self.views):
            kept = [o for o in self.observations if o.view != left_out]
            if {o.camera for o in kept} != set(range(self.cameras)) or not _connected(kept, self.cameras):
                raise ValueError(f"Without board view {left_out} the cameras are no longer tied to each other; "
                                 "every camera needs two views or more shared with a neighbour.")
            rows = np.concatenate([np.arange(starts[i], starts[i + 1]) for i, o in enumerate(self.observations)
                                   if o.view == left_out])
            J_view, r_view = J[rows], residual[rows]
            H_kept = H - (J_view.T @ J_view).toarray()
            g_kept = g - J_view.T @ r_view
            y = x + self._damped_step(H_kept / np.outer(scale, scale), g_kept / scale, 1e-10) / scale
            estimates.append([pose_difference(*_pose(x, self, c), *_pose(y, self, c)) for c in self.placed])
        estimates = np.array(estimates)  # (V, placed cameras, 6)
        deviations = estimates - estimates.mean(axis=0)
        variance = (self.views - 1) / self.views * np.sum(deviations ** 2, axis=0)
        std = np.zeros((self.cameras, 6))
        std[self.placed] = np.sqrt(variance)
        return std

    def result(self, x, jacobian_std, jackknife_std):
        residual, _ = self.residuals_and_jacobian(x, self.observations, jacobian=False)
        per_observation, per_observation_mm, overlap_px, overlap_mm, start = [], [], [], [], 0
        cameras_per_view = np.bincount([o.view for o in self.observations], minlength=self.views)
        for o in self.observations:
            n = 2 * len(o.object_points)
            r = residual[start:start + n]
            start += n
            per_observation.append(_rms_points(r))
            distances = self._board_distances(x, o)
            per_observation_mm.append(float(np.sqrt(np.mean(distances ** 2))))
            if cameras_per_view[o.view] >= 2:
                overlap_px.append(r)
                overlap_mm.append(distances)
        poses = [_pose(x, self, c) for c in range(self.cameras)]
        boards = [_matrix(*self.view_pose(x, v)) for v in range(self.views)]
        intrinsics = [self.intrinsics(x, c) for c in range(self.cameras)]
        return StationBundle(
            rotations=np.array([R for R, _ in poses]), translations=np.array([t for _, t in poses]),
            K=[K for K, _ in intrinsics], dist=[d for _, d in intrinsics],
            board_rotations=np.array([b[:3, :3] for b in boards]), board_translations=np.array([b[:3, 3] for b in boards]),
            rms_px=_rms_points(residual), observation_rms_px=np.array(per_observation),
            observation_rms_mm=np.array(per_observation_mm),
            overlap_rms_px=_rms_points(np.concatenate(overlap_px)) if overlap_px else float("nan"),
            overlap_rms_mm=float(np.sqrt(np.mean(np.concatenate(overlap_mm) ** 2))) if overlap_mm else float("nan"),
            pose_std=np.maximum(jacobian_std, jackknife_std), pose_std_jacobian=jacobian_std,
            pose_std_jackknife=jackknife_std)

    def _board_distances(self, x, o):
        """Distance (mm) on the adjusted board between each feature and where its observed pixel's ray meets it."""
        K, dist = self.intrinsics(x, o.camera)
        board_to_camera = _matrix(*self.camera_pose(x, o.camera)) @ _matrix(*self.view_pose(x, o.view))
        rays = normalized_coordinates(o.image_points, K, dist)
        # the ray (x, y, 1) meets the board plane z_board = 0: [r1 r2 t] (X, Y, 1)^T ~ (x, y, 1)^T
        homography = board_to_camera[:3][:, [0, 1, 3]]
        board = np.linalg.solve(homography, np.column_stack([rays, np.ones(len(rays))]).T).T
        board = board[:, :2] / board[:, 2:]
        return np.linalg.norm(board - o.object_points[:, :2], axis=1)


def _rms_points(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residual ** 2) * 2))


def _pose(x, problem, camera):
    r, t = problem.camera_pose(x, camera)
    return cv2.Rodrigues(np.asarray(r, np.float64))[0], np.asarray(t, np.float64).copy()


def _matrix(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def _vector(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])


def tied_groups(observations: Sequence[BoardObservation], cameras: int) -> list[set[int]]:
    """The groups of cameras tied to each other through views seen by two cameras or more (one group when the
    station can be calibrated), each camera in one group."""
    by_view: dict[int, set[int]] = {}
    for o in observations:
        by_view.setdefault(o.view, set()).add(o.camera)
    groups, left = [], set(range(cameras))
    while left:
        start = min(left)
        reached, frontier = {start}, [start]
        while frontier:
            camera = frontier.pop()
            for seen in by_view.values():
                if camera in seen:
                    for other in seen - reached:
                        reached.add(other)
                        frontier.append(other)
        groups.append(reached)
        left -= reached
    return groups


def _connected(observations, cameras) -> bool:
    return len(tied_groups(observations, cameras)) == 1

"""The camera EKF of the hybrid method: where each filter step lives.

    predict   CameraEKF.predict     constant-velocity motion model, fading memory (§3)
    observe   observation.py        reprojection model and Jacobians H (§4)
    gain      update(), step 2      Woodbury / information form, D x D solve (§5)
    update    update()              state correction, Joseph-form covariance (§5)
    IEKF      update(), step 4      iterations > 1 relinearise at the iterate (§5)
    robust    robust_update.py      1-point RANSAC + high-innovation rescue around
                                    update() (§6); estimators.py chooses the estimator
(§N = docs/method.md section N.)

The state holds only the camera (state.py: POS, QUAT, VEL, ANG); the map points are fixed,
triangulated inputs to the observation model, so an update costs O(n) in the number of
observed points. The quaternion is camera -> world (q^WC) so that the angular velocity is
a body rate, what nav_msgs/Odometry's twist wants.

Motion model, constant velocity, acceleration impulses n = [a, alpha]:
    r' = r + (v + a dt) dt,   q' = q * quat((w + alpha dt) dt),   v' = v + a dt,
    w' = w + alpha dt,        Q = diag(sigma_a^2 I3, sigma_alpha^2 I3)
    P' = lambda F P F^T + G Q G^T  with the fading-memory factor lambda >= 1.
`update` serves every estimator: the camera-only filter is the joint filter of the
in-filter refinement (§8) with zero points in its state.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from . import geometry as geo
from .observation import ReprojectionModel, rotated_by_quat_conj_jacobian
from .state import ANG, POS, POSE, QUAT, STATE_DIM, VEL

logger = logging.getLogger(__name__)

__all__ = ['ANG', 'POS', 'POSE', 'QUAT', 'STATE_DIM', 'VEL', 'CameraEKF', 'FilterError',
           'UpdateStats', 'chi2_2dof_quantile', 'motion_jacobians', 'motion_model',
           'pose_innovation', 'pose_update', 'update']


class FilterError(RuntimeError):
    """The filter reached a numerically invalid state (NaN, non-PSD covariance)."""


@dataclass
class UpdateStats:
    """Diagnostics of one update (kept for inspection, as filterpy does)."""

    n_used: int = 0            #: measurements (points) in the update
    nis: float = float('nan')  #: normalised innovation squared y^T S^-1 y (chi2, 2n dof)
    rms_innovation_px: float = float('nan')  #: before the update
    rms_residual_px: float = float('nan')    #: after the update


def chi2_2dof_quantile(probability: float) -> float:
    """Chi-square quantile for 2 degrees of freedom (closed form: -2 ln(1-p))."""
    return float(-2.0 * np.log1p(-probability))


def motion_model(x: np.ndarray, dt: float, noise: np.ndarray | None = None) -> np.ndarray:
    """x' = f(x, n) of the constant-velocity model with impulses n = [a, alpha] (6,)."""
    a, alpha = (np.zeros(3), np.zeros(3)) if noise is None else (noise[:3], noise[3:])
    out = x.copy()
    v = x[VEL] + a * dt
    w = x[ANG] + alpha * dt
    out[POS] = x[POS] + v * dt
    out[QUAT] = geo.quat_multiply(x[QUAT], geo.rotvec_to_quat(w * dt))
    out[VEL] = v
    out[ANG] = w
    return out


def motion_jacobians(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """F = df/dx (13x13) and G = df/dn (13x6) at n = 0."""
    q, w = x[QUAT], x[ANG]
    dq = geo.rotvec_to_quat(w * dt)
    dq_dtheta = geo.rotvec_to_quat_jacobian(w * dt)
    Lq = geo.quat_left_matrix(q)
    F = np.eye(STATE_DIM)
    F[POS, VEL] = np.eye(3) * dt
    F[QUAT, QUAT] = geo.quat_right_matrix(dq)            # q * dq = Rmat(dq) q
    F[QUAT, ANG] = Lq @ dq_dtheta * dt
    G = np.zeros((STATE_DIM, 6))
    G[POS, 0:3] = np.eye(3) * dt * dt
    G[VEL, 0:3] = np.eye(3) * dt
    G[QUAT, 3:6] = Lq @ dq_dtheta * dt * dt
    G[ANG, 3:6] = np.eye(3) * dt
    return F, G


def motion_rate(x: np.ndarray, dt: float) -> np.ndarray:
    """df/d(dt) (13,) of the constant-velocity model at n = 0: how the predicted state
    moves per second of error in the time step."""
    w = x[ANG]
    out = np.zeros(STATE_DIM)
    out[POS] = x[VEL]
    out[QUAT] = geo.quat_left_matrix(x[QUAT]) @ geo.rotvec_to_quat_jacobian(w * dt) @ w
    return out


# ---------------------------------------------------------------------- the EKF update
def normalise_quaternion(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q <- q/|q| and P <- J P J^T with J = d(q/|q|)/dq on the quaternion block."""
    q = x[QUAT]
    n = np.linalg.norm(q)
    Jq = (np.eye(4) - np.outer(q, q) / (n * n)) / n
    x = x.copy()
    x[QUAT] = q / n
    P = P.copy()
    P[QUAT, :] = Jq @ P[QUAT, :]
    P[:, QUAT] = P[:, QUAT] @ Jq.T
    return x, 0.5 * (P + P.T)


def _information(H: np.ndarray, col: np.ndarray, r_inv: np.ndarray, innovation: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """H^T R^-1 H (D,D) and H^T R^-1 y (D,) from the block structure of H: a map point's
    rows touch only the pose (7 columns), a filter point's rows the pose and its own rho.
    O(n) small products instead of a 2n x D GEMM (which multithreaded BLAS runs badly on
    a loaded machine)."""
    n, D = len(col), H.shape[1]
    Hn = H.reshape(n, 2, D)
    Hp = Hn[:, :, POSE]                                            # (n,2,7)
    w = r_inv.reshape(n, 2)
    wy = w * innovation.reshape(n, 2)
    A = np.zeros((D, D))
    b = np.zeros(D)
    A[POSE, POSE] = np.einsum('nki,nk,nkj->ij', Hp, w, Hp)
    b[POSE] = np.einsum('nki,nk->i', Hp, wy)
    f = np.flatnonzero(col >= 0)
    if len(f):
        c = col[f]
        hr = Hn[f, :, :][np.arange(len(f)), :, c]                  # (b,2) d/drho
        cross = np.einsum('fki,fk,fk->fi', Hp[f], w[f], hr)        # (b,7)
        np.add.at(A, (slice(0, 7), c), cross.T)
        np.add.at(A, (c, slice(0, 7)), cross)
        np.add.at(A, (c, c), np.sum(w[f] * hr * hr, axis=1))
        np.add.at(b, c, np.sum(hr * wy[f], axis=1))
    return A, b


def _nis(P: np.ndarray, HtRH: np.ndarray, Hty: np.ndarray, innovation: np.ndarray,
         r_inv: np.ndarray) -> float:
    """y^T S^-1 y by Woodbury, S^-1 = R^-1 - R^-1 H (I + P H^T R^-1 H)^-1 P H^T R^-1,
    from HtRH = H^T R^-1 H and Hty = H^T R^-1 y (D x D work only)."""
    return float(innovation @ (innovation * r_inv)
                 - Hty @ np.linalg.solve(np.eye(len(P)) + P @ HtRH, P @ Hty))


def update(x: np.ndarray, P: np.ndarray, z_px: np.ndarray, model: ReprojectionModel,
           sigma_px: float | np.ndarray, iterations: int
           ) -> tuple[np.ndarray, np.ndarray, UpdateStats]:
    """THE EKF update (docs/method.md §5): EKF (iterations=1) or iterated EKF, n points.

    x (D,), P (D,D): prior state and covariance (D = 13, or 13 + in-filter points);
    z_px (n,2) measured ideal pixels of the n measurements of `model`; sigma_px: pixel
    noise std, one value or one per point (n,), i.e. a diagonal R. Returns (x+, P+, stats).

    Steps, with B = P H^T R^-1 and C = B H = P H^T R^-1 H (D x D):
      1. innovation      y = z - h(x)
      2. gain            K = B - C (I + C)^-1 B = M B,  M = (I + C)^-1  (Woodbury: a
                         D x D solve instead of the 2n x 2n inverse of S; form (c) of the
                         EKFPnP reference)
      3. state           x+ = x + K y = x + M P H^T R^-1 y
      4. IEKF            iterations > 1: relinearise at x_i, y_i = z - h(x_i) - H (x - x_i)
      5. covariance      Joseph form P+ = (I - KH) P (I - KH)^T + K R K^T, which with
                         I - KH = M and K R K^T = M C P M^T is M (P + C P) M^T: symmetric
                         PSD under rounding, and K is never formed (D x 2n)
      6. renormalise q and map P through the normalisation Jacobian."""
    n = len(z_px)
    if n == 0:
        return x, P, UpdateStats()
    z = np.asarray(z_px, float).reshape(-1)
    sigma = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
    r_inv = np.repeat(1.0 / (sigma * sigma), 2)
    I = np.eye(len(x))
    px0, _, H0 = model.observe(x)
    y0 = z - px0.reshape(-1)                                       # 1. innovation
    x_i, H, C, M = x, H0, None, None
    stats = UpdateStats(n_used=n, rms_innovation_px=float(np.sqrt(np.mean(y0 ** 2) * 2)))
    for it in range(max(1, iterations)):
        if it == 0:
            y_lin = y0
        else:                                                      # 4. IEKF
            px_i, _, H = model.observe(x_i)
            y_lin = z - px_i.reshape(-1) - H @ (x - x_i)
        HtRH, Hty = _information(H, model.col, r_inv, y_lin)
        if it == 0:
            stats.nis = _nis(P, HtRH, Hty, y0, r_inv)
        C = P @ HtRH
        M = np.linalg.inv(I + C)                                   # 2. gain K = M B
        x_i = x + M @ (P @ Hty)                                    # 3. state
        x_i[QUAT] /= np.linalg.norm(x_i[QUAT])
    P_new = M @ (P + C @ P) @ M.T                                  # 5. Joseph form
    x_new, P_new = normalise_quaternion(x_i, P_new)                # 6.
    if not np.all(np.isfinite(x_new)) or not np.all(np.isfinite(P_new)):
        raise FilterError('state or covariance became non-finite in the update')
    px1, _, _ = model.observe(x_new, with_jacobian=False)
    stats.rms_residual_px = float(np.sqrt(np.mean((z - px1.reshape(-1)) ** 2) * 2))
    return x_new, P_new, stats


def pose_innovation(x: np.ndarray, P: np.ndarray, T_world_cam: np.ndarray,
                    cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A measured camera pose against the state: the innovation y (6,) =
    (r_z - r, log(R_z R^T)) in (position, world rotation vector), the Jacobian H (6, D)
    that maps the state to it (dtheta = 2 [0 I3] Rmat(q)^T dq, as in
    `CameraEKF.pose_covariance`), and the NIS y^T (H P H^T + cov)^-1 y."""
    H = np.zeros((6, len(x)))
    H[0:3, POS] = np.eye(3)
    H[3:6, QUAT] = 2.0 * geo.quat_right_matrix(x[QUAT]).T[1:, :]
    R_now = geo.quat_to_matrix(x[QUAT])
    y = np.concatenate((T_world_cam[:3, 3] - x[POS],
                        geo.quat_to_rotvec(geo.matrix_to_quat(T_world_cam[:3, :3] @ R_now.T))))
    S = H @ P @ H.T + cov
    return y, H, float(y @ np.linalg.solve(0.5 * (S + S.T), y))


def pose_update(x: np.ndarray, P: np.ndarray, T_world_cam: np.ndarray,
                cov: np.ndarray, keep_covariance: bool,
                prior_pose_cov: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """An EKF update with a measured camera pose `T_world_cam`, whose 6x6 covariance of
    (position, world rotation vector) is `cov` (pose_innovation). Returns (x+, P+).

    prior_pose_cov: the pose's prior covariance to weigh the measurement against, when
    it is not the state's own H P H^T (the published covariance, which counts the map's
    error that P leaves out, docs/method.md §14): the pose moves by
    prior (prior + cov)^-1 y and the rest of the state follows by its regression on the
    pose in P. keep_covariance: correct the mean only and leave P as it was, for a
    measurement that shares errors with the state (the local map's keyframe poses rest
    on pixels the filter has used: counting them again would make the filter confidently
    wrong; docs/method.md §12.2)."""
    y, H, _ = pose_innovation(x, P, T_world_cam, cov)
    PHt = P @ H.T
    HPH = H @ PHt
    prior = HPH if prior_pose_cov is None else np.asarray(prior_pose_cov, float)
    S = prior + cov
    S_inv_y = np.linalg.solve(0.5 * (S + S.T), y)
    if prior_pose_cov is None:
        dx = PHt @ S_inv_y
    else:
        dx = PHt @ np.linalg.solve(0.5 * (HPH + HPH.T), prior @ S_inv_y)
    x_new = x.copy()
    x_new[:QUAT.start] += dx[:QUAT.start]
    x_new[QUAT.stop:] += dx[QUAT.stop:]
    # the rotation part as a rotation (exact for any size), not a sum of quaternions
    dtheta = 2.0 * (geo.quat_right_matrix(x[QUAT]).T[1:, :] @ dx[QUAT])
    x_new[QUAT] = geo.quat_multiply(geo.rotvec_to_quat(dtheta), x[QUAT])
    if keep_covariance:
        P_new = P
    else:
        K = np.linalg.solve(0.5 * (S + S.T), PHt.T).T
        IKH = np.eye(len(x)) - K @ H
        P_new = IKH @ P @ IKH.T + K @ cov @ K.T
    x_new, P_new = normalise_quaternion(x_new, P_new)
    if not np.all(np.isfinite(x_new)) or not np.all(np.isfinite(P_new)):
        raise FilterError('state or covariance became non-finite in a pose update')
    return x_new, P_new


class CameraEKF:
    """13-state camera EKF. Attributes: x (13,), P (13,13), intrinsics (3,3)."""

    def __init__(self, intrinsics: np.ndarray) -> None:
        self.intrinsics = np.asarray(intrinsics, dtype=float)
        self.x = np.zeros(STATE_DIM)
        self.x[QUAT] = (1.0, 0.0, 0.0, 0.0)
        self.P = np.eye(STATE_DIM) * 1e-6
        self.last_update = UpdateStats()

    # ------------------------------------------------------------------ state access
    def initialise(self, T_world_cam: np.ndarray, v_world: np.ndarray, w_cam: np.ndarray,
                   pose_sigma: float, velocity_sigma: float,
                   angular_velocity_sigma: float) -> None:
        """Set the state and a diagonal prior (docs/method.md §3)."""
        self.x[POS] = T_world_cam[:3, 3]
        self.x[QUAT] = geo.matrix_to_quat(T_world_cam[:3, :3])
        self.x[VEL] = v_world
        self.x[ANG] = w_cam
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[POS, POS] = np.eye(3) * pose_sigma ** 2
        # world-frame rotation error dtheta ~ N(0, sigma^2 I) maps to the quaternion as
        # dq = 0.5 [0, dtheta] * q = 0.5 Rmat(q)[:, 1:] dtheta
        Jq = 0.5 * geo.quat_right_matrix(self.x[QUAT])[:, 1:]
        P[QUAT, QUAT] = pose_sigma ** 2 * (Jq @ Jq.T)
        P[VEL, VEL] = np.eye(3) * velocity_sigma ** 2
        P[ANG, ANG] = np.eye(3) * angular_velocity_sigma ** 2
        self.P = P

    @property
    def R_world_cam(self) -> np.ndarray:
        return geo.quat_to_matrix(self.x[QUAT])

    @property
    def T_world_cam(self) -> np.ndarray:
        return geo.make_T(self.R_world_cam, self.x[POS])

    def set_pose(self, T_world_cam: np.ndarray, pose_cov: np.ndarray) -> None:
        """Overwrite position and orientation with an external estimate (the EPnP
        baseline) and its 6x6 (position, world rotation vector) covariance; the pose's
        correlation with the velocities is dropped."""
        x, P = self.x, self.P
        x[POS] = T_world_cam[:3, 3]
        x[QUAT] = geo.matrix_to_quat(T_world_cam[:3, :3])
        P[POSE, :] = 0.0
        P[:, POSE] = 0.0
        P[POS, POS] = pose_cov[:3, :3]
        # world-frame rotation vector -> quaternion, as in `initialise`
        Jq = 0.5 * geo.quat_right_matrix(x[QUAT])[:, 1:]
        P[QUAT, QUAT] = Jq @ pose_cov[3:, 3:] @ Jq.T
        P[POS, QUAT] = pose_cov[:3, 3:] @ Jq.T
        P[QUAT, POS] = P[POS, QUAT].T

    # ------------------------------------------------------------------ prediction
    def predict(self, dt: float, accel_sigma: float, angular_accel_sigma: float,
                fading_memory: float, stamp_sigma_s: float = 0.0) -> None:
        """Constant-velocity prediction over dt seconds (Jacobians at the prior state).
        `stamp_sigma_s`: the standard deviation of the image stamp's error; the state
        moves by (v, q * w / 2) per second of it (docs/method.md §3.5)."""
        if not dt > 0.0:
            raise ValueError(f'dt must be positive, got {dt}')
        F, G = motion_jacobians(self.x, dt)
        Qn = np.diag([accel_sigma ** 2] * 3 + [angular_accel_sigma ** 2] * 3)
        # fading memory (Qi et al. 2016, docs/method.md §3.4): inflate the prior by
        # lambda >= 1
        self.P = fading_memory * (F @ self.P @ F.T) + G @ Qn @ G.T
        if stamp_sigma_s > 0.0:
            J_t = motion_rate(self.x, dt)
            self.P += stamp_sigma_s ** 2 * np.outer(J_t, J_t)
        self.x = motion_model(self.x, dt)
        self.x, self.P = normalise_quaternion(self.x, self.P)

    # ------------------------------------------------------------------ observation
    def observe(self, X_world: np.ndarray, x: np.ndarray | None = None,
                with_jacobian: bool = True):
        """Predicted ideal pixels of (N,3) map points, and optionally H (2N,13).

        Returns (px (N,2), in_front (N,) bool, H or None). H rows are interleaved
        (u0, v0, u1, v1, ...), matching z.reshape(-1)."""
        model = ReprojectionModel.of_map_points(self.intrinsics, X_world)
        return model.observe(self.x if x is None else x, with_jacobian)

    # ------------------------------------------------------------------ update
    def update(self, z_px: np.ndarray, X_world: np.ndarray, sigma_px: float | np.ndarray,
               iterations: int) -> UpdateStats:
        """`update` of this filter with n fixed map points X_world (n,3) seen at z_px."""
        model = ReprojectionModel.of_map_points(self.intrinsics, X_world)
        self.x, self.P, self.last_update = update(self.x, self.P, z_px, model, sigma_px,
                                                  iterations)
        return self.last_update

    def pose_nis(self, T_world_cam: np.ndarray, cov: np.ndarray) -> float:
        """The NIS of a measured pose against this filter's own covariance
        (pose_innovation)."""
        return pose_innovation(self.x, self.P, T_world_cam, cov)[2]

    def update_pose(self, T_world_cam: np.ndarray, cov: np.ndarray,
                    keep_covariance: bool, prior_pose_cov: np.ndarray | None = None
                    ) -> None:
        """`pose_update` of this filter."""
        self.x, self.P = pose_update(self.x, self.P, T_world_cam, cov, keep_covariance,
                                     prior_pose_cov)

    # ------------------------------------------------------------------ outputs
    def pose_covariance(self) -> np.ndarray:
        """6x6 covariance of (position, rotation vector) in the world frame.

        Rotation error as a world-frame (left) perturbation, q_true = exp(dtheta) * q,
        hence dtheta = 2 [0 I3] Rmat(q)^T dq: the ROS convention of rotations about the
        fixed axes of the parent (odom) frame."""
        J = np.zeros((6, STATE_DIM))
        J[0:3, POS] = np.eye(3)
        J[3:6, QUAT] = 2.0 * geo.quat_right_matrix(self.x[QUAT]).T[1:, :]
        cov = J @ self.P @ J.T
        return 0.5 * (cov + cov.T)

    def twist_cam(self) -> tuple[np.ndarray, np.ndarray]:
        """Twist in the camera frame: (v^C, w^C) (6,) and its 6x6 covariance."""
        v_cam, J_q = rotated_by_quat_conj_jacobian(self.x[QUAT], self.x[VEL][None, :])
        J = np.zeros((6, STATE_DIM))
        J[0:3, QUAT] = J_q[0]
        J[0:3, VEL] = geo.quat_to_matrix(self.x[QUAT]).T
        J[3:6, ANG] = np.eye(3)
        cov = J @ self.P @ J.T
        return np.concatenate((v_cam[0], self.x[ANG])), 0.5 * (cov + cov.T)

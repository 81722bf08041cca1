"""Camera-only EKF of the hybrid method (METHOD.md section 1): the EKF update lives here.

The state holds only the camera; the map points are fixed, triangulated inputs to the
observation model, so an update costs O(n) in the number of observed points.

State x (13), named slices below (MonoSLAM / Civera et al. 2010 convention):
    POS  r^W   camera centre in the world frame                     [m]
    QUAT q^WC  orientation, Hamilton wxyz, camera -> world rotation  [-]
    VEL  v^W   linear velocity in the world frame                   [m/s]
    ANG  w^C   angular velocity in the camera frame                 [rad/s]
METHOD.md writes the quaternion as world->camera (q^CW); we keep its conjugate so that the
angular velocity is a body rate (what nav_msgs/Odometry's twist wants). Same filter.

Motion model, constant velocity, acceleration impulses n = [a, alpha] (METHOD.md sec. 1):
    r' = r + (v + a dt) dt,   q' = q * quat((w + alpha dt) dt),   v' = v + a dt,
    w' = w + alpha dt,        Q = diag(sigma_a^2 I3, sigma_alpha^2 I3)
    P' = S F P F^T + G Q G^T  with the fading-memory factor S >= 1 (METHOD.md section 2).
Observation of a map point X^W: X^C = R(q)^T (X^W - r), u = fx X/Z + cx, v = fy Y/Z + cy.
Update: information (Woodbury) form with isotropic pixel noise R = sigma^2 I,
    B = P H^T R^-1,  C = B H (13x13),  K = B - C (I + C)^-1 B
so only a 13x13 system is solved (METHOD.md sec. 1 variant (c)); Joseph-form covariance
    P+ = (I - K H) P (I - K H)^T + K R K^T
which stays symmetric positive semi-definite under rounding. After each step the quaternion
is renormalised and P is transformed with the normalisation Jacobian.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from . import geometry as geo

logger = logging.getLogger(__name__)

POS = slice(0, 3)
QUAT = slice(3, 7)
VEL = slice(7, 10)
ANG = slice(10, 13)
STATE_DIM = 13
#: the part of the state the observation depends on (position and quaternion)
POSE = slice(0, 7)


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


def rotated_by_quat_conj_jacobian(q_wxyz: np.ndarray, y: np.ndarray
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """R(q)^T y and its derivative w.r.t. q, for (N,3) vectors y.

    R(q)^T y = R(q*) y = (w^2 - v.v) y + 2 (v.y) v - 2 w (v x y) with q = (w, v):
    the quadratic form of [0, X] = q* [0, y] q, differentiated term by term.
    Returns (N,3) rotated vectors and (N,3,4) Jacobians.
    """
    w, v = q_wxyz[0], q_wxyz[1:]
    vy = y @ v                                    # (N,)
    vxy = np.cross(v, y)                          # (N,3) = v x y
    out = (w * w - v @ v) * y + 2.0 * vy[:, None] * v - 2.0 * w * vxy
    J = np.empty((len(y), 3, 4))
    J[:, :, 0] = 2.0 * w * y - 2.0 * vxy
    # d/dv: -2 y v^T + 2 (v.y) I + 2 v y^T + 2 w [y]_x
    J[:, :, 1:] = (-2.0 * y[:, :, None] * v[None, None, :]
                   + 2.0 * vy[:, None, None] * np.eye(3)[None]
                   + 2.0 * v[None, :, None] * y[:, None, :])
    yx, yy, yz = y[:, 0], y[:, 1], y[:, 2]
    J[:, 0, 2] += 2.0 * w * -yz
    J[:, 0, 3] += 2.0 * w * yy
    J[:, 1, 1] += 2.0 * w * yz
    J[:, 1, 3] += 2.0 * w * -yx
    J[:, 2, 1] += 2.0 * w * -yy
    J[:, 2, 2] += 2.0 * w * yx
    return out, J


def pinhole_project(X_cam: np.ndarray, K: np.ndarray, with_jacobian: bool = True,
                    min_depth: float = 1e-6):
    """Ideal pixels (n,2) of camera-frame points, in-front mask (n,) and, optionally, the
    pinhole Jacobian d(u,v)/dX^C (n,2,3): u = fx X/Z + cx, v = fy Y/Z + cy."""
    Z = X_cam[:, 2]
    in_front = Z > min_depth
    inv_z = 1.0 / np.where(in_front, Z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    px = np.column_stack((fx * X_cam[:, 0] * inv_z + cx, fy * X_cam[:, 1] * inv_z + cy))
    if not with_jacobian:
        return px, in_front, None
    J_pi = np.zeros((len(X_cam), 2, 3))
    J_pi[:, 0, 0] = fx * inv_z
    J_pi[:, 0, 2] = -fx * X_cam[:, 0] * inv_z ** 2
    J_pi[:, 1, 1] = fy * inv_z
    J_pi[:, 1, 2] = -fy * X_cam[:, 1] * inv_z ** 2
    return px, in_front, J_pi


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


class CameraEKF:
    """13-state camera EKF. Attributes: x (13,), P (13,13), K (3,3) intrinsics."""

    def __init__(self, K: np.ndarray) -> None:
        self.K = np.asarray(K, dtype=float)
        self.x = np.zeros(STATE_DIM)
        self.x[QUAT] = (1.0, 0.0, 0.0, 0.0)
        self.P = np.eye(STATE_DIM) * 1e-6
        self.last_update = UpdateStats()

    # ------------------------------------------------------------------ state access
    def initialise(self, T_world_cam: np.ndarray, v_world: np.ndarray, w_cam: np.ndarray,
                   pose_sigma: float, velocity_sigma: float,
                   angular_velocity_sigma: float) -> None:
        """Set the state and a diagonal prior (METHOD.md sec. 1 step 2)."""
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

    # ------------------------------------------------------------------ prediction
    def predict(self, dt: float, accel_sigma: float, angular_accel_sigma: float,
                fading_memory: float = 1.0) -> None:
        """Constant-velocity prediction over dt seconds (Jacobians at the prior state)."""
        if not dt > 0.0:
            raise ValueError(f'dt must be positive, got {dt}')
        F, G = motion_jacobians(self.x, dt)
        Qn = np.diag([accel_sigma ** 2] * 3 + [angular_accel_sigma ** 2] * 3)
        # fading memory (Qi et al. 2016): inflate the propagated prior by S >= 1
        self.P = fading_memory * (F @ self.P @ F.T) + G @ Qn @ G.T
        self.x = motion_model(self.x, dt)
        self._normalise_quaternion()

    def _normalise_quaternion(self) -> None:
        """q <- q/|q| and P <- J P J^T with J = d(q/|q|)/dq on the quaternion block."""
        q = self.x[QUAT]
        n = np.linalg.norm(q)
        J = np.eye(STATE_DIM)
        J[QUAT, QUAT] = (np.eye(4) - np.outer(q, q) / (n * n)) / n
        self.x[QUAT] = q / n
        self.P = J @ self.P @ J.T
        self.P = 0.5 * (self.P + self.P.T)

    # ------------------------------------------------------------------ observation
    def observe(self, X_world: np.ndarray, x: np.ndarray | None = None,
                with_jacobian: bool = True):
        """Predicted ideal pixels of (N,3) map points, and optionally H (2N,13).

        Returns (px (N,2), in_front (N,) bool, H or None). H rows are interleaved
        (u0, v0, u1, v1, ...), matching z.reshape(-1)."""
        x = self.x if x is None else x
        y = np.asarray(X_world, dtype=float) - x[POS]
        X_cam, dXc_dq = rotated_by_quat_conj_jacobian(x[QUAT], y)
        px, in_front, J_pi = pinhole_project(X_cam, self.K, with_jacobian, min_depth=1e-6)
        if not with_jacobian:
            return px, in_front, None
        n = len(X_world)
        # dX^C/dr = -R^T (the same for every point); dX^C/dq from the quadratic form
        R_cw = geo.quat_to_matrix(x[QUAT]).T * np.dot(x[QUAT], x[QUAT])
        H = np.zeros((n, 2, STATE_DIM))
        H[:, :, POS] = -J_pi @ R_cw
        H[:, :, QUAT] = J_pi @ dXc_dq
        return px, in_front, H.reshape(2 * n, STATE_DIM)

    # ------------------------------------------------------------------ update
    @staticmethod
    def _r_inv(sigma_px: float | np.ndarray, n: int) -> np.ndarray:
        """Diagonal of R^-1 (2n,), from one sigma or one sigma per point (n,)."""
        sigma = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
        return np.repeat(1.0 / (sigma * sigma), 2)

    def gain(self, H: np.ndarray, sigma_px: float | np.ndarray) -> np.ndarray:
        """Kalman gain by the Woodbury identity (13x13 solve instead of 2n x 2n).

        K = B - C (I + C)^-1 B, B = P H^T R^-1, C = B H (METHOD.md sec. 1 form (c))."""
        r_inv = self._r_inv(sigma_px, H.shape[0] // 2)
        B = (self.P @ H.T) * r_inv[None, :]            # 13 x 2n
        C = B @ H                                      # 13 x 13
        return B - C @ np.linalg.solve(np.eye(STATE_DIM) + C, B)

    def update(self, z_px: np.ndarray, X_world: np.ndarray, sigma_px: float | np.ndarray,
               iterations: int = 1) -> UpdateStats:
        """EKF (iterations=1) or iterated EKF (Gauss-Newton) update with n points.

        z_px: (n,2) measured ideal pixels; X_world: (n,3) their fixed map points;
        sigma_px: pixel noise std, one value or one per point (n,) (diagonal R)."""
        n = len(z_px)
        if n == 0:
            self.last_update = UpdateStats()
            return self.last_update
        z = np.asarray(z_px, dtype=float).reshape(-1)
        x_prior = self.x.copy()
        x_i = x_prior
        px0, _, H0 = self.observe(X_world, x_prior)
        y0 = z - px0.reshape(-1)
        stats = UpdateStats(n_used=n, nis=self._nis(H0, y0, sigma_px),
                            rms_innovation_px=float(np.sqrt(np.mean(y0 ** 2)) * np.sqrt(2)))
        H, K = H0, None
        for it in range(max(1, iterations)):
            if it == 0:
                H, y_lin = H0, y0
            else:
                px_i, _, H = self.observe(X_world, x_i)
                # IEKF: linearise at x_i, correct for the offset from the prior
                y_lin = z - px_i.reshape(-1) - H @ (x_prior - x_i)
            K = self.gain(H, sigma_px)
            x_i = x_prior + K @ y_lin
            x_i[QUAT] /= np.linalg.norm(x_i[QUAT])
        self.x = x_i
        # Joseph form: P+ = (I-KH) P (I-KH)^T + K R K^T; symmetric PSD under rounding
        I_KH = np.eye(STATE_DIM) - K @ H
        r_diag = 1.0 / self._r_inv(sigma_px, n)
        self.P = I_KH @ self.P @ I_KH.T + (K * r_diag[None, :]) @ K.T
        self._normalise_quaternion()
        if not np.all(np.isfinite(self.x)) or not np.all(np.isfinite(self.P)):
            raise FilterError('state or covariance became non-finite in the update')
        px1, _, _ = self.observe(X_world, with_jacobian=False)
        stats.rms_residual_px = float(np.sqrt(np.mean((z - px1.reshape(-1)) ** 2))
                                      * np.sqrt(2))
        self.last_update = stats
        return stats

    def _nis(self, H: np.ndarray, y: np.ndarray, sigma_px: float | np.ndarray) -> float:
        """y^T S^-1 y with S = H P H^T + R, via Woodbury (no 2n x 2n inverse):
        S^-1 = R^-1 - R^-1 H (I + P H^T R^-1 H)^-1 P H^T R^-1."""
        r_inv = self._r_inv(sigma_px, H.shape[0] // 2)
        Hty = H.T @ (y * r_inv)
        C = (self.P @ H.T) @ (H * r_inv[:, None])
        return float(y @ (y * r_inv)
                     - Hty @ np.linalg.solve(np.eye(STATE_DIM) + C, self.P @ Hty))

    def innovation_covariances(self, H: np.ndarray, sigma_px: float | np.ndarray
                               ) -> np.ndarray:
        """Per-point 2x2 innovation covariances S_i = H_i P H_i^T + R_i, (n,2,2)."""
        Hn = H.reshape(-1, 2, STATE_DIM)[:, :, POSE]
        P = self.P[POSE, POSE]
        S = Hn @ P @ Hn.transpose(0, 2, 1)
        r = 1.0 / self._r_inv(sigma_px, len(Hn))[::2]
        S[:, 0, 0] += r
        S[:, 1, 1] += r
        return S

    def single_point_states(self, H: np.ndarray, y: np.ndarray, idx: np.ndarray,
                            sigma_px: float) -> np.ndarray:
        """States after a partial update with ONE point each (1-point RANSAC hypotheses).

        Covariance is not touched (Civera et al. 2010, Algorithm 1). Returns (h,13)."""
        Hn = H.reshape(-1, 2, STATE_DIM)[idx]                  # (h,2,13)
        yn = y.reshape(-1, 2)[idx]                             # (h,2)
        PHt = self.P @ Hn.transpose(0, 2, 1)                   # (h,13,2)
        S = Hn @ PHt
        r = np.broadcast_to(np.asarray(sigma_px, float) ** 2, (H.shape[0] // 2,))[idx]
        S[:, 0, 0] += r
        S[:, 1, 1] += r
        K = PHt @ np.linalg.inv(S)
        states = self.x[None, :] + (K @ yn[:, :, None])[:, :, 0]
        states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1, keepdims=True)
        return states

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

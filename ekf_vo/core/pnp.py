"""EPnP per-frame baseline (the comparison method of the EKFPnP paper).

Each frame's pose comes from the current 2D-3D matches alone: EPnP inside RANSAC
(cv2.solvePnPRansac, SOLVEPNP_EPNP), then Levenberg-Marquardt refinement on the inliers
(cv2.solvePnPRefineLM, the "EPnP+GN" of the paper). The covariance is the Gauss-Newton
approximation sigma^2 (J^T J)^-1 of the reprojection least squares, so the baseline can be
published like the EKF.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from . import geometry as geo

logger = logging.getLogger(__name__)


@dataclass
class PnPResult:
    ok: bool
    T_world_cam: np.ndarray | None = None
    pose_cov: np.ndarray | None = None      #: 6x6 (position, world rotation vector)
    inliers: np.ndarray | None = None       #: (n,) bool
    reason: str = ''


def solve_epnp(z_px: np.ndarray, X_world: np.ndarray, K: np.ndarray, sigma_px: float,
               ransac_px: float, refine: bool = True) -> PnPResult:
    """Pose of the camera from n >= 6 matches (ideal pixels (n,2), points (n,3))."""
    n = len(z_px)
    if n < 6:
        return PnPResult(False, reason=f'{n} matches, EPnP needs 6')
    obj = np.ascontiguousarray(X_world, dtype=np.float64)
    img = np.ascontiguousarray(z_px, dtype=np.float64)
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        obj, img, K, None, flags=cv2.SOLVEPNP_EPNP, reprojectionError=ransac_px,
        iterationsCount=100, confidence=0.999)
    if not ok or idx is None or len(idx) < 6:
        return PnPResult(False, reason='EPnP RANSAC failed')
    inl = np.zeros(n, bool)
    inl[idx.ravel()] = True
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    R_cw, _ = cv2.Rodrigues(rvec)
    T_cam_world = geo.make_T(R_cw, tvec.ravel())
    T_world_cam = geo.invert_T(T_cam_world)
    # Gauss-Newton covariance of (rvec, tvec) of T_cam_world from the projection Jacobian
    _, J = cv2.projectPoints(obj[inl], rvec, tvec, K, None)
    J = J[:, :6]                                         # d(u,v)/d(rvec, tvec)
    try:
        cov_rt = sigma_px ** 2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return PnPResult(False, reason='degenerate PnP geometry')
    # to (camera centre, world rotation vector): c = -R^T t; world rotation = R^T
    # dtheta_world = -R^T dtheta_cam (rvec perturbs R_cw on the left);
    # dc = [R^T t]_x ... computed numerically below to avoid sign slips
    A = _cam_world_to_world_cam_jacobian(rvec.ravel(), tvec.ravel())
    cov = A @ cov_rt @ A.T
    return PnPResult(True, T_world_cam, 0.5 * (cov + cov.T), inl)


def _cam_world_to_world_cam_jacobian(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """d(c, theta_world)/d(rvec, tvec) by central differences (6x6, cheap, exact enough)."""
    def f(p: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(p[:3])
        return np.concatenate((-R.T @ p[3:], geo.quat_to_rotvec(geo.matrix_to_quat(R.T))))
    p0 = np.concatenate((rvec, tvec))
    f0 = f(p0)
    R0 = geo.quat_to_matrix(geo.rotvec_to_quat(f0[3:]))
    A = np.zeros((6, 6))
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        fp, fm = f(p0 + d), f(p0 - d)
        A[:3, i] = (fp[:3] - fm[:3]) / (2 * eps)
        # world-frame (left) rotation perturbation: log(R(+) R0^T)
        Rp = geo.quat_to_matrix(geo.rotvec_to_quat(fp[3:])) @ R0.T
        Rm = geo.quat_to_matrix(geo.rotvec_to_quat(fm[3:])) @ R0.T
        A[3:, i] = (geo.quat_to_rotvec(geo.matrix_to_quat(Rp))
                    - geo.quat_to_rotvec(geo.matrix_to_quat(Rm))) / (2 * eps)
    return A

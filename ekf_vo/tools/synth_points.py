"""Synthetic point-feature sequences for the camera EKF (no images): the papers' protocols.

A sequence is a set of world points, camera poses T_world_cam along a smooth 6-DoF path and
noisy ideal-pixel observations; `run_ekf` tracks one with the camera EKF on the exact map
from a ground-truth start. The rendered-image counterpart is ekf_vo.tools.synth. Used by the
benchmarks (bench.bunny, bench.consistency: NEES, the bunny experiment of docs/method.md §9.4)
and by the tests of the estimator.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.ekf import CameraEKF
from ekf_vo.core.observation import ReprojectionModel
from ekf_vo.core.robust_update import RansacSettings, robust_update


@dataclass
class Sequence:
    K: np.ndarray                 #: 3x3
    X_world: np.ndarray           #: (N,3)
    T_world_cam: np.ndarray       #: (F,4,4)
    stamps_s: np.ndarray          #: (F,)
    width: int = 640
    height: int = 480


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0, 0, 1.0]),
            roll_rad: float = 0.0) -> np.ndarray:
    """T_world_cam of an optical camera at `position` looking at `target` (z forward,
    y down), rolled about its optical axis by `roll_rad`."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0, 0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack((x, y, z))
    Rz = geo.quat_to_matrix(geo.rotvec_to_quat(np.array([0, 0, roll_rad])))
    return geo.make_T(R @ Rz, position)


def smooth_orbit(n_frames: int, rate_hz: float, radius: float = 6.0, seed: int = 0,
                 target: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A smooth path around `target` on which all six DoF change; returns (T, stamps)."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, 6)
    target = np.zeros(3) if target is None else target
    t = np.arange(n_frames) / rate_hz
    T = np.empty((n_frames, 4, 4))
    for k, tk in enumerate(t):
        ang = 0.35 * tk + ph[0]
        r = radius * (1.0 + 0.25 * np.sin(0.5 * tk + ph[1]))
        pos = target + np.array([r * np.cos(ang), r * np.sin(ang),
                                 1.0 + 0.8 * np.sin(0.6 * tk + ph[2])])
        look = target + 0.5 * np.array([np.sin(0.7 * tk + ph[3]), np.cos(0.5 * tk + ph[4]),
                                        0.3 * np.sin(0.9 * tk)])
        T[k] = look_at(pos, look, roll_rad=0.15 * np.sin(0.8 * tk + ph[5]))
    return T, t


def project(K: np.ndarray, T_world_cam: np.ndarray, X_world: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pixels (N,2) and depth (N,) of world points seen from T_world_cam."""
    Xc = geo.transform_points(geo.invert_T(T_world_cam), X_world)
    px = np.column_stack((K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2],
                          K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]))
    return px, Xc[:, 2]


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """(6,) error (position, world rotation vector) matching EKF.pose_covariance():
    R_gt = exp(dtheta) R_est."""
    dtheta = geo.quat_to_rotvec(geo.matrix_to_quat(T_gt[:3, :3] @ T_est[:3, :3].T))
    return np.concatenate((T_gt[:3, 3] - T_est[:3, 3], dtheta))


def run_ekf(seq: Sequence, sigma_px: float, rng: np.random.Generator,
            accel_sigma: float = 2.0, angular_accel_sigma: float = 2.0,
            filter_sigma_px: float | None = None, one_point_ransac: bool = False,
            outlier_fraction: float = 0.0, iterations: int = 1,
            fading_memory: float = 1.0) -> dict:
    """Track the sequence with the camera EKF on the exact map from the GT of frames 0, 1.

    Returns per-frame estimates, covariances, NEES and inlier flags."""
    K = seq.K
    T0, T1 = seq.T_world_cam[0], seq.T_world_cam[1]
    dt0 = seq.stamps_s[1] - seq.stamps_s[0]
    ekf = CameraEKF(K)
    w = geo.quat_to_rotvec(geo.matrix_to_quat(T0[:3, :3].T @ T1[:3, :3])) / dt0
    ekf.initialise(T1, (T1[:3, 3] - T0[:3, 3]) / dt0, w, 1e-4, 0.05, 0.05)
    fs = sigma_px if filter_sigma_px is None else filter_sigma_px
    settings = dataclasses.replace(RansacSettings.from_config(VoConfig()),
                                   one_point=one_point_ransac, iterations=iterations)
    est, covs, nees, inlier_rates = [], [], [], []
    for k in range(2, len(seq.stamps_s)):
        ekf.predict(seq.stamps_s[k] - seq.stamps_s[k - 1], accel_sigma, angular_accel_sigma,
                    fading_memory)
        px, depth = project(K, seq.T_world_cam[k], seq.X_world)
        vis = (depth > 0.1) & (px[:, 0] >= 0) & (px[:, 0] < seq.width) & \
            (px[:, 1] >= 0) & (px[:, 1] < seq.height)
        z = px[vis] + rng.normal(0.0, sigma_px, (int(vis.sum()), 2))
        is_out = np.zeros(len(z), bool)
        if outlier_fraction > 0:
            is_out = rng.random(len(z)) < outlier_fraction
            z[is_out] += rng.uniform(15, 80, (int(is_out.sum()), 2)) * \
                rng.choice([-1, 1], (int(is_out.sum()), 2))
        model = ReprojectionModel.of_map_points(K, seq.X_world[vis])
        ekf.x, ekf.P, res = robust_update(ekf.x, ekf.P, z, model, fs, rng, settings)
        inlier_rates.append((res.inliers, is_out))
        e = pose_error(ekf.T_world_cam, seq.T_world_cam[k])
        cov = ekf.pose_covariance()
        est.append(ekf.T_world_cam)
        covs.append(cov)
        nees.append(float(e @ np.linalg.solve(cov, e)))
    return {'T_est': np.array(est), 'cov': np.array(covs), 'nees': np.array(nees),
            'inliers': inlier_rates, 'P_final': ekf.P}

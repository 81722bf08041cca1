"""Rotations, quaternions and rigid transforms (numpy only).

Conventions (used across the core):
- Quaternions in the EKF state are Hamilton, scalar first: `q_wxyz`. ROS messages use
  x, y, z, w: conversions are named `*_xyzw`.
- `q_world_cam` / `R_world_cam` rotate camera-frame vectors into the world frame;
  `T_world_cam` (4x4) maps camera-frame points to world points. The camera frame is the
  optical frame: x right, y down, z forward (REP-103 `*_optical`).
- Rotation vectors (axis * angle, radians) are the 3-D rotation parametrisation of all
  published covariances.
"""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """[v]_x such that skew(a) @ b == cross(a, b)."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices (n,3,3) of vectors (n,3): skew_batch(v)[i] @ w = v[i] x w."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def quat_normalize(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion with w >= 0 (the sign is irrelevant for a rotation)."""
    q = np.asarray(q_wxyz, dtype=float)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f'cannot normalise quaternion {q}')
    return q / n


def quat_multiply(a_wxyz: np.ndarray, b_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product a * b."""
    return quat_left_matrix(a_wxyz) @ np.asarray(b_wxyz, dtype=float)


def quat_left_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """L(q) with q * p == L(q) @ p."""
    w, x, y, z = q_wxyz
    return np.array([[w, -x, -y, -z],
                     [x, w, -z, y],
                     [y, z, w, -x],
                     [z, -y, x, w]])


def quat_right_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """R(q) with p * q == R(q) @ p."""
    w, x, y, z = q_wxyz
    return np.array([[w, -x, -y, -z],
                     [x, w, z, -y],
                     [y, -z, w, x],
                     [z, y, -x, w]])


def quat_conjugate(q_wxyz: np.ndarray) -> np.ndarray:
    return np.array([q_wxyz[0], -q_wxyz[1], -q_wxyz[2], -q_wxyz[3]])


def _unit_quat_matrix_entries(w, x, y, z) -> tuple:
    """The 9 entries (row-major) of the rotation matrix of the unit quaternion (w, x, y,
    z); scalars or arrays alike (quat_to_matrix, quat_to_matrix_batch)."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a (not necessarily unit) quaternion, normalised first."""
    return np.array(_unit_quat_matrix_entries(*quat_normalize(q_wxyz))).reshape(3, 3)


def quat_to_matrix_batch(q_wxyz: np.ndarray) -> np.ndarray:
    """`quat_to_matrix` of (n,4) quaternions at once: (n,3,3)."""
    q = np.asarray(q_wxyz, dtype=float).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1)
    if not np.all(np.isfinite(n) & (n >= 1e-12)):
        raise ValueError('cannot normalise a quaternion of the batch')
    return np.stack(_unit_quat_matrix_entries(*(q / n[:, None]).T), axis=1).reshape(-1, 3, 3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (wxyz, w >= 0) of a rotation matrix (Shepperd's method, robust)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * np.sqrt(1.0 + tr)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s,
                      (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s,
                      (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s,
                      (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s,
                      (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q = quat_normalize(q)
    return q if q[0] >= 0 else -q


def quat_wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    return np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]])


def quat_xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    return np.array([q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]])


def rotvec_to_quat(theta: np.ndarray) -> np.ndarray:
    """exp map: rotation vector (rad) -> unit quaternion wxyz."""
    theta = np.asarray(theta, dtype=float)
    angle = np.linalg.norm(theta)
    if angle < 1e-10:
        # second-order Taylor expansion keeps the map smooth at zero
        q = np.array([1.0 - angle * angle / 8.0, *(0.5 * theta)])
        return q / np.linalg.norm(q)
    half = 0.5 * angle
    return np.array([np.cos(half), *(np.sin(half) / angle * theta)])


def rotvec_to_quat_jacobian(theta: np.ndarray) -> np.ndarray:
    """d rotvec_to_quat(theta) / d theta (4x3), exact, with a small-angle limit."""
    theta = np.asarray(theta, dtype=float)
    angle = np.linalg.norm(theta)
    if angle < 1e-6:
        J = np.zeros((4, 3))
        J[0] = -0.25 * theta
        J[1:] = 0.5 * np.eye(3)
        return J
    half = 0.5 * angle
    s, c = np.sin(half), np.cos(half)
    u = theta / angle
    J = np.zeros((4, 3))
    J[0] = -0.5 * s * u
    # d(sin(|t|/2) t/|t|)/dt = (c/2) u u^T + (s/|t|)(I - u u^T)
    J[1:] = 0.5 * c * np.outer(u, u) + (s / angle) * (np.eye(3) - np.outer(u, u))
    return J


def quat_to_rotvec(q_wxyz: np.ndarray) -> np.ndarray:
    """log map: unit quaternion -> rotation vector (rad), angle in [0, pi]."""
    q = quat_normalize(q_wxyz)
    if q[0] < 0:
        q = -q
    vnorm = np.linalg.norm(q[1:])
    if vnorm < 1e-12:
        return 2.0 * q[1:]
    angle = 2.0 * np.arctan2(vnorm, q[0])
    return angle * q[1:] / vnorm


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of R_a^T R_b in degrees (geodesic distance between rotations)."""
    cos = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N,3) points, or (N,4,4) transforms, one per point."""
    if T.ndim == 3:
        return np.einsum('nij,nj->ni', T[:, :3, :3], X) + T[:, :3, 3]
    return X @ T[:3, :3].T + T[:3, 3]


def median_depth(X_world: np.ndarray, T_world_cam: np.ndarray) -> float | None:
    """Median depth along the optical axis of the points X_world (n,3) in front of the
    camera at T_world_cam; None when none is."""
    depth = (np.asarray(X_world, float).reshape(-1, 3) - T_world_cam[:3, 3]) @ \
        T_world_cam[:3, 2]
    depth = depth[depth > 0]
    return float(np.median(depth)) if len(depth) else None


def rotvecs_to_matrices(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (k,3,3) of rotation vectors (k,3) (vectorised Rodrigues)."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-12
    t = np.where(small, 1.0, theta)
    Kx = skew_batch(w / t[:, None])
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3)[None] + s * Kx + c * (Kx @ Kx)

"""Rotations, poses, odometry and their covariances <-> ROS messages.

geometry_msgs/Pose, PoseStamped and nav_msgs/Odometry, read by field name (rclpy and rosbags
classes alike; see :mod:`ekf_vo.bridge.common`).

Conventions: poses are 4x4 homogeneous transforms ``T_parent_child`` (maps points from the
child frame to the parent frame). Quaternions are ``(x, y, z, w)`` (ROS order), unit norm,
``w >= 0``. 6x6 covariances are in ROS order ``(x, y, z, rot X, rot Y, rot Z)``, serialised
row-major.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..core import geometry as geo
from .common import ConversionError, MessageFactory, as_float_array, get_field

__all__ = ['quat_xyzw_to_matrix', 'matrix_to_quat_xyzw', 'pose_msg_to_matrix',
           'pose_to_odometry', 'odometry_to_pose', 'pose_stamped_to_matrix',
           'matrix_to_pose_stamped', 'transform_pose_covariance']


def quat_xyzw_to_matrix(q: Any) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` -> 3x3 rotation matrix (normalised first).

    Raises ConversionError for non-finite or (near-)zero quaternions.
    """
    qa = as_float_array(q, 'quat_xyzw_to_matrix', 'quaternion', (4,))
    if float(np.linalg.norm(qa)) < 1e-12:
        raise ConversionError(f'quat_xyzw_to_matrix: quaternion {qa.tolist()} has zero norm')
    return geo.quat_to_matrix(geo.quat_xyzw_to_wxyz(qa))


def _check_rotation(R: Any, what: str, tol: float = 1e-6) -> np.ndarray:
    Ra = as_float_array(R, what, 'rotation', (3, 3))
    err = float(np.abs(Ra.T @ Ra - np.eye(3)).max())
    if err > tol or np.linalg.det(Ra) <= 0:
        raise ConversionError(
            f'{what}: not a rotation matrix '
            f'(|R^T R - I|max={err:.2e}, det={np.linalg.det(Ra):.6f})')
    return Ra


def matrix_to_quat_xyzw(R: Any, tol: float = 1e-6) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion ``(x, y, z, w)`` with ``w >= 0``.

    Computed by core.geometry.matrix_to_quat (Shepperd's method, accurate near 180
    degrees). Canonical sign as scipy's ``as_quat(canonical=True)``: ``w > 0``, or if
    ``w == 0`` the first non-zero component positive. Raises ConversionError when ``R`` is not
    orthonormal within ``tol`` or has det <= 0.
    """
    q = geo.quat_wxyz_to_xyzw(geo.matrix_to_quat(_check_rotation(R, 'matrix_to_quat_xyzw', tol)))
    if q[3] < 0 or (q[3] == 0 and q[np.flatnonzero(q)[0]] < 0):
        q = -q
    return q


def _check_transform(T: Any, what: str) -> np.ndarray:
    Ta = as_float_array(T, what, 'T', (4, 4))
    if not np.allclose(Ta[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9, rtol=0.0):
        raise ConversionError(f'{what}: last row of T must be (0, 0, 0, 1), got {Ta[3].tolist()}')
    _check_rotation(Ta[:3, :3], what)
    return Ta


def _check_cov6(cov: Any, what: str, name: str) -> np.ndarray:
    """Validate a 6x6 covariance: finite, symmetric, positive diagonal, PSD; return symmetrised."""
    C = as_float_array(cov, what, name, (6, 6), finite=False)
    if not np.isfinite(C).all():
        raise ConversionError(f'{what}: {name} contains NaN or inf')
    scale = float(np.abs(C).max())
    asym = float(np.abs(C - C.T).max())
    if asym > 1e-8 * scale:
        raise ConversionError(f'{what}: {name} is not symmetric (max |C - C^T| = {asym:.3e})')
    diag = np.diag(C)
    if np.any(diag <= 0.0):
        raise ConversionError(
            f'{what}: {name} has a non-positive diagonal {diag.tolist()}; refusing to publish '
            'zero/unknown covariance')
    C = 0.5 * (C + C.T)
    min_eig = float(np.linalg.eigvalsh(C).min())
    if min_eig < -1e-9 * scale:
        raise ConversionError(
            f'{what}: {name} is not positive semi-definite (min eigenvalue {min_eig:.3e})')
    return C


def _vec3(obj: Any, what: str) -> np.ndarray:
    return np.array([float(get_field(obj, 'x', what)), float(get_field(obj, 'y', what)),
                     float(get_field(obj, 'z', what))])


def pose_msg_to_matrix(pose: Any, what: str = 'Pose') -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 (quaternion normalised first)."""
    position = get_field(pose, 'position', what)
    orientation = get_field(pose, 'orientation', what)
    q = [float(get_field(orientation, c, what)) for c in 'xyzw']
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(q)
    T[:3, 3] = _vec3(position, what)
    return T


def _matrix_to_pose_msg(f: MessageFactory, T: np.ndarray) -> Any:
    q = matrix_to_quat_xyzw(T[:3, :3])
    t = T[:3, 3]
    return f.make('geometry_msgs/msg/Pose',
                  position=f.make('geometry_msgs/msg/Point',
                                  x=float(t[0]), y=float(t[1]), z=float(t[2])),
                  orientation=f.make('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]),
                                     z=float(q[2]), w=float(q[3])))


def pose_to_odometry(T_odom_base: np.ndarray, cov6_pose: np.ndarray, twist_lin: Any,
                     twist_ang: Any, cov6_twist: np.ndarray, stamp_ns: int, frame_id: str,
                     child_frame_id: str, typestore: Any = None) -> Any:
    """Build nav_msgs/Odometry from a pose, a twist and their covariances.

    * ``T_odom_base``: 4x4 pose of ``child_frame_id`` (base) in ``frame_id`` (odom).
    * ``cov6_pose``: 6x6 covariance of (x, y, z, rot X, rot Y, rot Z) about fixed axes of
      ``frame_id`` (use :func:`transform_pose_covariance` to re-express it).
    * ``twist_lin``, ``twist_ang``: (3,) linear [m/s] and angular [rad/s] velocity expressed in
      ``child_frame_id`` (nav_msgs/Odometry convention); ``cov6_twist`` their 6x6 covariance.

    Covariances are written row-major. Refuses (ConversionError) NaN/inf anywhere, a
    non-rotation T, and covariances that are not symmetric, have a non-positive diagonal or are
    not positive semi-definite: zero or NaN covariance is never published.
    """
    what = 'pose_to_odometry'
    T = _check_transform(T_odom_base, what)
    C_pose = _check_cov6(cov6_pose, what, 'pose covariance')
    C_twist = _check_cov6(cov6_twist, what, 'twist covariance')
    v = as_float_array(twist_lin, what, 'twist_lin', (3,))
    w = as_float_array(twist_ang, what, 'twist_ang', (3,))
    if not isinstance(child_frame_id, str):
        raise ConversionError(f'{what}: child_frame_id must be a str')
    f = MessageFactory(typestore)
    pose = f.make('geometry_msgs/msg/PoseWithCovariance', pose=_matrix_to_pose_msg(f, T),
                  covariance=f.f64_fixed(C_pose))
    twist = f.make(
        'geometry_msgs/msg/TwistWithCovariance',
        twist=f.make('geometry_msgs/msg/Twist',
                     linear=f.make('geometry_msgs/msg/Vector3',
                                   x=float(v[0]), y=float(v[1]), z=float(v[2])),
                     angular=f.make('geometry_msgs/msg/Vector3',
                                    x=float(w[0]), y=float(w[1]), z=float(w[2]))),
        covariance=f.f64_fixed(C_twist))
    return f.make('nav_msgs/msg/Odometry', header=f.header(stamp_ns, frame_id),
                  child_frame_id=child_frame_id, pose=pose, twist=twist)


def odometry_to_pose(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """nav_msgs/Odometry -> ``(T 4x4, pose cov 6x6, twist (6,) = (v, w), twist cov 6x6)``.

    Frames as in :func:`pose_to_odometry`. Covariances are read row-major and not validated
    (a subscriber decides what to do with a zero covariance); the quaternion is normalised.
    """
    what = 'Odometry'
    pwc = get_field(msg, 'pose', what)
    twc = get_field(msg, 'twist', what)
    T = pose_msg_to_matrix(get_field(pwc, 'pose', what), what)
    C_pose = as_float_array(get_field(pwc, 'covariance', what), what, 'pose covariance', (6, 6),
                             finite=False)
    tw = get_field(twc, 'twist', what)
    twist = np.concatenate([_vec3(get_field(tw, 'linear', what), what),
                            _vec3(get_field(tw, 'angular', what), what)])
    C_twist = as_float_array(get_field(twc, 'covariance', what), what, 'twist covariance', (6, 6),
                              finite=False)
    return T, C_pose, twist, C_twist


def pose_stamped_to_matrix(msg: Any) -> np.ndarray:
    """geometry_msgs/PoseStamped -> 4x4 ``T_frame_body`` (pose of the body in header.frame_id)."""
    return pose_msg_to_matrix(get_field(msg, 'pose', 'PoseStamped'), 'PoseStamped')


def matrix_to_pose_stamped(T: np.ndarray, stamp_ns: int, frame_id: str,
                           typestore: Any = None) -> Any:
    """4x4 ``T_frame_body`` -> geometry_msgs/PoseStamped in ``frame_id`` (quaternion w >= 0)."""
    Ta = _check_transform(T, 'matrix_to_pose_stamped')
    f = MessageFactory(typestore)
    return f.make('geometry_msgs/msg/PoseStamped', header=f.header(stamp_ns, frame_id),
                  pose=_matrix_to_pose_msg(f, Ta))


def transform_pose_covariance(cov6: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Re-express a 6x6 pose covariance from frame A in frame B: ``J C J^T``, ``J = diag(R, R)``.

    ``cov6`` is the covariance of a perturbation ``(dt, dtheta)`` (translation, small rotation
    vector; ROS order x, y, z, rot X, rot Y, rot Z) whose components are expressed in frame A;
    ``R = R_BA`` (3x3 rotation) maps A coordinates to B coordinates. Only the axes change, so
    this is exact for a pure change of the frame the perturbation is written in; it does not
    add the lever-arm coupling of a translated reference point (that needs the full SE(3)
    adjoint). The result is symmetrised.
    """
    what = 'transform_pose_covariance'
    C = as_float_array(cov6, what, 'cov6', (6, 6))
    Ra = _check_rotation(R, what)
    J = np.zeros((6, 6))
    J[:3, :3] = Ra
    J[3:, 3:] = Ra
    out = J @ C @ J.T
    return 0.5 * (out + out.T)

"""Camera optical frame -> robot base frame for odometry output (docs/ros.md).

The VO world is the optical frame of the bootstrap camera; odom is the base frame at that
moment, so with the extrinsic T_base_cam (camera optical frame in the base frame):
    T_odom_base = T_base_cam * T_world_cam * T_base_cam^-1
Covariances follow by the Jacobian of that map, including the lever arm of a camera that is
not at the base origin. Pure numpy: the node only converts the result to messages.
"""
from __future__ import annotations

import numpy as np

from . import geometry as geo


def optical_to_body_extrinsic(xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """T_base_cam from a translation and an x y z w quaternion (parameters)."""
    q = geo.quat_normalize(geo.quat_xyzw_to_wxyz(np.asarray(q_xyzw, float)))
    return geo.make_T(geo.quat_to_matrix(q), np.asarray(xyz, float))


def camera_to_base(T_world_cam: np.ndarray, pose_cov: np.ndarray, twist_cam: np.ndarray,
                   twist_cov: np.ndarray, T_base_cam: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(T_odom_base, pose_cov (odom frame), twist_base (6,), twist_cov) for nav_msgs/Odometry.

    pose_cov: 6x6 over (position, world rotation vector) of the camera in the VO world.
    twist_cam: (v, w) in the camera frame; the result is in the base frame (child frame).
    """
    R_bc = T_base_cam[:3, :3]
    T_cam_base = geo.invert_T(T_base_cam)
    T_odom_base = T_base_cam @ T_world_cam @ T_cam_base
    # base origin in the camera frame
    c = T_cam_base[:3, 3]
    # p_odom_base = R_bc (p_wc + R_wc c) + t_bc; a world rotation dtheta moves R_wc c by
    # dtheta x (R_wc c); rotations map through R_bc
    lever = T_world_cam[:3, :3] @ c
    J = np.zeros((6, 6))
    J[:3, :3] = R_bc
    J[:3, 3:] = -R_bc @ geo.skew(lever)
    J[3:, 3:] = R_bc
    cov = J @ pose_cov @ J.T
    # twist: v_base = R_bc (v_cam + w_cam x c), w_base = R_bc w_cam
    v_cam, w_cam = twist_cam[:3], twist_cam[3:]
    Jt = np.zeros((6, 6))
    Jt[:3, :3] = R_bc
    Jt[:3, 3:] = -R_bc @ geo.skew(c)
    Jt[3:, 3:] = R_bc
    twist = np.concatenate((R_bc @ (v_cam + np.cross(w_cam, c)), R_bc @ w_cam))
    tcov = Jt @ twist_cov @ Jt.T
    return T_odom_base, 0.5 * (cov + cov.T), twist, 0.5 * (tcov + tcov.T)


def points_to_odom(X_world: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Map points from the VO world (bootstrap optical frame) to odom: X_odom = T_bc X_w."""
    return geo.transform_points(T_base_cam, X_world)

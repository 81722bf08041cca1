"""The observation model of every EKF update: reprojection of points into the camera.

One vectorised model serves the fixed map points of the hybrid filter and the anchored
inverse-depth points of the in-filter refinement (docs/method.md §4 and §8):

    X^C ~ R(q)^T (rho (a - r) + m)

with, per measurement, the anchor `a`, the ray `m` and the inverse depth `rho`:
- a fixed map point X^W: a = X^W, m = 0, rho = 1 (not a state);
- an in-filter point: a = c (camera centre at its first observation), m = unit world
  bearing of that observation, rho = its inverse-depth state (column `col` of x).
The projection is invariant to the scale of X^C, so the form is valid at rho = 0.

Names: `x` is a state vector whose first 13 entries are the camera (ekf.POS, QUAT, ...);
`intrinsics` is the 3x3 pinhole matrix (never called K here: K is the Kalman gain).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry as geo
from .state import POS, QUAT

#: points closer than this along the optical axis count as behind the camera [map units]
MIN_DEPTH = 1e-9


def rotated_by_quat_conj_jacobian(q_wxyz: np.ndarray, v: np.ndarray
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """R(q)^T v and its derivative w.r.t. q, for (N,3) vectors v.

    R(q)^T v = R(q*) v = (w^2 - u.u) v + 2 (u.v) u - 2 w (u x v) with q = (w, u), the
    quadratic form of [0, X] = q* [0, v] q. It is linear in v, and so is each of its
    four partial derivatives w.r.t. q:

        d/dw   = 2 w I - 2 [u]x
        d/du_k = -2 u_k I + 2 u e_k^T + 2 e_k u^T - 2 w [e_k]x

    so the rotated vectors and all Jacobians are one (N,3) x (3,15) product.
    Returns (N,3) rotated vectors and (N,3,4) Jacobians.
    """
    w, x, y, z = (float(c) for c in q_wxyz)
    mats = np.array((
        ((w*w + x*x - y*y - z*z, 2*(x*y + w*z), 2*(x*z - w*y)),          # R(q)^T
         (2*(x*y - w*z), w*w - x*x + y*y - z*z, 2*(y*z + w*x)),
         (2*(x*z + w*y), 2*(y*z - w*x), w*w - x*x - y*y + z*z)),
        ((2*w, 2*z, -2*y), (-2*z, 2*w, 2*x), (2*y, -2*x, 2*w)),         # d/dw
        ((2*x, 2*y, 2*z), (2*y, -2*x, 2*w), (2*z, -2*w, -2*x)),         # d/dx
        ((-2*y, 2*x, -2*w), (2*x, 2*y, 2*z), (2*w, 2*z, -2*y)),         # d/dy
        ((-2*z, 2*w, 2*x), (-2*w, -2*z, 2*y), (2*x, 2*y, 2*z))))        # d/dz
    # (N,3) @ (3, 5*3): column block j is mats[j] v
    prod = np.asarray(v, float) @ mats.transpose(2, 0, 1).reshape(3, 15)
    prod = prod.reshape(-1, 5, 3)
    return prod[:, 0], prod[:, 1:].transpose(0, 2, 1)


def pinhole_project(X_cam: np.ndarray, intrinsics: np.ndarray, with_jacobian: bool = True,
                    min_depth: float = MIN_DEPTH):
    """Ideal pixels (n,2) of camera-frame points, in-front mask (n,) and, optionally, the
    pinhole Jacobian d(u,v)/dX^C (n,2,3): u = fx X/Z + cx, v = fy Y/Z + cy."""
    Z = X_cam[:, 2]
    in_front = Z > min_depth
    inv_z = 1.0 / np.where(in_front, Z, 1.0)
    fx, fy = intrinsics[0, 0], intrinsics[1, 1]
    cx, cy = intrinsics[0, 2], intrinsics[1, 2]
    px = np.column_stack((fx * X_cam[:, 0] * inv_z + cx, fy * X_cam[:, 1] * inv_z + cy))
    if not with_jacobian:
        return px, in_front, None
    J_pi = np.zeros((len(X_cam), 2, 3))
    J_pi[:, 0, 0] = fx * inv_z
    J_pi[:, 0, 2] = -fx * X_cam[:, 0] * inv_z ** 2
    J_pi[:, 1, 1] = fy * inv_z
    J_pi[:, 1, 2] = -fy * X_cam[:, 1] * inv_z ** 2
    return px, in_front, J_pi


@dataclass
class ReprojectionModel:
    """Stacked reprojection model of n measurements for one update.

    anchor (n,3): X^W for map points, c for filter points; ray (n,3): 0 / unit bearing m;
    col (n,): -1 for map points, the state column of rho for filter points.
    whiten (n,2,2) or None: W_i applied to each predicted pixel and its Jacobian rows, so
    that a measurement given as W_i z_i has the nominal isotropic noise although its own
    noise R_i is not (W_i = sigma L_i^-1, L_i L_i^T = R_i: `whitening`). W is a constant
    linear map, so the innovation is W_i (z_i - h_i(x)) (docs/method.md §15.8)."""

    intrinsics: np.ndarray
    anchor: np.ndarray
    ray: np.ndarray
    col: np.ndarray
    whiten: np.ndarray | None = None

    @classmethod
    def of_map_points(cls, intrinsics: np.ndarray, X_world: np.ndarray
                      ) -> 'ReprojectionModel':
        """Fixed map points only: the camera-only (hybrid) filter's model."""
        X = np.asarray(X_world, dtype=float).reshape(-1, 3)
        return cls(np.asarray(intrinsics, float), X, np.zeros_like(X),
                   np.full(len(X), -1, np.int64))

    def __len__(self) -> int:
        return len(self.anchor)

    def subset(self, rows: np.ndarray) -> 'ReprojectionModel':
        return ReprojectionModel(self.intrinsics, self.anchor[rows], self.ray[rows],
                                 self.col[rows],
                                 None if self.whiten is None else self.whiten[rows])

    def rho(self, x: np.ndarray) -> np.ndarray:
        """(n,) inverse depths (1 for map points) from a state x (D,)."""
        out = np.ones(len(self.col))
        f = self.col >= 0
        out[f] = x[self.col[f]]
        return out

    def observe(self, x: np.ndarray, with_jacobian: bool = True):
        """Ideal pixels (n,2), in-front mask (n,), H (2n, D) with rows (u0, v0, u1, ...).

        Jacobians (docs/method.md §4): dX^C/dr = -rho R^T, dX^C/dq from the quadratic
        form, dX^C/drho = R^T (a - r) (filter points only)."""
        rho = self.rho(x)
        d = self.anchor - x[POS]
        v = rho[:, None] * d + self.ray
        X_cam, dXc_dq = rotated_by_quat_conj_jacobian(x[QUAT], v)
        px, in_front, J_pi = pinhole_project(X_cam, self.intrinsics, with_jacobian)
        if self.whiten is not None:
            px = np.einsum('nij,nj->ni', self.whiten, px)
            if with_jacobian:
                J_pi = self.whiten @ J_pi
        if not with_jacobian:
            return px, in_front, None
        n = len(v)
        # the quadratic form scales with |q|^2, so does its derivative w.r.t. r
        R_cw = geo.quat_to_matrix(x[QUAT]).T * np.dot(x[QUAT], x[QUAT])
        J_R = J_pi @ R_cw                                        # (n,2,3)
        H = np.zeros((n, 2, len(x)))
        H[:, :, POS] = -J_R * rho[:, None, None]
        H[:, :, QUAT] = J_pi @ dXc_dq
        f = np.flatnonzero(self.col >= 0)
        if len(f):
            H[f, :, self.col[f]] = np.einsum('nij,nj->ni', J_R[f], d[f])
        return px, in_front, H.reshape(2 * n, len(x))

    def project_states(self, states: np.ndarray) -> np.ndarray:
        """Ideal pixels (h,n,2) of all measurements under h states (h,D); NaN behind the
        camera (the 1-point RANSAC hypotheses, robust_update.py)."""
        h = len(states)
        rho = np.ones((h, len(self.col)))
        f = self.col >= 0
        rho[:, f] = states[:, self.col[f]]
        R_wc = geo.quat_to_matrix_batch(states[:, QUAT])                   # (h,3,3)
        v = rho[:, :, None] * (self.anchor[None] - states[:, None, POS]) + self.ray[None]
        X_cam = np.einsum('hji,hnj->hni', R_wc, v)
        Z = X_cam[..., 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            inv_z = np.where(Z > MIN_DEPTH, 1.0 / Z, np.nan)
        k = self.intrinsics
        u = k[0, 0] * X_cam[..., 0] * inv_z + k[0, 2]
        w = k[1, 1] * X_cam[..., 1] * inv_z + k[1, 2]
        px = np.stack((u, w), axis=-1)
        if self.whiten is not None:
            px = np.einsum('nij,hnj->hni', self.whiten, px)
        return px


def world_point_jacobian(X_world: np.ndarray, T_world_cam: np.ndarray,
                         intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d ideal pixel / d X^W (n,2,3) of points X_world (n,3) seen from T_world_cam, and
    the in-front mask (n,)."""
    R_wc = T_world_cam[:3, :3]
    X_cam = (np.asarray(X_world, float).reshape(-1, 3) - T_world_cam[:3, 3]) @ R_wc
    _, front, J_pi = pinhole_project(X_cam, intrinsics)
    return J_pi @ R_wc.T, front


def projected_variance_px2(X_world: np.ndarray, cov_world: np.ndarray,
                           T_world_cam: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Pixel variance (n,) that a point's position covariance (n,3,3) adds to its
    reprojection in the camera at T_world_cam: the mean of the two eigen-directions,
    trace(J Sigma J^T) / 2 with J = d pixel / d X^W (docs/method.md §12.3). Points
    behind the camera get 0 (they are not measured)."""
    J, front = world_point_jacobian(X_world, T_world_cam, intrinsics)
    var = np.einsum('nij,njk,nik->n', J, cov_world, J) / 2.0
    return np.where(front, np.maximum(var, 0.0), 0.0)


def whitening(cov_px2: np.ndarray, sigma_px: float) -> np.ndarray:
    """W_i = sigma L_i^-1 (n,2,2) with L_i L_i^T = cov_px2[i]: W_i cov_i W_i^T = sigma^2 I,
    what ReprojectionModel.whiten applies (measurements with a 2x2 noise each become
    measurements with the nominal one)."""
    return sigma_px * np.linalg.inv(np.linalg.cholesky(cov_px2))

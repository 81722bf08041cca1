"""In-filter map refinement: a sliding set of inverse-depth points in the EKF state.

docs/method.md §8 (Li, Wang, Yang, Sun 2016, "recursive depth" + sliding point set),
with the inverse-depth parametrisation of Civera, Davison & Montiel (IEEE T-RO 2008).
Enabled by `map_refinement: filter`; the default hybrid filter (docs/method.md §1) keeps
only the 13 camera states.

Parametrisation (the choice, and why)
-------------------------------------
Anchored inverse depth with a FIXED anchor, one state per point:
    X^W = c + m / rho,   c: camera centre at the first observation (anchor),
                         m: unit world bearing of that first observation (the ray),
                         rho: inverse depth along the ray [1/m] -- the only state.
Civera's full form puts (c, azimuth, elevation, rho) in the state, 6 per point. We keep
the anchor and the ray out of the state, as the hybrid method keeps its triangulated map
out of the state:
- cost: the state is 13 + N (53 for N = 40) instead of 13 + 6N (253); the joint update
  and the per-hypothesis RANSAC work are cubic/quadratic in it, so 1 parameter per point
  is what keeps the per-frame cost close to the camera-only filter's;
- what the depth filter must learn is the depth: the ray direction is known to the pixel
  noise of one observation (1 px / f, ~0.1 deg) and the anchor to the EKF pose accuracy,
  both small next to the depth uncertainty of a new point (near to infinity). Ignoring
  them is the same approximation the hybrid map makes for every triangulated point (the
  EKF poses used to triangulate are taken as exact);
- it is Li et al.'s "recursive depth": N depths in the state, ordered by lifetime.
Observation in homogeneous form, valid even at rho = 0 (point at infinity):
    X^C ~ R^T (rho (c - r) + m)      (X^C scaled by rho; the projection is invariant)
A map point is the special case rho = 1 (fixed), c = X^W, m = 0, so map points and filter
points share one vectorised observation model with Jacobians
    dX^C/dr = -rho R^T,   dX^C/dq (quadratic form, ekf.rotated_by_quat_conj_jacobian),
    dX^C/drho = R^T (c - r)   (filter points only).
Points in the state are measurements for the camera too (the joint update moves both).

Initialisation (Civera 2008 sec. III-C): rho0 = 1 / d_guess (median depth of the visible
map), sigma_rho = `filter_init_rho_rel_sigma` * rho0; with the default 1.0 the 95% region
[rho0 - 1.96 sigma, rho0 + 1.96 sigma] runs from a third of d_guess to beyond infinity
(rho <= 0). No cross-covariance with the camera at birth (the anchor is fixed).

Life cycle (Li et al. 2016): at most N = `filter_max_points` points, kept ordered by birth
(observation lifetime). Each frame the m = `filter_retire_count` oldest are examined; those
observed >= `filter_min_observations` times whose relative depth std sigma_rho / rho is
below `filter_max_rel_depth_std` are FROZEN: X^W = c + m / rho goes to the fixed map and
the point is marginalised out of the state (its row and column deleted: the Gaussian
marginal of the rest). N/m >= 10 (validated in the config) so every point gets at least
~10 frames before its turn. Points whose track ends are frozen if converged, else dropped;
points still unconverged after `filter_max_observations` are dropped (far points with too
little parallax: they go back to ordinary triangulation). Freed slots take new tracks.
So the state never exceeds 13 + N and the per-frame cost stays bounded by N.

The camera part of the joint state lives in the CameraEKF (x, P) as always; this object
holds the point part (rho (n,), cross-covariance P_cp (13,n), P_pp (n,n)) and assembles
the joint state only for the update. Prediction: points are static, so
    P_cp <- lambda F P_cp,   P_pp <- lambda P_pp   (lambda = fading_memory; F at the
    prior state, as CameraEKF.predict).

The update is the one robust update (robust_update.py, ekf.update) on the joint state
(x, P) that `joint` assembles, with the model from `measurements`: map points and filter
points share one observation model (observation.py), so the camera-only filter is this
filter with zero points; the estimator (estimators.JointEstimator) writes the result back
with `set_joint` and `record_verdicts`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..config import VoConfig
from .ekf import CameraEKF, motion_jacobians
from .observation import ReprojectionModel
from .state import STATE_DIM

logger = logging.getLogger(__name__)


# ---------------------------------------------------------------------- the point set
@dataclass
class Retired:
    """Points that left the state in one `retire` call."""

    frozen_ids: np.ndarray       #: (k,) go to the fixed map
    frozen_X: np.ndarray         #: (k,3)
    frozen_n_obs: np.ndarray     #: (k,)
    dropped_ids: np.ndarray      #: (j,) left without a map point


class PointFilter:
    """The in-filter point set: N inverse depths and their covariance with the camera.

    Attributes (n points, ordered by birth = observation lifetime):
        ids (n,) track ids; anchor (n,3) c; ray (n,3) m; rho (n,); birth (n,) frame
        index; n_obs (n,) inlier observations; misses (n,) consecutive outlier verdicts;
        P_cp (13,n) camera-point cross-covariance; P_pp (n,n)."""

    def __init__(self, cfg: VoConfig, intrinsics: np.ndarray) -> None:
        self.intrinsics = np.asarray(intrinsics, float)
        f_mean = float(0.5 * (self.intrinsics[0, 0] + self.intrinsics[1, 1]))
        #: angular std of the fixed anchor ray (one observation's pixel noise) [rad]
        self.ray_sigma_rad = float(cfg.filter_ray_sigma_px) / f_mean
        self.max_points = int(cfg.filter_max_points)
        self.retire_count = int(cfg.filter_retire_count)
        self.max_rel_depth_std = float(cfg.filter_max_rel_depth_std)
        self.min_observations = int(cfg.filter_min_observations)
        self.max_observations = int(cfg.filter_max_observations)
        self.init_rho_rel_sigma = float(cfg.filter_init_rho_rel_sigma)
        self.cull_after_misses = int(cfg.cull_after_misses)
        self.clear()

    def clear(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.anchor = np.zeros((0, 3))
        self.ray = np.zeros((0, 3))
        self.rho = np.zeros(0)
        self.birth = np.zeros(0, np.int64)
        self.n_obs = np.zeros(0, np.int64)
        self.misses = np.zeros(0, np.int64)
        self.P_cp = np.zeros((STATE_DIM, 0))
        self.P_pp = np.zeros((0, 0))
        self.n_frozen = 0
        self.n_dropped = 0

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def state_dim(self) -> int:
        return STATE_DIM + len(self.ids)

    @property
    def free_slots(self) -> int:
        return self.max_points - len(self.ids)

    def rows_of(self, track_ids: np.ndarray) -> np.ndarray:
        """Row in the point set of each track id (n,), -1 when not in the filter."""
        pos = {int(t): k for k, t in enumerate(self.ids)}
        return np.array([pos.get(int(t), -1) for t in track_ids], np.int64)

    def depth_rel_std(self, cam_centre: np.ndarray | None = None) -> np.ndarray:
        """Relative depth std sigma_d / d (inf when rho <= 0).

        sigma_rho / rho from the filter, plus, when the current camera centre is given,
        the part the filter cannot see: the anchor ray is fixed, so its angular error
        (one observation's pixel noise, ray_sigma_rad) shifts the depth seen from a
        viewpoint at parallax theta by about d * sigma_ray / sin(theta), which no number
        of later observations averages out (the triangulation floor of the first view)."""
        s = np.sqrt(np.maximum(np.diag(self.P_pp), 0.0))
        with np.errstate(divide='ignore'):
            rel = np.where(self.rho > 0, s / np.maximum(self.rho, 1e-300), np.inf)
        if cam_centre is None or len(self.ids) == 0:
            return rel
        v = self.X_world() - np.asarray(cam_centre, float)
        with np.errstate(invalid='ignore', divide='ignore'):
            sin_par = np.linalg.norm(np.cross(v, self.ray), axis=1) / np.linalg.norm(v, axis=1)
            ray_rel = self.ray_sigma_rad / sin_par
        total = np.sqrt(rel ** 2 + ray_rel ** 2)
        return np.where(np.isfinite(total), total, np.inf)

    def X_world(self) -> np.ndarray:
        """(n,3) current point estimates (NaN for rho <= 0)."""
        with np.errstate(divide='ignore'):
            inv = np.where(self.rho > 0, 1.0 / np.maximum(self.rho, 1e-300), np.nan)
        return self.anchor + self.ray * inv[:, None]

    # ------------------------------------------------------------------ prediction
    def predict(self, x_cam_prior: np.ndarray, dt: float, fading_memory: float
                ) -> None:
        """Propagate the cross-covariance; call BEFORE CameraEKF.predict (same F)."""
        if len(self.ids) == 0:
            return
        F, _ = motion_jacobians(x_cam_prior, dt)
        self.P_cp = fading_memory * (F @ self.P_cp)
        self.P_pp = fading_memory * self.P_pp

    # ------------------------------------------------------------------ joint state
    def joint(self, ekf: CameraEKF) -> tuple[np.ndarray, np.ndarray]:
        n = len(self.ids)
        x = np.concatenate((ekf.x, self.rho))
        P = np.empty((STATE_DIM + n, STATE_DIM + n))
        P[:STATE_DIM, :STATE_DIM] = ekf.P
        P[:STATE_DIM, STATE_DIM:] = self.P_cp
        P[STATE_DIM:, :STATE_DIM] = self.P_cp.T
        P[STATE_DIM:, STATE_DIM:] = self.P_pp
        return x, P

    def set_joint(self, ekf: CameraEKF, x: np.ndarray, P: np.ndarray) -> None:
        ekf.x = x[:STATE_DIM].copy()
        ekf.P = P[:STATE_DIM, :STATE_DIM].copy()
        self.rho = x[STATE_DIM:].copy()
        self.P_cp = P[:STATE_DIM, STATE_DIM:].copy()
        self.P_pp = P[STATE_DIM:, STATE_DIM:].copy()

    def measurements(self, X_map: np.ndarray, rows: np.ndarray) -> ReprojectionModel:
        """Model of the map points X_map (a,3) followed by the filter points `rows` (b,)
        whose rho sit at joint-state columns 13 + row."""
        rows = np.asarray(rows, np.int64)
        X_map = np.asarray(X_map, float).reshape(-1, 3)
        return ReprojectionModel(
            self.intrinsics,
            np.concatenate((X_map, self.anchor[rows])),
            np.concatenate((np.zeros((len(X_map), 3)), self.ray[rows])),
            np.concatenate((np.full(len(X_map), -1, np.int64), STATE_DIM + rows)))

    def record_verdicts(self, rows: np.ndarray, inliers: np.ndarray) -> None:
        """Count the update's inlier / outlier verdicts on the filter points `rows`."""
        rows = np.asarray(rows, np.int64)
        self.n_obs[rows[inliers]] += 1
        self.misses[rows[inliers]] = 0
        self.misses[rows[~inliers]] += 1

    # ------------------------------------------------------------------ life cycle
    def add(self, track_ids: np.ndarray, px_ideal: np.ndarray, T_world_cam: np.ndarray,
            depth_guess: float, frame_index: int) -> int:
        """New points (at most the free slots) anchored at the current camera; returns
        how many entered. Prior rho ~ N(1/d, (init_rho_rel_sigma / d)^2)."""
        k = min(self.free_slots, len(track_ids))
        if k <= 0 or not depth_guess > 0:
            return 0
        track_ids = np.asarray(track_ids, np.int64)[:k]
        px = np.asarray(px_ideal, float).reshape(-1, 2)[:k]
        # bearing in the camera frame: K^-1 [u v 1]^T, then rotated into the world
        rays_c = np.column_stack((px, np.ones(k))) @ np.linalg.inv(self.intrinsics).T
        rays_w = rays_c @ T_world_cam[:3, :3].T
        rays_w /= np.linalg.norm(rays_w, axis=1, keepdims=True)
        rho0 = 1.0 / depth_guess
        n = len(self.ids)
        self.ids = np.concatenate((self.ids, track_ids))
        self.anchor = np.concatenate((self.anchor, np.repeat(T_world_cam[None, :3, 3], k, 0)))
        self.ray = np.concatenate((self.ray, rays_w))
        self.rho = np.concatenate((self.rho, np.full(k, rho0)))
        self.birth = np.concatenate((self.birth, np.full(k, frame_index, np.int64)))
        self.n_obs = np.concatenate((self.n_obs, np.zeros(k, np.int64)))
        self.misses = np.concatenate((self.misses, np.zeros(k, np.int64)))
        self.P_cp = np.concatenate((self.P_cp, np.zeros((STATE_DIM, k))), axis=1)
        P_pp = np.zeros((n + k, n + k))
        P_pp[:n, :n] = self.P_pp
        P_pp[n:, n:] = np.eye(k) * (self.init_rho_rel_sigma * rho0) ** 2
        self.P_pp = P_pp
        return k

    def remove(self, rows: np.ndarray) -> None:
        """Marginalise points out of the state: delete their rows and columns."""
        rows = np.asarray(rows, np.int64)
        if len(rows) == 0:
            return
        keep = np.ones(len(self.ids), bool)
        keep[rows] = False
        for name in ('ids', 'anchor', 'ray', 'rho', 'birth', 'n_obs', 'misses'):
            setattr(self, name, getattr(self, name)[keep])
        self.P_cp = self.P_cp[:, keep]
        self.P_pp = self.P_pp[np.ix_(keep, keep)]

    def retire(self, alive_ids: np.ndarray, cam_centre: np.ndarray | None = None
               ) -> Retired:
        """End-of-frame bookkeeping: freeze converged points (the m oldest, and any whose
        track ended), drop dead / repeatedly outlying / never-converging points.
        `cam_centre` (the current camera centre) adds the anchor-ray term to the
        accuracy test (depth_rel_std)."""
        converged = (self.n_obs >= self.min_observations) & \
            (self.depth_rel_std(cam_centre) < self.max_rel_depth_std)
        alive = np.isin(self.ids, np.asarray(alive_ids, np.int64))
        order = np.lexsort((self.ids, self.birth))          # oldest first
        oldest = np.zeros(len(self.ids), bool)
        oldest[order[:self.retire_count]] = True
        freeze = converged & (oldest | ~alive) & (self.misses == 0)
        drop = ~freeze & (~alive | (self.misses >= self.cull_after_misses) |
                          (self.n_obs >= self.max_observations))
        X = self.X_world()
        out = Retired(self.ids[freeze].copy(), X[freeze].copy(), self.n_obs[freeze].copy(),
                      self.ids[drop].copy())
        self.n_frozen += int(freeze.sum())
        self.n_dropped += int(drop.sum())
        self.remove(np.flatnonzero(freeze | drop))
        return out

"""In-filter map refinement: a sliding set of inverse-depth points in the EKF state.

METHOD.md section 3 (Li, Wang, Yang, Sun 2016, "recursive depth" + sliding point set),
with the inverse-depth parametrisation of Civera, Davison & Montiel (IEEE T-RO 2008).
Enabled by `map_refinement: filter`; the default hybrid filter (METHOD.md sec. 1) keeps
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
    P_cp <- S F P_cp,   P_pp <- S P_pp   (F at the prior state, as CameraEKF.predict).

The robust update is 1-point RANSAC (Civera et al. JFR 2010, ransac.py) generalised to
the joint state: hypotheses are single-measurement partial updates of the joint state,
projections of all measurements under each hypothesis (the hypothesis' own rho for the
filter points), support by pixel distance, then the low-innovation update and the
high-innovation rescue with the updated joint covariance.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from . import geometry as geo
from .ekf import (POS, POSE, QUAT, STATE_DIM, CameraEKF, FilterError, UpdateStats,
                  chi2_2dof_quantile, motion_jacobians, pinhole_project,
                  rotated_by_quat_conj_jacobian)

logger = logging.getLogger(__name__)


# ---------------------------------------------------------------------- observation model
@dataclass
class Measurements:
    """Stacked observation model of map points and filter points for one update.

    anchor (n,3): X^W for map points, c for filter points; ray (n,3): 0 / unit bearing m;
    col (n,): -1 for map points, the joint-state column of rho for filter points."""

    K: np.ndarray
    anchor: np.ndarray
    ray: np.ndarray
    col: np.ndarray

    def __len__(self) -> int:
        return len(self.anchor)

    def subset(self, rows: np.ndarray) -> 'Measurements':
        return Measurements(self.K, self.anchor[rows], self.ray[rows], self.col[rows])

    def rho(self, x: np.ndarray) -> np.ndarray:
        """(n,) inverse depths (1 for map points) from a joint state x (D,)."""
        out = np.ones(len(self.col))
        f = self.col >= 0
        out[f] = x[self.col[f]]
        return out

    def observe(self, x: np.ndarray, with_jacobian: bool = True):
        """Ideal pixels (n,2), in-front mask (n,), H (2n, D) with rows (u0, v0, u1, ...)."""
        rho = self.rho(x)
        d = self.anchor - x[POS]
        y = rho[:, None] * d + self.ray
        X_cam, dXc_dq = rotated_by_quat_conj_jacobian(x[QUAT], y)
        px, in_front, J_pi = pinhole_project(X_cam, self.K, with_jacobian, min_depth=1e-9)
        if not with_jacobian:
            return px, in_front, None
        n = len(y)
        # the quadratic form scales with |q|^2 (as CameraEKF.observe)
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
        """Ideal pixels (h,n,2) of all measurements under h joint states (h,D); NaN when
        behind the camera (1-point RANSAC hypotheses)."""
        h = len(states)
        rho = np.ones((h, len(self.col)))
        f = self.col >= 0
        rho[:, f] = states[:, self.col[f]]
        R_wc = np.stack([geo.quat_to_matrix(q) for q in states[:, QUAT]])   # (h,3,3)
        y = rho[:, :, None] * (self.anchor[None] - states[:, None, POS]) + self.ray[None]
        X_cam = np.einsum('hji,hnj->hni', R_wc, y)
        Z = X_cam[..., 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            inv_z = np.where(Z > 1e-9, 1.0 / Z, np.nan)
        u = self.K[0, 0] * X_cam[..., 0] * inv_z + self.K[0, 2]
        v = self.K[1, 1] * X_cam[..., 1] * inv_z + self.K[1, 2]
        return np.stack((u, v), axis=-1)


# ---------------------------------------------------------------------- joint EKF steps
def _normalise_quaternion(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q <- q/|q|, P <- J P J^T (the normalisation Jacobian on the quaternion block)."""
    q = x[QUAT]
    n = np.linalg.norm(q)
    Jq = (np.eye(4) - np.outer(q, q) / (n * n)) / n
    x = x.copy()
    x[QUAT] = q / n
    P = P.copy()
    P[QUAT, :] = Jq @ P[QUAT, :]
    P[:, QUAT] = P[:, QUAT] @ Jq.T
    return x, 0.5 * (P + P.T)


def _nis(P: np.ndarray, HtRH: np.ndarray, Hty: np.ndarray, y: np.ndarray,
         r_inv: np.ndarray) -> float:
    """y^T S^-1 y by Woodbury, S^-1 = R^-1 - R^-1 H (I + P H^T R^-1 H)^-1 P H^T R^-1,
    from HtRH = H^T R^-1 H and Hty = H^T R^-1 y (D x D work only)."""
    return float(y @ (y * r_inv)
                 - Hty @ np.linalg.solve(np.eye(len(P)) + P @ HtRH, P @ Hty))


def _information(H: np.ndarray, col: np.ndarray, r_inv: np.ndarray, y: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """H^T R^-1 H (D,D) and H^T R^-1 y (D,) from the block structure of H: a map point's
    rows touch only the pose (7 columns), a filter point's rows the pose and its own rho.
    O(n) small products instead of a 2n x D GEMM (which multithreaded BLAS runs badly on
    a loaded machine)."""
    n, D = len(col), H.shape[1]
    Hn = H.reshape(n, 2, D)
    Hp = Hn[:, :, POSE]                                            # (n,2,7)
    w = r_inv.reshape(n, 2)
    wy = w * y.reshape(n, 2)
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


def joint_update(x: np.ndarray, P: np.ndarray, z_px: np.ndarray, meas: Measurements,
                 sigma: np.ndarray, iterations: int = 1
                 ) -> tuple[np.ndarray, np.ndarray, UpdateStats]:
    """EKF / iterated EKF update of the joint state with n measurements.

    Information form with a diagonal R: with C = P H^T R^-1 H (D x D) and
    M = (I + C)^-1, the Woodbury gain K = B - C (I + C)^-1 B (B = P H^T R^-1) equals M B,
    so  x+ = x + M P H^T R^-1 y,  I - K H = M,  K R K^T = M C P M^T,  and the Joseph form
    P+ = (I - KH) P (I - KH)^T + K R K^T = M (P + C P) M^T: no D x 2n system is solved
    (CameraEKF.update, METHOD.md sec. 1 form (c), for D = 13 + n_points)."""
    n = len(z_px)
    z = np.asarray(z_px, float).reshape(-1)
    r_inv = np.repeat(1.0 / (sigma * sigma), 2)
    D = len(x)
    I = np.eye(D)
    px0, _, H0 = meas.observe(x)
    y0 = z - px0.reshape(-1)
    x_i, H, C, M = x, H0, None, None
    stats = UpdateStats(n_used=n, rms_innovation_px=float(np.sqrt(np.mean(y0 ** 2) * 2)))
    for it in range(max(1, iterations)):
        if it == 0:
            y_lin = y0
        else:
            px_i, _, H = meas.observe(x_i)
            y_lin = z - px_i.reshape(-1) - H @ (x - x_i)
        HtRH, Hty = _information(H, meas.col, r_inv, y_lin)
        if it == 0:
            stats.nis = _nis(P, HtRH, Hty, y0, r_inv)
        C = P @ HtRH
        M = np.linalg.inv(I + C)
        x_i = x + M @ (P @ Hty)
        x_i[QUAT] /= np.linalg.norm(x_i[QUAT])
    P_new = M @ (P + C @ P) @ M.T
    x_new, P_new = _normalise_quaternion(x_i, P_new)
    if not np.all(np.isfinite(x_new)) or not np.all(np.isfinite(P_new)):
        raise FilterError('joint state or covariance became non-finite in the update')
    px1, _, _ = meas.observe(x_new, with_jacobian=False)
    stats.rms_residual_px = float(np.sqrt(np.mean((z - px1.reshape(-1)) ** 2) * 2))
    return x_new, P_new, stats


@dataclass
class JointRobustResult:
    """Outcome of `robust_joint_update`; arrays refer to the measurement rows."""

    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    n_low_innovation: int = 0
    n_rescued: int = 0
    n_hypotheses: int = 0
    stats: UpdateStats = field(default_factory=UpdateStats)


def _innovation_covariances(P: np.ndarray, H: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    Hn = H.reshape(-1, 2, P.shape[0])
    S = Hn @ P @ Hn.transpose(0, 2, 1)
    S[:, 0, 0] += sigma ** 2
    S[:, 1, 1] += sigma ** 2
    return S


def robust_joint_update(x: np.ndarray, P: np.ndarray, z_px: np.ndarray,
                        meas: Measurements, sigma_px: float | np.ndarray,
                        rng: np.random.Generator, one_point: bool = True,
                        inlier_px: float = 2.0, probability: float = 0.99,
                        max_hypotheses: int = 50, gate_probability: float = 0.99,
                        iterations: int = 1
                        ) -> tuple[np.ndarray, np.ndarray, JointRobustResult]:
    """1-point RANSAC EKF update (ransac.robust_update) on the joint state.

    Returns the updated (x, P) and which measurement rows were inliers."""
    n = len(z_px)
    res = JointRobustResult(inliers=np.zeros(n, bool))
    if n == 0:
        return x, P, res
    sigma = np.broadcast_to(np.asarray(sigma_px, float), (n,)).copy()
    px_pred, in_front, H = meas.observe(x)
    y = z_px - px_pred
    valid = in_front & np.all(np.isfinite(y), axis=1)
    gate = chi2_2dof_quantile(gate_probability)
    low = np.zeros(n, bool)
    if one_point and np.count_nonzero(valid) >= 2:
        candidates = np.flatnonzero(valid)
        Hn = H.reshape(n, 2, len(x))
        n_hyp, best, tried = max_hypotheses, -1, 0
        while tried < n_hyp:
            batch = rng.choice(candidates, size=min(n_hyp - tried, 16), replace=True)
            # partial update with one measurement each, covariance untouched (Civera 2010)
            Hb = Hn[batch]
            PHt = P @ Hb.transpose(0, 2, 1)                              # (h,D,2)
            S = Hb @ PHt
            S[:, 0, 0] += sigma[batch] ** 2
            S[:, 1, 1] += sigma[batch] ** 2
            states = x[None] + (PHt @ np.linalg.solve(S, y[batch][:, :, None]))[:, :, 0]
            states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1, keepdims=True)
            err = np.linalg.norm(meas.project_states(states) - z_px[None], axis=2)
            support = (err < inlier_px) & valid[None]
            counts = support.sum(axis=1)
            tried += len(batch)
            b = int(np.argmax(counts))
            if counts[b] > best:
                best = int(counts[b])
                low = support[b]
                eps = best / len(candidates)
                if eps >= 1.0:
                    break
                n_hyp = min(max_hypotheses, int(np.ceil(
                    np.log(1.0 - probability) / np.log(max(1e-12, 1.0 - eps)))))
        res.n_hypotheses = tried
    else:
        S = _innovation_covariances(P, H, sigma)
        d2 = np.einsum('ni,nij,nj->n', y, np.linalg.inv(S), y)
        low = valid & (d2 < gate)
    res.n_low_innovation = int(np.count_nonzero(low))
    if res.n_low_innovation == 0:
        return x, P, res
    rows = np.flatnonzero(low)
    x, P, res.stats = joint_update(x, P, z_px[rows], meas.subset(rows), sigma[rows],
                                   iterations)
    inliers = low.copy()
    if one_point:
        rest = np.flatnonzero(valid & ~low)
        if len(rest):
            sub = meas.subset(rest)
            px_r, front_r, H_r = sub.observe(x)
            y_r = z_px[rest] - px_r
            S_r = _innovation_covariances(P, H_r, sigma[rest])
            d2 = np.einsum('ni,nij,nj->n', y_r, np.linalg.inv(S_r), y_r)
            rescued = rest[front_r & (d2 < gate)]
            if len(rescued):
                x, P, res.stats = joint_update(x, P, z_px[rescued], meas.subset(rescued),
                                               sigma[rescued], iterations)
                inliers[rescued] = True
                res.n_rescued = len(rescued)
    res.inliers = inliers
    return x, P, res


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

    def __init__(self, K: np.ndarray, max_points: int = 40, retire_count: int = 4,
                 max_rel_depth_std: float = 0.05, min_observations: int = 10,
                 max_observations: int = 100, init_rho_rel_sigma: float = 1.0,
                 cull_after_misses: int = 3, ray_sigma_px: float = 1.0) -> None:
        self.K = np.asarray(K, float)
        #: angular std of the fixed anchor ray (one observation's pixel noise) [rad]
        self.ray_sigma_rad = float(ray_sigma_px) / float(0.5 * (self.K[0, 0] + self.K[1, 1]))
        self.max_points = int(max_points)
        self.retire_count = int(retire_count)
        self.max_rel_depth_std = float(max_rel_depth_std)
        self.min_observations = int(min_observations)
        self.max_observations = int(max_observations)
        self.init_rho_rel_sigma = float(init_rho_rel_sigma)
        self.cull_after_misses = int(cull_after_misses)
        self.clear()

    @classmethod
    def from_config(cls, cfg, K: np.ndarray) -> 'PointFilter':
        return cls(K, cfg.filter_max_points, cfg.filter_retire_count,
                   cfg.filter_max_rel_depth_std, cfg.filter_min_observations,
                   cfg.filter_max_observations, cfg.filter_init_rho_rel_sigma,
                   cfg.cull_after_misses, cfg.pixel_sigma_px)

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
    def predict(self, x_cam_prior: np.ndarray, dt: float, fading_memory: float = 1.0
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

    def measurements(self, X_map: np.ndarray, rows: np.ndarray) -> Measurements:
        """Map points X_map (a,3) followed by the filter points `rows` (b,)."""
        rows = np.asarray(rows, np.int64)
        return Measurements(
            self.K,
            np.concatenate((np.asarray(X_map, float).reshape(-1, 3), self.anchor[rows])),
            np.concatenate((np.zeros((len(X_map), 3)), self.ray[rows])),
            np.concatenate((np.full(len(X_map), -1, np.int64), STATE_DIM + rows)))

    def robust_update(self, ekf: CameraEKF, z_map: np.ndarray, X_map: np.ndarray,
                      z_pts: np.ndarray, rows: np.ndarray, sigma_px: float,
                      rng: np.random.Generator, **kwargs
                      ) -> tuple[np.ndarray, np.ndarray, JointRobustResult]:
        """Joint robust update with map matches (z_map, X_map) and filter points `rows`
        observed at z_pts. Writes the result back into `ekf` and the point set; records
        the filter points' inlier verdicts. Returns (map inliers, point inliers, result)."""
        meas = self.measurements(X_map, rows)
        z = np.concatenate((np.asarray(z_map, float).reshape(-1, 2),
                            np.asarray(z_pts, float).reshape(-1, 2)))
        x, P = self.joint(ekf)
        x, P, out = robust_joint_update(x, P, z, meas, sigma_px, rng, **kwargs)
        self.set_joint(ekf, x, P)
        ekf.last_update = out.stats
        a = len(X_map)
        pt_in = out.inliers[a:]
        rows = np.asarray(rows, np.int64)
        self.n_obs[rows[pt_in]] += 1
        self.misses[rows[pt_in]] = 0
        self.misses[rows[~pt_in]] += 1
        return out.inliers[:a], pt_in, out

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
        rays_c = np.column_stack((px, np.ones(k))) @ np.linalg.inv(self.K).T
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

"""Two-view bootstrap of the map: essential matrix, relative pose, first triangulation.

Step 1 of the hybrid pipeline (docs/method.md §2.1): from two frames at the start of the
sequence, estimate the epipolar geometry, recover the relative pose and triangulate the
first map. Monocular scale is arbitrary: the translation is scaled to
`bootstrap_baseline_m` (or the `baseline` argument). `from_known_poses` is the paper's
ground-truth bootstrap (the first two true poses fix the scale; only triangulation).

Essential matrix by Nister's five-point algorithm inside RANSAC (cv2.findEssentialMat),
decomposition + cheirality vote by cv2.recoverPose (H&Z sec. 9.6.2). A pair is refused,
with a reason, when

- too few tracks are common to both frames, or their median displacement is tiny (the
  rays cannot have parallax: translational flow is about f * parallax, so a median flow
  below 0.5 f tan(bootstrap_min_parallax_deg) px cannot reach the required parallax);
- RANSAC finds no essential matrix;
- the motion is (close to) a pure rotation or the scene is too far away: the homography
  H = K R K^-1 explains the correspondences as well as E does (model selection in the
  spirit of ORB-SLAM, Mur-Artal et al., IEEE T-RO 2015, sec. IV) AND the median
  parallax is below bootstrap_min_parallax_deg. Under pure rotation E is undefined (any t
  fits), so its "pose" would be noise;
- the median parallax is below bootstrap_min_parallax_deg (depths poorly constrained);
- fewer than bootstrap_min_inliers points triangulate validly.

Pixels are IDEAL (undistorted) coordinates of the pinhole K; the caller undistorts.
Frames: `T_cur_ref` maps points of the reference camera frame into the current camera
frame, X_cur = R_cur_ref X_ref + t_cur_ref. For `try_pair` the world frame IS the
reference camera frame (X_world == X_ref).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.map_uncertainty import relative_pose_covariance
from ekf_vo.core.triangulation import TriangulationResult, triangulate_points

logger = logging.getLogger(__name__)

#: RANSAC confidence of the essential matrix and homography fits.
_RANSAC_PROB = 0.999
#: Homography/essential inlier ratio above which H "explains the motion as well as E".
#: Measured on synthetic 1 px noise scenes: pure rotation gives 0.8-1.0 (E over-fits the
#: noise there), general motion with depth variation 0.2-0.3.
H_OVER_E_RATIO = 0.7
#: Homography RANSAC threshold in multiples of the essential one, chosen so that both
#: models keep the same fraction of true inliers: the E error (point to epipolar line,
#: Sampson) is 1-D with std sigma, the H forward transfer error is 2-D and carries the
#: noise of both images (std sqrt(2) sigma per axis, Rayleigh norm). P(|N(0,1)| < 1) =
#: 0.683 = 1 - exp(-k^2 / 4) gives k = 2.13.
_H_THRESHOLD_SCALE = 2.13
#: Inlier gate of the refined epipolar model, in multiples of bootstrap_ransac_px: the
#: RANSAC threshold is tuned to pick a clean sample set, the gate keeps every point
#: compatible with the noise (3 sigma when the threshold is about one sigma).
_GATE_SCALE = 3.0
#: Huber width of the polish, in multiples of bootstrap_ransac_px (about 2 sigma).
_HUBER_SCALE = 2.0
#: Fewest correspondences findEssentialMat accepts (five-point algorithm).
_MIN_POINTS_ESSENTIAL = 5
#: Turns of the translation [rad] at which the polish starts again, on either side and
#: both axes across it (other_basin): 20 and 40 deg.
_START_TURNS = (np.radians(20.0), -np.radians(20.0), np.radians(40.0), -np.radians(40.0))
#: Gauss-Newton iterations a turned start gets before it is judged; one that is then
#: below RANSAC's cost gets the full polish (the bootstrap frame's time, on a node at 30 Hz)
_START_ITERATIONS = 3
#: A turned start's model replaces RANSAC's only if twice its cost decrease, over the
#: Sampson residuals' variance, passes chi-square 5 dof at 99.9 % (other_basin)
_BASIN_CHI2 = 20.52
#: floor of that variance [px^2] (noise-free pixels)
_MIN_SAMPSON_VAR_PX2 = 0.01
#: A model that fits within chance of the one taken is another relative pose when its
#: rotation is beyond the taken pair's covariance: chi-square 3 dof at 99.9 %
#: (EpipolarBasins.rivals); the covariance is floored at _DISTINCT_FLOOR_RAD a axis, so
#: the same basin polished a little further (0.1-0.3 deg) is never a rival
_DISTINCT_CHI2 = 16.27
_DISTINCT_FLOOR_RAD = np.radians(0.1)
#: A model of another basin is a candidate only if it triangulates at least this share
#: of the points the model it is compared with puts in front of both cameras
#: (EpipolarBasins._explains). On the rendered drone over its floor the right model put
#: every point in front (276-282 of 276-282) and the other decomposition of the plane
#: 60-93 %, fitting the pixels better by up to chi 45; noise puts a far point or two
#: behind, not a few percent
_CHEIRALITY_SHARE = 0.97


@dataclass
class BootstrapResult:
    """Outcome of a bootstrap attempt.

    Attributes:
        ok: the pair was accepted.
        reason: 'ok' or why the pair was refused.
        R_cur_ref: (3, 3) rotation reference camera -> current camera.
        t_cur_ref: (3,) translation, |t| = the baseline (map units).
        T_cur_ref: (4, 4) [R_cur_ref | t_cur_ref].
        point_ids: (M,) int64 track ids of the valid triangulated points.
        X_ref: (M, 3) those points in the reference camera frame (map units).
        X_world: (M, 3) those points in the world frame (== X_ref for `try_pair`).
        inlier_ids: (K,) int64 ids of the correspondences within the inlier gate of the
            refined epipolar geometry (superset of point_ids); for
            `from_known_poses` the common ids.
        median_parallax_deg: median ray angle over the inliers that triangulate in front
            of both cameras with a small reprojection error (before the per-point
            parallax cut).
        n_inliers: M, the number of valid triangulated points.
        n_common: tracks common to both frames.
        median_flow_px: median displacement of the common tracks.
        h_over_e: homography inliers / essential inliers (NaN when not computed).
        triangulation: the per-point result over the common tracks (or None).
    """

    ok: bool
    reason: str
    R_cur_ref: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_cur_ref: np.ndarray = field(default_factory=lambda: np.zeros(3))
    T_cur_ref: np.ndarray = field(default_factory=lambda: np.eye(4))
    point_ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    X_ref: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    X_world: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    inlier_ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    median_parallax_deg: float = 0.0
    n_inliers: int = 0
    n_common: int = 0
    median_flow_px: float = 0.0
    h_over_e: float = float('nan')
    triangulation: TriangulationResult | None = None
    #: refused as a rotation: a homography explains the tracks at little parallax
    rotation_like: bool = False
    #: (k, 3) the rotations of the other poses of a flat scene that fit the pair better
    #: (EpipolarBasins.rivals), as world (= reference camera) rotation vectors from
    #: R_cur_ref^T to theirs: what the map's covariance must hold (docs/method.md §2.1.2)
    rival_rotvecs: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))


def _se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, np.float64).reshape(3)
    return T


def _inverse_se3(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return _se3(R.T, -R.T @ T[:3, 3])


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def homogeneous(p: np.ndarray) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) homogeneous pixels."""
    return np.hstack((p, np.ones((p.shape[0], 1))))


def _fundamental(R: np.ndarray, t: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    """F = K^-T [t]x R K^-1 (H&Z eq. 9.18)."""
    return K_inv.T @ _skew(t) @ R @ K_inv


def sampson_of_fundamental(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of homogeneous pixels x1, x2 (N, 3) to one or a stack of
    fundamental matrices F (..., 3, 3) -> (..., N); see sampson_px."""
    Fx1 = x1 @ np.swapaxes(F, -1, -2)
    Ftx2 = x2 @ F
    num = np.sum(x2 * Fx1, axis=-1)
    den = np.sqrt(Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2
                  + Ftx2[..., 1] ** 2)
    return num / np.maximum(den, 1e-300)


def sampson_px(R: np.ndarray, t: np.ndarray, p_ref: np.ndarray, p_cur: np.ndarray,
               K: np.ndarray) -> np.ndarray:
    """Signed Sampson distance (pixels) of correspondences to the epipolar geometry.

    F = K^-T [t]x R K^-1 (H&Z eq. 9.18), r = x2^T F x1 / sqrt((F x1)_1^2 + (F x1)_2^2 +
    (F^T x2)_1^2 + (F^T x2)_2^2) (H&Z eq. 11.9): the first-order geometric distance of
    (x1, x2) to the nearest exact correspondence. Shapes: p_ref, p_cur (N, 2) -> (N,).
    """
    return sampson_of_fundamental(_fundamental(R, t, np.linalg.inv(K)),
                                  homogeneous(p_ref), homogeneous(p_cur))


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector t."""
    a = np.eye(3)[int(np.argmin(np.abs(t)))]
    b1 = _skew(t) @ a                 # t x a (np.cross costs 10x more on 3-vectors)
    b1 /= np.linalg.norm(b1)
    return np.column_stack((b1, _skew(t) @ b1))


#: refine_relative_pose's central-difference step (radians of rotation; the same move of
#: the unit translation on its sphere)
_DIFF_STEP = 1e-6
#: its rotation increments exp([+h e_k]x) for k = 0, 1, 2, then exp([-h e_k]x)
_DIFF_ROTATIONS = np.stack([cv2.Rodrigues(sign * _DIFF_STEP * np.eye(3)[k])[0]
                            for sign in (1.0, -1.0) for k in range(3)])


def refine_relative_pose(R: np.ndarray, t: np.ndarray, p_ref: np.ndarray,
                         p_cur: np.ndarray, K: np.ndarray, gate_px: float,
                         huber_px: float, iterations: int = 10
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton polish of (R, t) on the Sampson distance, robust (Huber, IRLS).

    RANSAC returns the model of a minimal five-point sample, accurate only to the noise of
    those five points; a least-squares polish on all inliers is the standard last step
    (H&Z sec. 11.6 / "gold standard" in spirit, with the Sampson approximation). The
    5 dof are a rotation increment R <- R exp([w]x) and a move of t on the unit sphere,
    t <- normalise(t + B a) with B a tangent basis. Only correspondences within `gate_px`
    of the current model enter each iteration; Huber weights with `huber_px` keep
    moderate outliers from pulling the model. The Jacobian is numerical (central
    differences, 5 columns, the ten perturbed models evaluated as one stack): cheap for
    a few hundred points and free of algebra slips.

    Returns the refined (R (3, 3), t (3,) unit).
    """
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(3)
    t = t / np.linalg.norm(t)
    h = _DIFF_STEP
    K_inv = np.linalg.inv(K)
    x1_all, x2_all = homogeneous(p_ref), homogeneous(p_cur)
    t_signs = np.array([1.0, 1.0, -1.0, -1.0])[:, None]
    damping = 1e-9 * np.eye(5)

    def apply(R0: np.ndarray, t0: np.ndarray, B: np.ndarray, d: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        R1 = R0 @ cv2.Rodrigues(d[:3].reshape(3, 1))[0]
        t1 = t0 + B @ d[3:]
        return R1, t1 / np.linalg.norm(t1)

    for _ in range(iterations):
        r = sampson_of_fundamental(_fundamental(R, t, K_inv), x1_all, x2_all)
        sel = np.abs(r) < gate_px
        if int(sel.sum()) < _MIN_POINTS_ESSENTIAL * 2:
            break
        x1, x2, r = x1_all[sel], x2_all[sel], r[sel]
        B = _tangent_basis(t)
        # the ten models of the central differences: R exp([+-h e_k]x), then t moved by
        # +-h along the tangent basis (+h first, then -h, in each)
        t_moved = t + h * t_signs * np.vstack((B.T, B.T))                 # (4, 3)
        t_moved /= np.linalg.norm(t_moved, axis=1, keepdims=True)
        F_rot = K_inv.T @ _skew(t) @ (R @ _DIFF_ROTATIONS) @ K_inv             # (6, 3, 3)
        F_tra = K_inv.T @ np.stack([_skew(v) for v in t_moved]) @ R @ K_inv     # (4, 3, 3)
        r_moved = sampson_of_fundamental(np.concatenate((F_rot, F_tra)), x1, x2)
        r_rot, r_tra = r_moved[:6], r_moved[6:]
        J = np.column_stack(((r_rot[:3] - r_rot[3:]).T, (r_tra[:2] - r_tra[2:]).T)) / (2 * h)
        a = np.abs(r)
        w = np.where(a <= huber_px, 1.0, huber_px / np.maximum(a, 1e-300))
        JtW = J.T * w
        try:
            delta = np.linalg.solve(JtW @ J + damping, -JtW @ r)
        except np.linalg.LinAlgError:
            break
        R, t = apply(R, t, B, delta)
        if np.linalg.norm(delta) < 1e-10:
            break
    return R, t


def robust_sampson_cost(R: np.ndarray, t: np.ndarray, p_ref: np.ndarray,
                        p_cur: np.ndarray, K: np.ndarray, gate_px: float,
                        huber_px: float) -> float:
    """Huber cost of the Sampson distances, each truncated at `gate_px` (an outlier
    costs the same under every model): the score that compares polished models."""
    a = np.minimum(np.abs(sampson_px(R, t, p_ref, p_cur, K)), gate_px)
    return float(np.sum(np.where(a <= huber_px, 0.5 * a ** 2,
                                 huber_px * a - 0.5 * huber_px ** 2)))


class EpipolarModel(NamedTuple):
    """A relative pose of a pair polished from one start (epipolar_basins)."""

    cost: float           #: robust Sampson cost (robust_sampson_cost)
    R: np.ndarray         #: (3, 3) R_cur_ref
    t: np.ndarray         #: (3,) unit t_cur_ref
    #: points it triangulates in front of both cameras, with t or -t; 0 for a model
    #: that fits too badly to be compared (epipolar_basins)
    n_front: int
    #: polished from a decomposition of the homography: it replaces RANSAC's model by
    #: the points it puts in front, never by its cost alone (EpipolarBasins.winner)
    planar: bool = False


@dataclass
class EpipolarBasins:
    """Models of a pair polished from several starts (epipolar_basins), RANSAC's first,
    and the Sampson residuals' variance [px^2] around RANSAC's model that their costs
    are compared by."""

    models: list[EpipolarModel]
    variance_px2: float

    def chi(self, cost_a: float, cost_b: float) -> float:
        """Twice the cost decrease from a to b over the residuals' variance: chi-square
        5 dof when b is a's model polished further by noise alone."""
        return 2.0 * (cost_a - cost_b) / self.variance_px2

    def _explains(self, m: EpipolarModel, than: EpipolarModel) -> bool:
        """`m` puts (nearly) as many points in front of both cameras as `than`: the
        other decomposition of a flat scene may put many of them behind (a drone over
        its floor: 7-40 %), which its Sampson cost does not see (_CHEIRALITY_SHARE)."""
        return m.n_front >= _CHEIRALITY_SHARE * than.n_front

    def winner(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The model that replaces RANSAC's, or None: one that puts clearly more points
        in front of both cameras and fits the pixels not clearly worse (a flat scene's
        decomposition RANSAC took, with a third of its points behind); or a turned
        start that fits better by more than chance (_BASIN_CHI2) and puts as many in
        front. Of those, the one of least cost. A decomposition of the homography does
        not win by its cost alone: between the two poses of a flat scene the tracks'
        cost cannot be trusted to choose (docs/method.md §2.1.2: on the rendered narrow
        orbit, seed 1, the wrong one fitted better by chi 9-35 in 5 of the 7 pairs
        0-5 ... 0-11)."""
        first = self.models[0]

        def wins(m: EpipolarModel) -> bool:
            chi = self.chi(first.cost, m.cost)
            if not self._explains(first, m):
                return chi > -_BASIN_CHI2
            return not m.planar and chi >= _BASIN_CHI2 and self._explains(m, first)

        better = [m for m in self.models[1:] if wins(m)]
        if not better:
            return None
        best = min(better, key=lambda m: m.cost)
        return best.R, best.t

    def rivals(self, R: np.ndarray, cov_rot: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """The models the pair cannot rule out against the model taken (of these,
        rotation R; cov_rot the 3x3 world covariance of R^T, as relative_pose_covariance
        gives it): those that fit the pixels better or within chance of it (_BASIN_CHI2)
        and the points as well, but whose rotation its covariance does not cover
        (_DISTINCT_CHI2). Each as (d, chi): the world rotation vector from R^T to its
        R^T, and its chi against the model taken (positive: it fits better)."""
        taken = min(self.models, key=lambda m: float(np.sum((m.R - R) ** 2)))
        C = cov_rot + np.eye(3) * _DISTINCT_FLOOR_RAD ** 2
        found = []
        for m in self.models:
            chi = self.chi(taken.cost, m.cost)
            if chi <= -_BASIN_CHI2 or not self._explains(m, taken):
                continue                       # fits clearly worse, or its points do
            # world frame: R1^T = Exp(d) R^T
            d = geo.quat_to_rotvec(geo.matrix_to_quat(m.R.T @ R))
            if float(d @ np.linalg.solve(C, d)) > _DISTINCT_CHI2:
                found.append((d, chi))
        return found


def epipolar_basins(R0: np.ndarray, t0: np.ndarray, p_ref: np.ndarray, p_cur: np.ndarray,
                    K: np.ndarray, gate_px: float, huber_px: float,
                    homography: np.ndarray | None = None) -> EpipolarBasins | None:
    """RANSAC's polished model (R0, t0) and the models polished again from other starts
    (docs/method.md §2.1.1): translations turned away from it, and the relative poses
    of the homography's decompositions; None when too few pixels are near the model to
    judge other starts by.

    Why the turned starts: a camera moving forward has a second minimum of the epipolar
    cost, the translation turned sideways by 20-40 deg with a yaw or pitch of 2-3 deg
    that compensates it (Oliensis, IJCV 2005). RANSAC's model lands in either basin and
    a polish stays in it: the rendered walk after standing, seed 6, started 3.1 deg off
    with a covariance of 0.2 deg. Why the homography's: a scene close to a plane has two
    relative poses that fit it (the planar ambiguity, H&Z sec. 13.1.1; Faugeras &
    Lustman 1988), and RANSAC's five-point model may be the wrong one: the rendered orbit
    after standing, seed 77, took a pair 8.3 deg off, its translation 63 deg away, where
    the homography's other decomposition polished to 0.15 deg. What decides between
    them is in EpipolarBasins: winner and rivals."""
    r0 = np.abs(sampson_px(R0, t0, p_ref, p_cur, K))
    near = r0 < gate_px
    if np.count_nonzero(near) < 2 * _MIN_POINTS_ESSENTIAL:
        return None                        # nothing to judge other starts by
    var = max(float(np.mean(r0[near] ** 2)), _MIN_SAMPSON_VAR_PX2)

    cost0 = robust_sampson_cost(R0, t0, p_ref, p_cur, K, gate_px, huber_px)

    def model(R: np.ndarray, t: np.ndarray, planar: bool = False) -> EpipolarModel:
        cost = robust_sampson_cost(R, t, p_ref, p_cur, K, gate_px, huber_px)
        # a model is compared with RANSAC's or with one that fits better: beyond chance
        # of RANSAC's cost it is never a candidate, and its points are not counted
        n_front = 0 if 2.0 * (cost - cost0) / var >= _BASIN_CHI2 else \
            max(int(np.count_nonzero(triangulate_points(
                np.eye(4), _se3(R, sign * t), p_ref, p_cur, K, gate_px, 0.0).valid))
                for sign in (1.0, -1.0))
        return EpipolarModel(cost, R, t, n_front, planar)

    models = [model(R0, t0)]
    B = _tangent_basis(t0)
    for turn in _START_TURNS:
        for axis in range(2):
            t_start = t0 + math.tan(turn) * B[:, axis]
            R1, t1 = refine_relative_pose(R0, t_start / np.linalg.norm(t_start), p_ref,
                                          p_cur, K, gate_px=gate_px, huber_px=huber_px,
                                          iterations=_START_ITERATIONS)
            if robust_sampson_cost(R1, t1, p_ref, p_cur, K, gate_px, huber_px) < cost0:
                R1, t1 = refine_relative_pose(R1, t1, p_ref, p_cur, K, gate_px=gate_px,
                                              huber_px=huber_px)
            models.append(model(R1, t1))
    if homography is not None:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(homography, K)
        starts = []
        for Rh, th in zip(Rs, ts):
            th = th.reshape(3)
            # t and -t cost the same (Sampson): one start per rotation
            if np.linalg.norm(th) > 0 and not any(np.allclose(Rh, R) for R in starts):
                starts.append(Rh)
                models.append(model(*refine_relative_pose(
                    Rh, th / np.linalg.norm(th), p_ref, p_cur, K, gate_px=gate_px,
                    huber_px=huber_px), planar=True))
    return EpipolarBasins(models, var)


def other_basin(R0: np.ndarray, t0: np.ndarray, p_ref: np.ndarray, p_cur: np.ndarray,
                K: np.ndarray, gate_px: float, huber_px: float,
                basins: EpipolarBasins | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """A polished model (R0, t0) polished again from other starts (epipolar_basins, or
    `basins` already found): the model of another basin that replaces it
    (EpipolarBasins.winner), its t signed by its points, or None. A turned start wins by
    fitting the pixels better by more than chance: twice the cost decrease over the
    residuals' variance passes chi-square 5 dof at 99.9 %. The other basin won by
    115-147; the same basin polished further won by 0.1-8.7, moving the rotation by up
    to 0.24 deg, on two rendered ground robots away from the truth."""
    basins = basins or epipolar_basins(R0, t0, p_ref, p_cur, K, gate_px, huber_px)
    found = None if basins is None else basins.winner()
    if found is None:
        return None         # no other basin: at most the same one, polished further
    R, t = found
    # the Sampson cost cannot tell t from -t (R moved continuously from the voted
    # decomposition): the sign that puts most of the model's own inliers in front of
    # the reference camera, depth from x2 ~ lambda R x1 + t
    inl = np.abs(sampson_px(R, t, p_ref, p_cur, K)) < gate_px
    K_inv = np.linalg.inv(K)
    x1 = homogeneous(p_ref[inl]) @ K_inv.T
    x2 = homogeneous(p_cur[inl]) @ K_inv.T
    a, b = np.cross(x2, x1 @ R.T), np.cross(x2, t)
    depth_sign = -np.einsum('ij,ij->i', a, b)
    return (R, t) if np.count_nonzero(depth_sign > 0) >= np.count_nonzero(depth_sign < 0) \
        else (R, -t)


def common_tracks(ids_ref: np.ndarray, px_ref: np.ndarray, ids_cur: np.ndarray,
                  px_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersect two id-labelled observation sets.

    Returns (ids (C,) int64 ascending, px_ref (C, 2), px_cur (C, 2)); rows with a
    non-finite pixel are dropped. Raises ValueError on mismatched shapes or duplicate ids.
    """
    ids_ref = np.asarray(ids_ref, np.int64).reshape(-1)
    ids_cur = np.asarray(ids_cur, np.int64).reshape(-1)
    px_ref = np.asarray(px_ref, np.float64).reshape(-1, 2)
    px_cur = np.asarray(px_cur, np.float64).reshape(-1, 2)
    if ids_ref.shape[0] != px_ref.shape[0] or ids_cur.shape[0] != px_cur.shape[0]:
        raise ValueError('ids and px must have the same length')
    if np.unique(ids_ref).size != ids_ref.size or np.unique(ids_cur).size != ids_cur.size:
        raise ValueError('duplicate track ids')
    ids, i_ref, i_cur = np.intersect1d(ids_ref, ids_cur, assume_unique=True,
                                       return_indices=True)
    p_ref, p_cur = px_ref[i_ref], px_cur[i_cur]
    finite = np.isfinite(p_ref).all(axis=1) & np.isfinite(p_cur).all(axis=1)
    return ids[finite], p_ref[finite], p_cur[finite]


class TwoViewBootstrap:
    """Essential-matrix bootstrap of the first map from two frames.

    Args:
        cfg: uses bootstrap_min_parallax_deg, bootstrap_min_inliers, bootstrap_ransac_px,
            bootstrap_baseline_m, triangulation_max_reproj_px,
            bootstrap_point_min_parallax_deg.
        K: (3, 3) pinhole intrinsics of the IDEAL (undistorted) pixel coordinates.
    """

    def __init__(self, cfg: VoConfig, K: np.ndarray) -> None:
        K = np.asarray(K, np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f'K must be a finite 3x3 pinhole matrix, got {K!r}')
        self.cfg = cfg
        self.K = K
        f = 0.5 * (K[0, 0] + K[1, 1])
        # Translational flow of a point is about f * parallax (small angles); half of it
        # is a cheap lower bound below which the parallax test is not tried. A pair
        # whose tracks are going (kept_share < 1) may be judged by the relief gate, and
        # whether its scene has relief is known only after the fit; a pair judged by
        # the full gate after all meets the full gate's bound then.
        def min_flow(gate_deg: float) -> float:
            return float(getattr(cfg, 'bootstrap_min_flow_px',
                                 0.5 * f * math.tan(math.radians(gate_deg))))
        self.min_flow_px = min_flow(cfg.bootstrap_min_parallax_deg)
        self._min_flow_relief_px = min_flow(min(cfg.bootstrap_min_parallax_deg,
                                                self.parallax_gate(0.0, lasting=False)))

    # ------------------------------------------------------------------ public API

    def try_pair(self, ids_ref: np.ndarray, px_ref: np.ndarray, ids_cur: np.ndarray,
                 px_cur: np.ndarray, baseline: float | None = None,
                 min_parallax_deg: float | None = None,
                 kept_share: float = 1.0) -> BootstrapResult:
        """Attempt a bootstrap from a reference and a current frame.

        Args:
            ids_ref, px_ref: (N,) int64 track ids and (N, 2) IDEAL pixels, reference.
            ids_cur, px_cur: (M,) int64 track ids and (M, 2) IDEAL pixels, current.
            baseline: |t_cur_ref| to impose (map units); default bootstrap_baseline_m.
            min_parallax_deg: the median parallax the pair must reach; default
                `parallax_gate`.
            kept_share: the share of the reference's tracks the current frame kept
                from the frame before; the next frame is expected to keep as many
                (1: the tracks last, so a pair is never taken at the relief gate).

        Returns:
            BootstrapResult; `ok` False with a `reason` when the pair is refused.
        """
        cfg = self.cfg
        baseline = float(cfg.bootstrap_baseline_m if baseline is None else baseline)
        if not baseline > 0 or not math.isfinite(baseline):
            raise ValueError(f'baseline must be positive and finite, got {baseline}')
        ids, p_ref, p_cur = common_tracks(ids_ref, px_ref, ids_cur, px_cur)
        n_common = int(ids.shape[0])
        need = max(int(cfg.bootstrap_min_inliers), _MIN_POINTS_ESSENTIAL)
        if n_common < need:
            return self._refuse(f'too few common tracks ({n_common} < {need})',
                                n_common=n_common)
        flow = float(np.median(np.linalg.norm(p_cur - p_ref, axis=1)))
        min_flow = self._min_flow_relief_px if kept_share < 1 and min_parallax_deg is None \
            else self.min_flow_px
        if flow < min_flow:
            return self._refuse(f'insufficient parallax: median flow {flow:.2f} px < '
                                f'{min_flow:.2f} px', n_common=n_common,
                                median_flow_px=flow)

        # (b) Essential matrix (Nister five-point + RANSAC) and relative pose.
        thr = float(cfg.bootstrap_ransac_px)
        pose = self._relative_pose(p_ref, p_cur, thr)
        if isinstance(pose, str):
            return self._refuse(pose, n_common=n_common, median_flow_px=flow)
        R, t, inl, n_e = pose

        H, h_over_e = self._homography(p_ref, p_cur, n_e)
        judged = self._judge_pose(ids, p_ref, p_cur, R, t, inl, h_over_e, n_common, flow,
                                  baseline, min_parallax_deg, kept_share)
        if not judged.ok:
            return judged
        # (f) Only for a pair that would be taken (it costs 10 polishes): is there another
        # basin of the epipolar cost that fits better? Then that model is judged instead.
        gate, huber = _GATE_SCALE * thr, _HUBER_SCALE * thr
        basins = epipolar_basins(R, t, p_ref, p_cur, self.K, gate, huber, H)
        found = other_basin(R, t, p_ref, p_cur, self.K, gate, huber, basins)
        if found is not None:
            R, t = found
            logger.info('bootstrap: the relative pose moved to the other basin of the '
                        'epipolar cost')
            inl = np.abs(sampson_px(R, t, p_ref, p_cur, self.K)) < gate
            judged = self._judge_pose(ids, p_ref, p_cur, R, t, inl, h_over_e, n_common,
                                      flow, baseline, min_parallax_deg, kept_share)
        if not judged.ok or basins is None:
            return judged
        # (g) Is there another relative pose that fits within chance, beyond this one's
        # covariance (the planar ambiguity, docs/method.md §2.1.2)? Then the pair cannot
        # tell which, and a map made of it would be published confidently wrong half
        # the time.
        cov_rot = relative_pose_covariance(
            self.K, np.eye(4), _inverse_se3(judged.T_cur_ref), judged.X_ref,
            self.cfg.pixel_sigma_px)[3:, 3:]
        rivals = basins.rivals(R, cov_rot)
        level = [d for d, chi in rivals if chi < _BASIN_CHI2]
        if level:
            return self._refuse(
                f'ambiguous: two relative poses {np.degrees(np.linalg.norm(level[0])):.1f} '
                f'deg apart fit the pair about as well (a scene close to a plane); waiting '
                f'for parallax to tell them apart', n_common=n_common, median_flow_px=flow,
                h_over_e=h_over_e, median_parallax_deg=judged.median_parallax_deg,
                n_inliers=judged.n_inliers, triangulation=judged.triangulation)
        # a flat scene's other pose that fits clearly better: the tracks may be what
        # favours it (docs/method.md §2.1.2), waiting does not undo them, and the map's
        # covariance holds the difference instead
        judged.rival_rotvecs = np.array([d for d, _ in rivals]).reshape(-1, 3)
        return judged

    def _judge_pose(self, ids: np.ndarray, p_ref: np.ndarray, p_cur: np.ndarray,
                    R: np.ndarray, t: np.ndarray, inl: np.ndarray, h_over_e: float,
                    n_common: int, flow: float, baseline: float,
                    min_parallax_deg: float | None, kept_share: float) -> BootstrapResult:
        """Steps (c)-(e) of try_pair for the relative pose (R, t unit) with inliers
        `inl`: triangulation, degeneracy and parallax gates, scale."""
        cfg = self.cfg
        # (c) Triangulate the inliers (unit baseline; the scale is applied at the end,
        # all checks are scale-invariant).
        T_ref = np.eye(4)
        T_cur = _se3(R, t)
        tri = triangulate_points(T_ref, T_cur, p_ref, p_cur, self.K,
                                 cfg.triangulation_max_reproj_px,
                                 cfg.bootstrap_point_min_parallax_deg)
        good_geom = inl & np.isfinite(tri.reproj_err_px) & \
            (tri.reproj_err_px < cfg.triangulation_max_reproj_px)
        med_par = float(np.median(tri.parallax_deg[good_geom])) if good_geom.any() else 0.0
        valid = inl & tri.valid
        n_valid = int(valid.sum())

        # (d) Degeneracy: homography vs essential (pure rotation / planar at infinity),
        # `h_over_e` (_homography).
        common = dict(n_common=n_common, median_flow_px=flow, h_over_e=h_over_e,
                      median_parallax_deg=med_par, n_inliers=n_valid, triangulation=tri)
        lasting = n_valid * float(kept_share) >= cfg.bootstrap_min_inliers
        min_par = float(self.parallax_gate(h_over_e, lasting) if min_parallax_deg is None
                        else min_parallax_deg)
        if flow < self.min_flow_px and min_par >= cfg.bootstrap_min_parallax_deg:
            # judged by the full gate after all: the pre-check it would have failed
            return self._refuse(f'insufficient parallax: median flow {flow:.2f} px < '
                                f'{self.min_flow_px:.2f} px', **common)
        if h_over_e >= H_OVER_E_RATIO and med_par < min_par:
            return self._refuse(
                f'pure rotation / insufficient parallax: the homography explains '
                f'{100 * h_over_e:.0f}% of the essential inliers and the median parallax '
                f'is {med_par:.2f} deg < {min_par:.2f} deg', rotation_like=True, **common)
        if med_par < min_par:
            waiting = min_parallax_deg is None and \
                med_par >= self.parallax_gate(h_over_e, lasting=False)
            return self._refuse(f'insufficient parallax: median {med_par:.2f} deg < '
                               f'{min_par:.2f} deg'
                               + (' (waiting while the tracks last)' if waiting else ''),
                               **common)
        if n_valid < int(cfg.bootstrap_min_inliers):
            return self._refuse(f'too few valid triangulated points ({n_valid} < '
                                f'{cfg.bootstrap_min_inliers})', **common)

        # (e) Fix the scale: |t| = baseline, the points scale with it.
        t_s = t * baseline
        X_ref = tri.X_world[valid] * baseline
        logger.info('bootstrap ok: %d points, median parallax %.2f deg, H/E %.2f',
                    n_valid, med_par, h_over_e)
        return BootstrapResult(
            ok=True, reason='ok', R_cur_ref=R, t_cur_ref=t_s, T_cur_ref=_se3(R, t_s),
            point_ids=ids[valid], X_ref=X_ref, X_world=X_ref.copy(), inlier_ids=ids[inl],
            **common)

    def parallax_gate(self, h_over_e: float, lasting: bool = True) -> float:
        """The median parallax [deg] a pair must reach (docs/method.md §2.2.1).

        Depth relief (the homography explains less than bootstrap_relief_h_over_e of
        the essential matrix's inliers) makes the five-point pose unique and well
        conditioned at less parallax: on a car at 10 Hz (H/E 0.25-0.6) one frame of
        motion gives a pose within 0.3 deg and 1 deg of translation direction at 1-1.5
        deg of median parallax. But a pair with more parallax gives a better first map
        (KITTI 06, 8 seeds: 1-frame pairs 0.152 % ATE, 2-frame pairs 0.148 %; as JPEG,
        at half size, flickering or backwards 7-34 % worse), so the lower gate is for
        a pair whose tracks will not last (`lasting` False): a fast car keeps half its
        tracks a frame and would never reach the full gate. Flat or far scenes and
        rotations (H/E 0.55-1.2 in the rendered rooms) keep the full gate: there the
        five-point solution may be the wrong one of the planar ambiguity."""
        cfg = self.cfg
        if h_over_e < cfg.bootstrap_relief_h_over_e and not lasting:
            return float(cfg.bootstrap_relief_parallax_deg)
        return float(cfg.bootstrap_min_parallax_deg)

    def _relative_pose(self, p_ref: np.ndarray, p_cur: np.ndarray, thr: float):
        """Step (b) of try_pair: (R, t (unit), inlier mask, essential inliers) of the pair,
        or the reason for refusing it (str)."""
        E, mask_e = cv2.findEssentialMat(p_ref, p_cur, self.K, method=cv2.RANSAC,
                                         prob=_RANSAC_PROB, threshold=thr)
        if E is None or mask_e is None or E.shape[0] < 3:
            return 'no essential matrix found'
        E = E[:3]   # several stacked solutions may come back; RANSAC keeps the best first
        mask_e = mask_e.reshape(-1).astype(bool)
        n_e = int(mask_e.sum())
        if n_e < 2 * _MIN_POINTS_ESSENTIAL:
            # The count that matters (valid triangulated points) is checked after the
            # polish, whose gate is wider than the RANSAC threshold.
            return f'too few essential-matrix inliers ({n_e})'
        # recoverPose: the decomposition (of four) with most points in front of both
        # cameras; it returns x_cur = R x_ref + t with |t| = 1.
        _, R, t, _ = cv2.recoverPose(E, p_ref, p_cur, self.K,
                                     mask=(mask_e.astype(np.uint8) * 255))
        t = t.reshape(3)
        t = t / np.linalg.norm(t)
        # Least-squares polish on all correspondences near the model (RANSAC's model
        # comes from five points only); the refined model then re-selects the inliers
        # with a gate of _GATE_SCALE thresholds, the triangulation checks decide the rest.
        gate = _GATE_SCALE * thr
        R, t = refine_relative_pose(R, t, p_ref, p_cur, self.K, gate_px=gate,
                                    huber_px=_HUBER_SCALE * thr)
        inl = np.abs(sampson_px(R, t, p_ref, p_cur, self.K)) < gate
        return R, t, inl, n_e

    def from_known_poses(self, T_ref_world: np.ndarray, T_cur_world: np.ndarray,
                         ids_ref: np.ndarray, px_ref: np.ndarray, ids_cur: np.ndarray,
                         px_cur: np.ndarray, min_points: int | None = None
                         ) -> BootstrapResult:
        """Triangulate the first map from two GIVEN poses (the paper's GT bootstrap).

        Args:
            T_ref_world, T_cur_world: (4, 4) world -> camera poses of the two frames.
            ids_ref, px_ref, ids_cur, px_cur: as in `try_pair` (IDEAL pixels).
            min_points: fewest valid points to accept (default bootstrap_min_inliers).

        Returns:
            BootstrapResult with X_world (world frame), X_ref (reference camera frame)
            and T_cur_ref = T_cur_world T_ref_world^-1. No parallax refusal: the poses,
            and so the scale, are known; points below the per-point parallax are simply
            not triangulated.
        """
        cfg = self.cfg
        T_ref_world = np.asarray(T_ref_world, np.float64)
        T_cur_world = np.asarray(T_cur_world, np.float64)
        need = int(cfg.bootstrap_min_inliers if min_points is None else min_points)
        ids, p_ref, p_cur = common_tracks(ids_ref, px_ref, ids_cur, px_cur)
        n_common = int(ids.shape[0])
        T_cur_ref = T_cur_world @ _inverse_se3(T_ref_world)
        if n_common < need:
            return self._refuse(f'too few common tracks ({n_common} < {need})',
                                n_common=n_common)
        tri = triangulate_points(T_ref_world, T_cur_world, p_ref, p_cur, self.K,
                                 cfg.triangulation_max_reproj_px,
                                 cfg.bootstrap_point_min_parallax_deg)
        good_geom = np.isfinite(tri.reproj_err_px) & \
            (tri.reproj_err_px < cfg.triangulation_max_reproj_px)
        med_par = float(np.median(tri.parallax_deg[good_geom])) if good_geom.any() else 0.0
        valid = tri.valid
        n_valid = int(valid.sum())
        common = dict(n_common=n_common,
                      median_flow_px=float(np.median(np.linalg.norm(p_cur - p_ref, axis=1))),
                      median_parallax_deg=med_par, n_inliers=n_valid, triangulation=tri,
                      R_cur_ref=T_cur_ref[:3, :3].copy(), t_cur_ref=T_cur_ref[:3, 3].copy(),
                      T_cur_ref=T_cur_ref, inlier_ids=ids)
        if n_valid < need:
            return self._refuse(f'too few valid triangulated points ({n_valid} < {need})',
                                **common)
        X_world = tri.X_world[valid]
        X_ref = X_world @ T_ref_world[:3, :3].T + T_ref_world[:3, 3]
        return BootstrapResult(ok=True, reason='ok', point_ids=ids[valid], X_ref=X_ref,
                               X_world=X_world, **common)

    # ------------------------------------------------------------------ internals

    def _homography(self, p_ref: np.ndarray, p_cur: np.ndarray, n_e: int
                    ) -> tuple[np.ndarray | None, float]:
        """The homography of the pair (RANSAC; None when none is found) and its inliers
        divided by the essential matrix's (0 then)."""
        thr = float(self.cfg.bootstrap_ransac_px) * _H_THRESHOLD_SCALE
        H, mask_h = cv2.findHomography(p_ref, p_cur, cv2.RANSAC, thr,
                                       confidence=_RANSAC_PROB)
        if H is None or mask_h is None or n_e == 0:
            return None, 0.0
        return H, float(mask_h.sum()) / float(n_e)

    @staticmethod
    def _refuse(reason: str, **kwargs: object) -> BootstrapResult:
        logger.debug('bootstrap refused: %s', reason)
        return BootstrapResult(ok=False, reason=reason, **kwargs)

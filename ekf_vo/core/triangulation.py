"""Two-view triangulation of ideal pixel observations, with the usual validity checks.

Convention: `T_cam_world` (4x4) maps world points into the camera optical frame
(x right, y down, z forward): X_cam = R X_world + t, with [R | t] the top 3x4 block.
Pixels are IDEAL (undistorted) coordinates of the pinhole K: u = fx X/Z + cx,
v = fy Y/Z + cy.

Method: linear (DLT) triangulation (Hartley & Zisserman, "Multiple View Geometry", 2nd
ed., sec. 12.2) through cv2.triangulatePoints, fed with NORMALISED image coordinates
K^-1 [u v 1]^T and the projection matrices [R | t]: normalising first is the
conditioning H&Z recommend (sec. 4.4.4) and makes the algebraic error meaningful. A point
is valid only when

1. its homogeneous coordinate is non-zero and the result finite,
2. it lies in front of both cameras (cheirality, depth > `min_depth`),
3. its reprojection error is below `max_reproj_px` in BOTH views,
4. the parallax angle between the two viewing rays, angle(X - C1, X - C2) with C the
   camera centres, is at least `min_parallax_deg` (small parallax means depth is poorly
   constrained: depth error grows like pixel noise / parallax).

Degenerate cases (they yield valid = False, never an exception):

- zero baseline (both camera centres equal, e.g. pure rotation): every ray pair meets at
  the centre or nowhere; the parallax is 0 for all points;
- points on (or near) the baseline, i.e. near the epipoles: the two rays are (nearly)
  collinear, parallax ~ 0, depth unobservable;
- points at infinity or rays that are parallel (homogeneous w ~ 0): X is non-finite and
  reported as NaN;
- points behind either camera (a mismatched track, or the wrong one of the four
  essential-matrix decompositions): cheirality fails;
- N = 0: empty arrays.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from . import geometry as geo

logger = logging.getLogger(__name__)

#: Minimum depth (in the map's length unit) for the cheirality check.
DEFAULT_MIN_DEPTH = 1e-6
#: |w| below this (relative to the largest homogeneous coordinate) is a point at infinity.
_W_EPS = 1e-12


@dataclass
class TriangulationResult:
    """Per-point output of `triangulate_points`.

    Attributes:
        X_world: (N, 3) float64 points in the world frame (NaN where w ~ 0).
        valid: (N,) bool, all checks passed.
        reproj_err_px: (N,) float64, the LARGER of the two views' reprojection errors
            (inf where a depth is not positive).
        parallax_deg: (N,) float64, angle between the rays from the two camera centres
            to the point (0 where undefined).
        depth1: (N,) float64, z of the point in camera 1.
        depth2: (N,) float64, z of the point in camera 2.
        sq_err_sum_px2: (N,) float64, the two views' squared reprojection errors summed
            (inf where a depth is not positive): four coordinates fit by three, so at the
            least-squares point it is sigma^2 times a chi-square of 1 dof.
    """

    X_world: np.ndarray
    valid: np.ndarray
    reproj_err_px: np.ndarray
    parallax_deg: np.ndarray
    depth1: np.ndarray
    depth2: np.ndarray
    sq_err_sum_px2: np.ndarray

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.valid))


def _check_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f'{name} must be a finite 4x4 matrix, got shape {T.shape}')
    return T


def project(T_cam_world: np.ndarray, X_world: np.ndarray, K: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points (no distortion), by one camera (4, 4) or by one
    camera per point (N, 4, 4).

    Returns (px (N, 2) ideal pixels, depth (N,) z in the camera frame).
    """
    X_cam = geo.transform_points(T_cam_world, X_world)
    z = X_cam[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        uv = X_cam[:, :2] / z[:, None]
    px = uv @ K[:2, :2].T + K[:2, 2]
    return px, z


def triangulate_points(T_cam1_world: np.ndarray, T_cam2_world: np.ndarray,
                       px1: np.ndarray, px2: np.ndarray, K: np.ndarray,
                       max_reproj_px: float, min_parallax_deg: float,
                       min_depth: float = DEFAULT_MIN_DEPTH) -> TriangulationResult:
    """Triangulate N correspondences seen by two posed pinhole cameras.

    Args:
        T_cam1_world, T_cam2_world: (4, 4) world -> camera poses (X_cam = R X_w + t).
        px1, px2: (N, 2) IDEAL pixel coordinates in camera 1 and camera 2.
        K: (3, 3) pinhole intrinsics shared by both views.
        max_reproj_px: largest accepted reprojection error (pixels, each view).
        min_parallax_deg: smallest accepted angle between the two rays (degrees).
        min_depth: smallest accepted depth in both cameras (map units).

    Returns:
        TriangulationResult with per-point points, validity and diagnostics.
    """
    T1 = _check_pose(T_cam1_world, 'T_cam1_world')
    T2 = _check_pose(T_cam2_world, 'T_cam2_world')
    K = np.asarray(K, np.float64)
    px1 = np.asarray(px1, np.float64).reshape(-1, 2)
    px2 = np.asarray(px2, np.float64).reshape(-1, 2)
    if px1.shape != px2.shape:
        raise ValueError(f'px1 {px1.shape} and px2 {px2.shape} differ')
    n = px1.shape[0]
    if n == 0:
        e = np.empty(0, np.float64)
        return TriangulationResult(np.empty((0, 3)), np.empty(0, bool), e, e.copy(),
                                   e.copy(), e.copy(), e.copy())

    X, finite = _dlt(T1, T2, px1, px2, K)
    C1 = -T1[:3, :3].T @ T1[:3, 3]
    return _checked(X, finite, project(T1, X, K), C1, T2, px1, px2, K, max_reproj_px,
                    min_parallax_deg, min_depth)


def triangulate_points_from(T_cam1_world: list[np.ndarray], first: np.ndarray,
                            T_cam2_world: np.ndarray, px1: np.ndarray, px2: np.ndarray,
                            K: np.ndarray, max_reproj_px: float, min_parallax_deg: float,
                            min_depth: float = DEFAULT_MIN_DEPTH) -> TriangulationResult:
    """`triangulate_points` of N correspondences whose first views differ: point i was
    seen first by the camera T_cam1_world[first[i]], and now by T_cam2_world. The same
    DLT per first view, and the same checks, in one pass over all the points (map
    growth triangulates the candidates of several frames at once, docs/method.md
    §17.8)."""
    T2 = _check_pose(T_cam2_world, 'T_cam2_world')
    T1s = np.stack([_check_pose(T, 'T_cam1_world') for T in T_cam1_world]) \
        if len(T_cam1_world) else np.zeros((0, 4, 4))
    K = np.asarray(K, np.float64)
    px1 = np.asarray(px1, np.float64).reshape(-1, 2)
    px2 = np.asarray(px2, np.float64).reshape(-1, 2)
    first = np.asarray(first, np.int64).reshape(-1)
    if px1.shape != px2.shape or first.shape[0] != px1.shape[0]:
        raise ValueError(f'px1 {px1.shape}, px2 {px2.shape} and first {first.shape} differ')
    X = np.full((px1.shape[0], 3), np.nan)
    finite = np.zeros(px1.shape[0], bool)
    for v in np.unique(first).tolist():
        rows = first == v
        X[rows], finite[rows] = _dlt(T1s[v], T2, px1[rows], px2[rows], K)
    T1 = T1s[first]
    C1 = -np.einsum('nji,nj->ni', T1[:, :3, :3], T1[:, :3, 3])
    return _checked(X, finite, project(T1, X, K), C1, T2, px1, px2, K, max_reproj_px,
                    min_parallax_deg, min_depth)


def _dlt(T1: np.ndarray, T2: np.ndarray, px1: np.ndarray, px2: np.ndarray, K: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """DLT points (n,3) (NaN where not finite or at infinity) and whether each is finite."""
    # Normalised coordinates: x = K^-1 [u v 1]^T (H&Z sec. 4.4.4 conditioning).
    K_inv = np.linalg.inv(K)
    x1 = px1 @ K_inv[:2, :2].T + K_inv[:2, 2]
    x2 = px2 @ K_inv[:2, :2].T + K_inv[:2, 2]
    finite_in = np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1)
    x1 = np.where(finite_in[:, None], x1, 0.0)
    x2 = np.where(finite_in[:, None], x2, 0.0)

    # DLT (H&Z eq. 12.1-12.2): smallest singular vector of the stacked cross products.
    Xh = cv2.triangulatePoints(T1[:3], T2[:3], x1.T.copy(), x2.T.copy())   # (4, N)
    w = Xh[3]
    scale = np.abs(Xh).max(axis=0)
    at_inf = ~(np.abs(w) > _W_EPS * np.maximum(scale, 1e-300))
    with np.errstate(divide='ignore', invalid='ignore'):
        X = (Xh[:3] / np.where(at_inf, np.nan, w)).T
    finite = finite_in & ~at_inf & np.isfinite(X).all(axis=1)
    X[~finite] = np.nan
    return X, finite


def _checked(X: np.ndarray, finite: np.ndarray, proj1: tuple[np.ndarray, np.ndarray],
             C1: np.ndarray, T2: np.ndarray, px1: np.ndarray, px2: np.ndarray,
             K: np.ndarray, max_reproj_px: float, min_parallax_deg: float,
             min_depth: float) -> TriangulationResult:
    """The validity checks of the module docstring, given the points' projection into
    their first view (px, depth) and its centre C1 ((3,) or one per point (n,3))."""
    n = X.shape[0]
    # Cheirality: in front of both cameras.
    px1_hat, z1 = proj1
    px2_hat, z2 = project(T2, X, K)
    in_front = finite & (z1 > min_depth) & (z2 > min_depth)

    # Reprojection error, the worse of the two views.
    with np.errstate(invalid='ignore'):
        e1 = np.linalg.norm(px1_hat - px1, axis=1)
        e2 = np.linalg.norm(px2_hat - px2, axis=1)
        err = np.maximum(e1, e2)
        sq_sum = e1 ** 2 + e2 ** 2
    usable = in_front & np.isfinite(err)
    err = np.where(usable, err, np.inf)
    sq_sum = np.where(usable, sq_sum, np.inf)

    # Parallax: angle between the rays from the centres C = -R^T t to X.
    C2 = -T2[:3, :3].T @ T2[:3, 3]
    r1 = X - C1
    r2 = X - C2
    with np.errstate(invalid='ignore', divide='ignore'):
        cos = np.einsum('ij,ij->i', r1, r2) / (np.linalg.norm(r1, axis=1) *
                                                np.linalg.norm(r2, axis=1))
        parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    parallax = np.where(np.isfinite(parallax), parallax, 0.0)

    valid = in_front & (err < max_reproj_px) & (parallax >= min_parallax_deg)
    logger.debug('triangulated %d/%d (finite %d, in front %d)', int(valid.sum()), n,
                 int(finite.sum()), int(in_front.sum()))
    return TriangulationResult(X, valid, err, parallax, z1, z2, sq_sum)


def depth_debiased(X_world: np.ndarray, centre: np.ndarray, cov: np.ndarray,
                   max_rel_shift: float = 0.25) -> np.ndarray:
    """Points (n,3) moved towards the camera centre(s) `centre` ((3,) or (n,3)) they are
    seen from by the second-order bias of a two-view depth (docs/method.md §7.2.1).

    A depth triangulated from a parallax angle is d = b / theta; with the measured
    angle theta + e, e ~ N(0, s^2), E[d_hat] = d (1 + s^2 / theta^2) + O(s^4), i.e. the
    depth is too long on average by var(d) / d, where var(d) = u^T cov u is the point's
    variance along its unit ray u. The inverse depth is unbiased; the depth is not, and a
    map point's depth is what carries the scale to the next frame's translation (§7.2.1).
    `cov` (n,3,3) is the point's covariance at the pixel noise the caller believes. The
    shift is capped at `max_rel_shift` of the depth (a guard: a gated point's relative
    depth spread is far below that)."""
    X = np.asarray(X_world, float).reshape(-1, 3)
    ray = X - np.asarray(centre, float)
    d = np.linalg.norm(ray, axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        u = ray / d[:, None]
        var_d = np.einsum('ni,nij,nj->n', u, np.asarray(cov, float), u)
        rel = np.clip(var_d / d ** 2, 0.0, max_rel_shift)
    rel = np.where(np.isfinite(rel), rel, 0.0)
    return X - (rel * d)[:, None] * np.where(np.isfinite(u), u, 0.0)

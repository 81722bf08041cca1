"""An independent check of the filter's rotation: the two-view geometry between keyframes.

docs/method.md §15.2. The filter's rotation comes from the map; if the map bends (points
made from drifting poses, a bootstrap that conditioned it badly), the filter follows it
while its innovations stay small. The relative rotation of two keyframes can also be had
without the map: from the essential matrix of the tracks they share. OpenCV's
USAC_ACCURATE estimator (RANSAC with local optimisation) reaches the maximum-likelihood
spread on these problems (measured: test/test_rotation_check.py), so its covariance is
the two-view bundle-adjustment covariance of map_uncertainty.relative_pose_covariance,
with the pixel noise estimated from the inliers' own Sampson errors.

    d = Log(R_ab,filter R_ab,two-view^T)        (rotation vector in keyframe a's frame)
    NEES = d^T Sigma_two-view^-1 d              (3 dof; 16.27 is the 99.9 % bound)

Not judged (None): a pair whose rays barely differ (median parallax below
`min_parallax_deg`), and a pair whose shared tracks a homography explains about as well
as the essential matrix (a plane filling the view, or a rotation about the centre: there
the essential matrix is ambiguous — two solutions fit a plane — and on the rendered room's
walls it was degrees off while its covariance said hundredths). The model selection is
the bootstrap's (bootstrap.py, after ORB-SLAM's): the homography's share of the inliers.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from . import geometry as geo
from .map_uncertainty import relative_pose_covariance

#: fewest shared inlier tracks for a verdict
MIN_POINTS = 20


@dataclass(frozen=True)
class RotationCheck:
    discrepancy_world: np.ndarray   #: (3,) filter minus two-view, world rotation vector
    nees: float                     #: against the two-view covariance (3 dof)
    angle_deg: float                #: |discrepancy|
    sigma_px: float                 #: pixel noise estimated from the inliers
    n_inliers: int
    parallax_deg: float             #: median angle between the inliers' rays


def _sampson_px(E: np.ndarray, K: np.ndarray, pa: np.ndarray, pb: np.ndarray
                ) -> np.ndarray:
    """Sampson distances [px] of the pixel pairs to the epipolar geometry F = K^-T E K^-1."""
    Ki = np.linalg.inv(K)
    F = Ki.T @ E @ Ki
    xa = np.column_stack((pa, np.ones(len(pa))))
    xb = np.column_stack((pb, np.ones(len(pb))))
    Fxa, Ftxb = xa @ F.T, xb @ F
    num = np.sum(xb * Fxa, axis=1)
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    return np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def check_rotation(K: np.ndarray, ids_a: np.ndarray, px_a: np.ndarray,
                   T_world_a: np.ndarray, ids_b: np.ndarray, px_b: np.ndarray,
                   T_world_b: np.ndarray, threshold_px: float, min_parallax_deg: float,
                   max_homography_share: float, filter_cov_rot: np.ndarray | None = None,
                   seed: int = 0) -> RotationCheck | None:
    """Compare the filter's relative rotation of keyframes a and b (their poses) with
    the essential matrix of the IDEAL pixels of the tracks (ids) they share. None when
    there is not enough to judge. `filter_cov_rot`: the filter's 3x3 world rotation
    covariance, taken for each keyframe's share of the relative error."""
    common, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
    if len(common) < MIN_POINTS:
        return None
    pa = np.ascontiguousarray(px_a[ia], dtype=np.float64)
    pb = np.ascontiguousarray(px_b[ib], dtype=np.float64)
    cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(pa, pb, K, cv2.USAC_ACCURATE, 0.999, threshold_px)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    _, R_ba, t_ba, mask, X_h = cv2.recoverPose(E, pa, pb, K, distanceThresh=1e6,
                                               mask=mask.copy())
    inl = mask.ravel() > 0
    if np.count_nonzero(inl) < MIN_POINTS:
        return None
    X_a = (X_h[:3] / X_h[3]).T[inl]                   # points in frame a, |t| = 1
    T_a_b = geo.make_T(R_ba.T, (-R_ba.T @ t_ba).ravel())
    ray_a = X_a / np.linalg.norm(X_a, axis=1, keepdims=True)
    ray_b = X_a - T_a_b[:3, 3]
    ray_b /= np.linalg.norm(ray_b, axis=1, keepdims=True)
    parallax = float(np.degrees(np.median(np.arccos(np.clip(
        np.sum(ray_a * ray_b, axis=1), -1, 1)))))
    if not parallax >= min_parallax_deg:
        return None
    n = int(np.count_nonzero(inl))
    H, h_mask = cv2.findHomography(pa, pb, cv2.USAC_ACCURATE, threshold_px)
    if H is not None and h_mask is not None and \
            np.count_nonzero(h_mask) >= max_homography_share * n:
        return None
    err = _sampson_px(E, K, pa[inl], pb[inl])
    # Sampson errors are the distance to the epipolar manifold: ~ sigma per pair;
    # corrected for the 5 parameters fitted
    sigma = float(np.sqrt(np.mean(err ** 2) * n / max(n - 5, 1)))
    sigma = max(sigma, 1e-3)
    cov = relative_pose_covariance(K, np.eye(4), T_a_b, X_a, sigma)[3:, 3:]
    if filter_cov_rot is not None:
        R_aw = T_world_a[:3, :3].T
        cov = cov + 2.0 * R_aw @ filter_cov_rot @ R_aw.T
    R_ab_filter = T_world_a[:3, :3].T @ T_world_b[:3, :3]
    d_a = geo.quat_to_rotvec(geo.matrix_to_quat(R_ab_filter @ T_a_b[:3, :3].T))
    try:
        nees = float(d_a @ np.linalg.solve(cov, d_a))
    except np.linalg.LinAlgError:
        return None
    return RotationCheck(T_world_a[:3, :3] @ d_a, nees,
                         float(np.degrees(np.linalg.norm(d_a))), sigma, n, parallax)


class DeferredCheck:
    """`check_rotation` in a worker thread of its own: submitted at a keyframe, taken
    before the next frame's verdict (pipeline.py), which is when its evidence was first
    used anyway, so the figures are those of running it in line. OpenCV releases the GIL
    in the essential matrix / homography estimation, so the check overlaps the next
    frame's tracking (docs/method.md §17.3)."""

    def __init__(self) -> None:
        self._pool: ThreadPoolExecutor | None = None
        self._pending: Future | None = None

    def submit(self, *args: Any, **kwargs: Any) -> None:
        """Run check_rotation(*args, **kwargs); an earlier one not taken is dropped."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix='ekf_vo_rot')
        self._pending = self._pool.submit(check_rotation, *args, **kwargs)

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def take(self) -> RotationCheck | None:
        """The submitted check's verdict (waiting for it; what it raised is raised
        here); None without one."""
        future, self._pending = self._pending, None
        return None if future is None else future.result()

    def close(self) -> None:
        self._pending = None
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None

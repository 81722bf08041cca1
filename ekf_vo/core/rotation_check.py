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
`min_parallax_deg`). A pair whose shared tracks a homography explains about as well as
the essential matrix (a plane filling the view, or a camera orbiting what it looks at;
the model selection is the bootstrap's, after ORB-SLAM's: the homography's share of the
inliers) is ambiguous: two solutions fit a plane, and on the rendered room's walls the
essential matrix's was degrees off while its covariance said hundredths. Such a pair is
judged against each candidate (the essential matrix's rotation and those of the
homography's decompositions with the points in front) and the filter is given the one
it is closest to: the least the evidence says (docs/method.md §15.11).

The discrepancies of consecutive pairs add up (`KeyframeRotationJudge`): a filter that
is off by half a degree at every keyframe, each pair within its bound, is off by degrees
after ten, and the sum is judged against the sum of the pairs' covariances.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from . import geometry as geo
from .bootstrap import homogeneous, sampson_of_fundamental
from .map_uncertainty import relative_pose_covariance
from .orientation_only import fit_rotation

#: fewest shared inlier tracks for a verdict
MIN_POINTS = 20
#: share of the shared tracks one rotation must explain for a pair to be judged as a
#: rotation without a baseline (a translation with depth in view leaves more unexplained)
_PURE_ROTATION_SHARE = 0.9
#: a homography decomposition whose plane normal is within this of the last ambiguous
#: pair's is that plane seen again (the filter's orientation carries it to the world)
NORMAL_CONTINUITY_DEG = 15.0


@dataclass(frozen=True)
class RotationCheck:
    discrepancy_world: np.ndarray   #: (3,) filter minus two-view, world rotation vector
    cov_world: np.ndarray           #: (3,3) its covariance (two views' and the filter's)
    nees: float                     #: against the two-view covariance (3 dof)
    angle_deg: float                #: |discrepancy|
    sigma_px: float                 #: pixel noise estimated from the inliers
    n_inliers: int
    parallax_deg: float             #: median angle between the inliers' rays
    ambiguous: bool = False         #: a homography explained the tracks (candidates judged)
    #: the unit normal (world) of the plane the judged candidate sees, None: no plane
    plane_normal_world: np.ndarray | None = None
    #: every candidate the filter was weighed against: (R_ba, the rotation of b's frame
    #: from a's; True for a homography decomposition), the judged one among them
    candidates: tuple = ()


@dataclass(frozen=True)
class KeyframePairCheck:
    """One keyframe pair's check as it was judged (KeyframeRotationJudge.take): which
    pair, the filter's orientations it was handed, and the verdict (None: not judged).
    FrameResult.keyframe_pair_check carries it on the frame where it was taken, for the
    benchmarks (bench.keyframe_pairs) and for anyone tracing a verdict."""

    frame_a: int                    #: frame index of the pair's first keyframe
    frame_b: int                    #: and of its second (the newest keyframe)
    R_world_a: np.ndarray           #: the filter's orientation at a, as judged
    R_world_b: np.ndarray
    check: RotationCheck | None
    second_look: bool = False       #: the wider pair of a second look (§15.2)


def _sampson_px(E: np.ndarray, K: np.ndarray, pa: np.ndarray, pb: np.ndarray
                ) -> np.ndarray:
    """Sampson distances [px] of the pixel pairs to the epipolar geometry F = K^-T E K^-1."""
    Ki = np.linalg.inv(K)
    return np.abs(sampson_of_fundamental(Ki.T @ E @ Ki, homogeneous(pa), homogeneous(pb)))


def _normalised(K: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Rays (n,3) of IDEAL pixels px (n,2) on the normalised image plane (z = 1)."""
    Ki = np.linalg.inv(K)
    return np.column_stack((px @ Ki[:2, :2].T + Ki[:2, 2], np.ones(len(px))))


def _homography_candidates(H: np.ndarray, K: np.ndarray, pa: np.ndarray, pb: np.ndarray,
                           sigma_px: float, min_parallax_deg: float
                           ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(R_ba, 3x3 rotation covariance in frame a, unit plane normal in frame a) of each
    decomposition of H that keeps the points in front of both views (at most two: the
    planar ambiguity) and whose plane is seen with min_parallax_deg of median parallax. The covariance is the
    two-view one of that decomposition's own geometry (the plane's points at unit
    distance), plus the rays' bound on a rotation."""
    _, Rs, ts, normals = cv2.decomposeHomographyMat(H, K)
    # the visibility test takes normalised image coordinates (the normals are in the
    # camera frame), as float32 pairs
    m_a, m_b = _normalised(K, pa), _normalised(K, pb)
    keep = cv2.filterHomographyDecompByVisibleRefpoints(
        Rs, normals, m_a[:, :2].astype(np.float32).reshape(-1, 1, 2),
        m_b[:, :2].astype(np.float32).reshape(-1, 1, 2))
    rows = range(len(Rs)) if keep is None else np.asarray(keep).ravel().tolist()
    rays_cov = _bearing_rotation_covariance(K, pa, sigma_px)
    out = []
    for k in rows:
        R_ba, t_ba, n = np.asarray(Rs[k], float), np.asarray(ts[k], float).ravel(), \
            np.asarray(normals[k], float).ravel()
        depth = m_a @ n
        front = depth > 1e-9
        if np.count_nonzero(front) < MIN_POINTS:
            continue
        X_a = m_a[front] / depth[front, None]                      # on the plane n.X = 1
        T_a_b = geo.make_T(R_ba.T, -R_ba.T @ t_ba)
        if _median_parallax_deg(X_a, T_a_b[:3, 3]) < min_parallax_deg:
            continue                  # no baseline: a rotation, judged by _pure_rotation
        out.append((R_ba, rays_cov + relative_pose_covariance(
            K, np.eye(4), T_a_b, X_a, sigma_px)[3:, 3:], n / np.linalg.norm(n)))
    return out


def _median_parallax_deg(X_a: np.ndarray, centre_b_in_a: np.ndarray) -> float:
    """Median angle [deg] between the rays from view a and from view b (its centre in
    a's frame) to the points X_a (n,3)."""
    ray_a = X_a / np.linalg.norm(X_a, axis=1, keepdims=True)
    ray_b = X_a - centre_b_in_a
    ray_b /= np.linalg.norm(ray_b, axis=1, keepdims=True)
    return float(np.degrees(np.median(np.arccos(np.clip(
        np.sum(ray_a * ray_b, axis=1), -1, 1)))))


def _pure_rotation(K: np.ndarray, pa: np.ndarray, pb: np.ndarray, sigma_px: float,
                   threshold_px: float, seed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_ba, 3x3 covariance) when one rotation explains all but a few of the rays
    within threshold_px (orientation_only.fit_rotation): a rotation without a baseline,
    which a homography fits but the essential matrix cannot. Its covariance is the fit's
    plus the rotation a translation under the threshold can pass for."""
    f = 0.5 * float(K[0, 0] + K[1, 1])
    b_a, b_b = (r / np.linalg.norm(r, axis=1, keepdims=True)
                for r in (_normalised(K, pa), _normalised(K, pb)))
    fit = fit_rotation(b_a, b_b, np.sqrt(2.0) * sigma_px / f, threshold_px / f,
                       np.random.default_rng(seed))
    if fit is None or fit.inlier_share < _PURE_ROTATION_SHARE:
        return None
    # fit.cov_cur is in frame b; as a rotation vector of R_ab it is seen from a
    R_ab = fit.R_cur_ref.T
    cov_a = R_ab @ fit.cov_cur @ R_ab.T + (threshold_px / f) ** 2 * np.eye(3)
    return fit.R_cur_ref, cov_a


def _bearing_rotation_covariance(K: np.ndarray, px: np.ndarray, sigma_px: float
                                 ) -> np.ndarray:
    """3x3 covariance of a rotation fitted to the rays of pixels px seen in two views
    with pixel noise sigma_px each: (sigma^2 / f^2) 2 (sum_i (I - c_i c_i^T))^-1."""
    c = _normalised(K, px)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    info = len(c) * np.eye(3) - c.T @ c
    f = 0.5 * (K[0, 0] + K[1, 1])
    return 2.0 * (sigma_px / f) ** 2 * np.linalg.pinv(info)


def check_rotation(K: np.ndarray, ids_a: np.ndarray, px_a: np.ndarray,
                   T_world_a: np.ndarray, ids_b: np.ndarray, px_b: np.ndarray,
                   T_world_b: np.ndarray, threshold_px: float, min_parallax_deg: float,
                   max_homography_share: float, filter_cov_rot: np.ndarray | None = None,
                   seed: int = 0, plane_normal_world: np.ndarray | None = None
                   ) -> RotationCheck | None:
    """Compare the filter's relative rotation of keyframes a and b (their poses) with
    the essential matrix of the IDEAL pixels of the tracks (ids) they share. None when
    there is not enough to judge. `filter_cov_rot`: the filter's 3x3 world rotation
    covariance, taken for each keyframe's share of the relative error.

    Where a homography explains the tracks about as well as the essential matrix, the
    two-view rotation is ambiguous (module docstring): the filter is judged against the
    candidate it is closest to, among the essential matrix's and the homography's
    decompositions, so what is reported is the least the evidence says. Unless the
    plane is the one the last ambiguous pair chose (`plane_normal_world`, within
    NORMAL_CONTINUITY_DEG): a camera does not change the plane it sees from one keyframe
    to the next, while the wrong solution's normal turns with the baseline."""
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
    parallax = _median_parallax_deg(X_a, T_a_b[:3, 3])
    n = int(np.count_nonzero(inl))
    H, h_mask = cv2.findHomography(pa, pb, cv2.USAC_ACCURATE, threshold_px)
    ambiguous = H is not None and h_mask is not None and \
        np.count_nonzero(h_mask) >= max_homography_share * n
    # the essential matrix's rotation needs a baseline; a homography's, from a plane
    # seen with parallax or from a pure rotation, is judged whatever E's parallax says
    if not ambiguous and not parallax >= min_parallax_deg:
        return None
    err = _sampson_px(E, K, pa[inl], pb[inl])
    # Sampson errors are the distance to the epipolar manifold: ~ sigma per pair;
    # corrected for the 5 parameters fitted
    sigma = float(np.sqrt(np.mean(err ** 2) * n / max(n - 5, 1)))
    sigma = max(sigma, 1e-3)
    R_wa = T_world_a[:3, :3]
    candidates = []                        # (R_ba, covariance in a, world plane normal)
    if parallax >= min_parallax_deg:
        candidates.append((R_ba, relative_pose_covariance(K, np.eye(4), T_a_b, X_a,
                                                          sigma)[3:, 3:], None))
    if ambiguous:
        h_in = h_mask.ravel() > 0
        planes = [(R, cov, R_wa @ n) for R, cov, n in _homography_candidates(
            H, K, pa[h_in], pb[h_in], sigma, min_parallax_deg)]
        # |cos| of each plane's angle to the last pair's plane
        cos = [0.0 if plane_normal_world is None else abs(float(c[2] @ plane_normal_world))
               for c in planes]
        same = [c for c, k in zip(planes, cos) if k > np.cos(np.radians(NORMAL_CONTINUITY_DEG))]
        if len(same) == 1 and min(cos) < np.cos(np.radians(3 * NORMAL_CONTINUITY_DEG)):
            candidates = same
        else:
            candidates += planes
            rotation = _pure_rotation(K, pa, pb, sigma, threshold_px, seed)
            if rotation is not None:
                candidates.append((*rotation, None))
    filter_part = np.zeros((3, 3))
    if filter_cov_rot is not None:
        filter_part = 2.0 * R_wa.T @ filter_cov_rot @ R_wa
    return _closest(candidates, T_world_a[:3, :3].T @ T_world_b[:3, :3], filter_part,
                    R_wa, (sigma, n, parallax, ambiguous))


def _closest(candidates: list, R_ab_filter: np.ndarray, filter_part: np.ndarray,
             R_wa: np.ndarray, stats: tuple) -> RotationCheck | None:
    """The check against the candidate (R_ba, covariance in a, world normal) the
    filter's R_ab is closest to (smallest NEES). Its plane normal is the candidate's,
    or, for the essential matrix's, that of the plane candidate it agrees with."""
    judged = []
    for R_c, cov_c, normal in candidates:
        d = geo.quat_to_rotvec(geo.matrix_to_quat(R_ab_filter @ R_c))
        cov = cov_c + filter_part
        try:
            judged.append((float(d @ np.linalg.solve(cov, d)), d, cov, R_c, normal))
        except np.linalg.LinAlgError:
            continue
    if not judged:
        return None
    nees, d_a, cov, R_c, normal = min(judged, key=lambda j: j[0])
    if normal is None:
        twins = [c[2] for c in candidates if c[2] is not None and geo.rotation_angle_deg(
            c[0], R_c) < NORMAL_CONTINUITY_DEG / 10]
        normal = twins[0] if twins else None
    return RotationCheck(R_wa @ d_a, R_wa @ cov @ R_wa.T, nees,
                         float(np.degrees(np.linalg.norm(d_a))), *stats, normal,
                         tuple((R, n is not None) for R, _, n in candidates))


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


#: a failed keyframe pair with less median parallax [deg] is not counted until a wider
#: pair, from its first keyframe to the next one, is judged (KeyframeRotationJudge.judge)
SECOND_LOOK_PARALLAX_DEG = 1.5


class KeyframeRotationJudge:
    """The keyframes' rotation check (in its worker, DeferredCheck) and what it
    concludes. A pair beyond `max_nees` adds its discrepancy d d^T to the published
    covariance (§15.2). The pairs' discrepancies are also summed over the trailing runs
    of up to `drift_window` judged pairs of one map, and over all of them since the map
    began; the largest sum beyond `max_nees`
    against the summed covariances is a drift, and the published covariance is made to
    hold it. A drift beyond `lost_deg` (0: never) means the map no longer holds the
    camera: it is dropped, not relocalised in (docs/method.md §15.11). A pair that is
    not judged hands its first keyframe back (`span_from`): the next pair starts there,
    so that the drift over it is seen (§15.18)."""

    def __init__(self, max_nees: float, drift_window: int, lost_deg: float) -> None:
        self.max_nees = float(max_nees)
        self.lost_rad = float(np.radians(lost_deg))
        self._job = DeferredCheck()
        self._pairs: deque = deque(maxlen=max(int(drift_window), 1))
        #: every judged pair of this map: (summed discrepancy, summed covariance, pairs)
        self._total = (np.zeros(3), np.zeros((3, 3)), 0)
        self._normal: np.ndarray | None = None  #: the last judged pair's plane (world)
        self.last: RotationCheck | None = None     #: the last pair's check
        #: a failed pair with little parallax, waiting for a second look (judge)
        self._doubtful: RotationCheck | None = None
        self._longer = False            #: the submitted check is the second look
        #: why this map no longer holds the camera (a drift beyond lost_deg), or ''
        self.map_lost = ''
        #: the submitted pair's first keyframe (opaque: the caller's), and the one the
        #: next pair should start from when that pair was not judged (span_from)
        self._submitted_first: Any = None
        self.span_from: Any = None
        #: the submitted pair (frame indices and the filter's orientations), for the
        #: record `take` returns
        self._submitted_pair: tuple | None = None

    def submit(self, K: np.ndarray, ids_a: np.ndarray, px_a: np.ndarray,
               T_world_a: np.ndarray, ids_b: np.ndarray, px_b: np.ndarray,
               T_world_b: np.ndarray, *args: Any, longer: bool = False, first: Any = None,
               frames: tuple[int, int] = (-1, -1), **kwargs: Any) -> None:
        """check_rotation(K, ids_a, ..., T_world_b, *args, **kwargs) in the worker, with
        the plane of the last ambiguous pair. `longer`: the pair is the second look at a
        doubtful one (from its first keyframe to the newest). `first`: the pair's first
        keyframe, handed back as `span_from` if the pair is not judged. `frames`: the
        pair's frame indices, for the record `take` returns."""
        self._longer = bool(longer) and self._doubtful is not None
        self._submitted_first = first
        self._submitted_pair = (int(frames[0]), int(frames[1]),
                                np.array(T_world_a[:3, :3]), np.array(T_world_b[:3, :3]))
        self._job.submit(K, ids_a, px_a, T_world_a, ids_b, px_b, T_world_b, *args,
                         plane_normal_world=self._normal, **kwargs)

    @property
    def wants_second_look(self) -> bool:
        """The last pair failed with little parallax: judge the next one from that
        pair's first keyframe instead (judge)."""
        return self._doubtful is not None

    @property
    def pending(self) -> bool:
        return self._job.pending

    def reset(self) -> None:
        """A new map: its drift starts from nothing."""
        self._doubtful = None
        self._longer = False
        self._pairs.clear()
        self._total = (np.zeros(3), np.zeros((3, 3)), 0)
        self._normal = None
        self.map_lost = ''
        # (a submitted check not yet taken keeps its pair: take returns both)
        self._submitted_first = self.span_from = None

    def close(self) -> None:
        self._job.close()

    def take(self, world_cov) -> tuple[str, KeyframePairCheck | None]:
        """The submitted check's verdict (judge): the reason to be DEGRADED or '', and
        the record of the pair as checked."""
        longer, self._longer = self._longer, False
        check = self._job.take()
        # a pair not judged (too little parallax, too few tracks) leaves its drift
        # unseen: the next pair starts where it started (docs/method.md §15.18)
        self.span_from = self._submitted_first if check is None and not longer else None
        record = None if self._submitted_pair is None else \
            KeyframePairCheck(*self._submitted_pair, check, longer)
        self._submitted_pair = None
        return self.judge(check, world_cov, longer), record

    def judge(self, check: RotationCheck | None, world_cov, longer: bool = False) -> str:
        """One keyframe pair's check: its evidence, and the drift's, added to
        `world_cov` (map_uncertainty.WorldCovariance); the reason to be DEGRADED, or
        ''.

        A pair that fails with less than SECOND_LOOK_PARALLAX_DEG of parallax is not
        counted yet: the next check spans it and the next keyframe (`longer`), and that
        wider pair is judged in its place. With little parallax the two views can be
        wrong by more than their covariance says (a homography's plane at 0.5-0.8 deg:
        0.7-1.2 deg off, docs/method.md §15.4). When the wider pair cannot be judged,
        the doubtful one counts as it was."""
        reasons = []
        if longer:
            doubtful, self._doubtful = self._doubtful, None
            if check is None:
                check = doubtful
        else:
            if self._doubtful is not None:      # no wider look came: it counts as it was
                earlier, self._doubtful = self._doubtful, None
                reasons.append(self._count(earlier, world_cov))
            if (check is not None and check.nees > self.max_nees
                    and check.parallax_deg < SECOND_LOOK_PARALLAX_DEG):
                self.last, self._doubtful = check, check
                return '; '.join(r for r in reasons if r)
        self.last = check
        if check is not None:
            reasons.append(self._count(check, world_cov))
        return '; '.join(r for r in reasons if r)

    def _count(self, check: RotationCheck, world_cov) -> str:
        """A judged pair's evidence and the drift's (judge)."""
        if check.plane_normal_world is not None:
            self._normal = check.plane_normal_world
        reasons = []
        if check.nees > self.max_nees:
            world_cov.add_rotation_evidence(check.discrepancy_world)
            reasons.append(f'rotation {check.angle_deg:.2f} deg off the two-view geometry '
                           f'(NEES {check.nees:.0f})')
        self._pairs.append((check.discrepancy_world, check.cov_world))
        d_all, cov_all, n_all = self._total
        self._total = (d_all + check.discrepancy_world, cov_all + check.cov_world, n_all + 1)
        drift = self.drift()
        if drift is not None:
            d_sum, nees, n = drift
            world_cov.cover_rotation(d_sum)
            reasons.append(f'rotation drifting: {np.degrees(np.linalg.norm(d_sum)):.1f} deg '
                           f'off the two-view geometry over {n} keyframe pairs '
                           f'(NEES {nees:.0f})')
            if 0.0 < self.lost_rad < np.linalg.norm(d_sum):
                self.map_lost = f'the map drifted: {reasons[-1]}'
        world_cov.cover_rotation(self.unexplained())
        return '; '.join(reasons)

    def _runs(self) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """(summed discrepancy, summed covariance, pairs): first the run since the map
        began, then the trailing runs of two or more pairs within the window."""
        runs, d_sum, cov_sum = [self._total], np.zeros(3), np.zeros((3, 3))
        for n, (d, cov) in enumerate(reversed(self._pairs), start=1):
            d_sum, cov_sum = d_sum + d, cov_sum + cov
            if n >= 2:
                runs.append((d_sum, cov_sum, n))
        return runs

    def unexplained(self) -> np.ndarray:
        """The largest drift the noise of the window's runs does not explain, significant
        or not (the run since the map began is left out: its noise grows without bound,
        and so would the share of it taken for a drift). Under
        a drift e, E|d|^2 = |e|^2 + trace S, so |d|^2 - trace S estimates |e|^2 (a world
        rotation vector along d; zeros when no run has any)."""
        best, best_excess = np.zeros(3), 0.0
        for d_sum, cov_sum, _ in self._runs()[1:]:      # the window's runs
            norm2 = float(d_sum @ d_sum)
            if norm2 <= 0.0:
                continue
            excess = norm2 - float(np.trace(cov_sum))
            if excess > best_excess:
                best, best_excess = d_sum * np.sqrt(excess / norm2), excess
        return best

    def drift(self) -> tuple[np.ndarray, float, int] | None:
        """(summed discrepancy, its NEES, pairs) of the largest run of two or more pairs
        whose sum is beyond max_nees, among the trailing runs within the window and the
        run of every pair since the map began; None when there is none."""
        best = None
        for d_sum, cov_sum, n in self._runs():
            if n < 2:
                continue
            nees = float(d_sum @ np.linalg.solve(cov_sum, d_sum))
            if nees > self.max_nees and (
                    best is None or d_sum @ d_sum > best[0] @ best[0]):
                best = (d_sum.copy(), nees, n)
        return best

"""The local map: keyframes, and the windowed bundle adjustment run beside the frame loop.

docs/method.md §12. The pipeline hands every tracked frame's pose and observations to
`LocalMapper.consider`; a frame becomes a keyframe when the last keyframe's map points are
being lost (covisibility), or when the camera has moved or turned enough since it
(ORB-SLAM's keyframe rules, Mur-Artal et al., T-RO 2015, sec. V-E, in a simpler form).
Each new keyframe starts an adjustment of the last `ba_window_keyframes` keyframes and the
map points they see (local_ba.py) on a snapshot, in a worker process (ba_process.py),
so the frame loop goes on; the result is applied before the update of the frame
`ba_apply_after_frames` later (`harvest`), waiting for the worker only if it is not done
by then, so that the result never depends on timing (offline and live runs agree).

What an adjustment changes: the map points' positions and covariances, the window's
keyframe poses, and it culls points whose reprojection error stays large. It does not
write the filter's state: the camera follows the refined map through the next
measurements (the odometry stays continuous; docs/method.md §12.2), and with
ba_pose_feedback the newest adjusted keyframe's pose is handed to the filter as a
measurement (take_correction; pipeline.VisualOdometry._feed_back).
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import Future, wait
from dataclasses import dataclass

import numpy as np

from ..config import VoConfig
from . import ba_process
from .local_ba import WindowProblem, WindowSolution, adjust_window
from .map import LandmarkMap
from .map_uncertainty import adjusted_pose_covariance, carry_pose_covariance

logger = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A frame kept for an adjustment (this local map's, or the multi-view bootstrap's):
    its pose and the tracks it observed."""

    frame_index: int
    T_world_cam: np.ndarray | None  #: 4x4, refined by the adjustments (None: not posed yet)
    ids: np.ndarray            #: (n,) int64 track ids (ascending in the local map)
    px: np.ndarray             #: (n,2) their IDEAL pixels
    stamp_ns: int = 0
    #: world covariance (6x6) and centre of the pose when it became a keyframe: the
    #: anchor of the points an adjustment expresses relative to it (map_uncertainty.py)
    anchor: tuple | None = None
    #: the filter's pose when it became a keyframe (never refined: the rotation check
    #: judges the filter, rotation_check.py)
    T_world_cam_filter: np.ndarray | None = None
    #: information (6x6) of the last adjustment about this keyframe's pose (zeros: none)
    prior_info: np.ndarray | None = None


@dataclass
class AdjustmentStats:
    """What the adjustments did (for ~/status and the bench)."""

    n_runs: int = 0
    last_ms: float = 0.0          #: time of the last adjustment in the worker
    total_ms: float = 0.0
    max_ms: float = 0.0
    wait_ms: float = 0.0          #: time the frame loop waited for a worker, in total
    n_waits: int = 0              #: frames that had to wait
    last_points: int = 0
    last_keyframes: int = 0
    last_rms_px: float = 0.0
    n_culled: int = 0
    n_keyframes: int = 0
    n_failed: int = 0             #: adjustments that raised (numerically): skipped
    #: pose feedback (ba_pose_feedback): the last NIS against the filter, how many were
    #: applied, and how far the last one moved the filter
    feedback_last_nis: float = 0.0
    n_feedback: int = 0
    feedback_last_m: float = 0.0
    feedback_last_deg: float = 0.0

    def as_status(self) -> dict:
        """The figures ~/status reports (times in ms, rounded)."""
        return {'keyframes': self.n_keyframes, 'ba_runs': self.n_runs,
                'ba_last_ms': round(self.last_ms, 1), 'ba_max_ms': round(self.max_ms, 1),
                'ba_mean_ms': round(self.total_ms / self.n_runs, 1) if self.n_runs else 0.0,
                'ba_wait_ms_total': round(self.wait_ms, 1), 'ba_frames_waited': self.n_waits,
                'ba_last_points': self.last_points, 'ba_last_rms_px': round(self.last_rms_px, 2),
                'ba_culled': self.n_culled, 'ba_failed': self.n_failed,
                'ba_feedback_last_nis': round(self.feedback_last_nis, 1),
                'ba_feedbacks': self.n_feedback,
                'ba_feedback_last_m': round(self.feedback_last_m, 4),
                'ba_feedback_last_deg': round(self.feedback_last_deg, 3)}


@dataclass
class _Pending:
    future: Future
    apply_at: int                 #: frame index at which the result is applied
    keyframes: list               #: the window's Keyframe objects (poses written back)
    point_ids: np.ndarray
    gauge: int                    #: the newest of the keyframes that fix the gauge


class LocalMapper:
    """Keyframe selection and the adjustment worker of one VisualOdometry."""

    def __init__(self, cfg: VoConfig, K: np.ndarray) -> None:
        self.cfg = cfg
        self.K = np.asarray(K, float)
        ba_process.start()      # ahead of the first adjustment (~0.3 s to start)
        self.stats = AdjustmentStats()
        self.keyframes: list[Keyframe] = []
        self._pending: _Pending | None = None
        #: the last applied adjustment's word on its newest adjusted keyframe, for the
        #: filter (take_correction); None: none since the last take
        self._correction: PoseCorrection | None = None

    def reset(self) -> None:
        """Forget the keyframes; a running adjustment is left to finish and ignored."""
        self.keyframes = []
        self._pending = None
        self._correction = None

    def take_correction(self) -> 'PoseCorrection | None':
        """The newest adjusted keyframe's pose from the last applied adjustment, once."""
        corr, self._correction = self._correction, None
        return corr

    def close(self, wait: bool = True) -> None:
        """Drop a running adjustment's result (it finishes on the shared worker; `wait`:
        wait for it to)."""
        pend, self._pending = self._pending, None
        if wait and pend is not None:
            try:
                pend.future.result()
            except Exception:  # noqa: BLE001 - its result is dropped either way
                pass

    # ------------------------------------------------------------------ keyframes
    def consider(self, frame_index: int, T_world_cam: np.ndarray, ids: np.ndarray,
                 px_ideal: np.ndarray, has_point: np.ndarray, landmarks: LandmarkMap,
                 anchor: tuple | None = None) -> bool:
        """Make this frame a keyframe if the rules say so, and start an adjustment.
        ids/px_ideal: every track of the frame; has_point: those with a map point;
        anchor: the pose's world (covariance, centre)."""
        if not self._is_keyframe(T_world_cam, ids[has_point], landmarks):
            return False
        self.add_keyframe(frame_index, T_world_cam, ids, px_ideal, anchor)
        if self._pending is None and len(self.keyframes) >= 2:
            self._launch(frame_index, landmarks)
        return True

    def add_keyframe(self, frame_index: int, T_world_cam: np.ndarray, ids: np.ndarray,
                     px_ideal: np.ndarray, anchor: tuple | None = None) -> None:
        """Append a keyframe (the bootstrap's frames enter this way, without the rules)."""
        order = np.argsort(ids, kind='stable')
        self.keyframes.append(Keyframe(frame_index, np.array(T_world_cam, float),
                                       np.asarray(ids, np.int64)[order],
                                       np.asarray(px_ideal, float)[order],
                                       anchor=anchor,
                                       T_world_cam_filter=np.array(T_world_cam, float)))
        self.stats.n_keyframes += 1
        # keep what the next windows can use (older keyframes are never adjusted again)
        del self.keyframes[:-self.cfg.ba_window_keyframes]

    def _is_keyframe(self, T_world_cam: np.ndarray, map_ids: np.ndarray,
                     landmarks: LandmarkMap) -> bool:
        c = self.cfg
        if not self.keyframes:
            return True
        last = self.keyframes[-1]
        last_map = last.ids[landmarks.contains(last.ids)] if len(last.ids) else last.ids
        if len(last_map) and \
                len(np.intersect1d(last_map, map_ids)) < c.keyframe_min_covisibility * \
                len(last_map):
            return True
        R_rel = last.T_world_cam[:3, :3].T @ T_world_cam[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(R_rel) - 1) / 2, -1, 1)))
        if angle > c.keyframe_max_rotation_deg:
            return True
        if len(map_ids):
            _, X = landmarks.lookup(map_ids)
            depth = np.median((X - T_world_cam[:3, 3]) @ T_world_cam[:3, 2])
            moved = np.linalg.norm(T_world_cam[:3, 3] - last.T_world_cam[:3, 3])
            if depth > 0 and moved > c.keyframe_max_baseline_ratio * depth:
                return True
        return False

    # ------------------------------------------------------------------ adjustment
    def _problem(self, landmarks: LandmarkMap
                 ) -> tuple[WindowProblem, np.ndarray, int] | None:
        """The window's problem: map points seen by at least two of its keyframes; and the
        index of the newest keyframe that fixes its gauge."""
        kfs = self.keyframes
        seen = [kf.ids[landmarks.contains(kf.ids)] for kf in kfs]
        all_ids, counts = np.unique(np.concatenate(seen), return_counts=True)
        point_ids = all_ids[counts >= 2]
        if len(point_ids) == 0:
            return None
        cam_idx, pt_idx, px = [], [], []
        for k, kf in enumerate(kfs):
            common, i_kf, i_pt = np.intersect1d(kf.ids, point_ids, assume_unique=True,
                                                return_indices=True)
            cam_idx.append(np.full(len(common), k))
            pt_idx.append(i_pt)
            px.append(kf.px[i_kf])
        _, X = landmarks.lookup(point_ids)
        cam_idx, pt_idx = np.concatenate(cam_idx), np.concatenate(pt_idx)
        px = np.concatenate(px)
        ok = self._wide_enough(X, cam_idx, pt_idx)
        keep = ok[pt_idx]
        remap = -np.ones(len(point_ids), np.int64)
        remap[ok] = np.arange(int(ok.sum()))
        point_ids, X = point_ids[ok], X[ok]
        cam_idx, pt_idx, px = cam_idx[keep], remap[pt_idx[keep]], px[keep]
        if len(point_ids) == 0:
            return None
        gauge = self._gauge(cam_idx, len(kfs))
        if gauge is None:
            return None
        fixed, gauge_index = gauge
        prior = None
        if self.cfg.ba_pose_prior_weight > 0:
            prior = np.stack([kf.prior_info if kf.prior_info is not None else np.zeros((6, 6))
                              for kf in kfs])
        problem = WindowProblem(np.stack([kf.T_world_cam for kf in kfs]), fixed, X.copy(),
                                cam_idx, pt_idx, px, prior)
        return problem, point_ids, gauge_index

    def _gauge(self, cam_idx: np.ndarray, n_keyframes: int
               ) -> tuple[np.ndarray, int] | None:
        """Which keyframes are held fixed, and the newest of those that fix the gauge.

        The gauge (position, orientation and scale of a monocular window) is fixed by the
        oldest ba_fixed_keyframes keyframes that see at least ba_min_keyframe_points of
        the window's points; the keyframes before them are held too. A keyframe
        that sees fewer is held as well: it can neither fix the gauge nor be estimated.
        After a turn in place the oldest keyframes may see none of the points the window
        adjusts; fixing them anyway left the window free to slide and scale, and its
        marginal covariances (10^8 map units^2) entered the map (docs/method.md §12.2).
        None: fewer than ba_fixed_keyframes + 1 keyframes see enough points."""
        c = self.cfg
        seen = np.bincount(cam_idx, minlength=n_keyframes) >= c.ba_min_keyframe_points
        order = np.flatnonzero(seen)
        if len(order) <= c.ba_fixed_keyframes:
            return None
        gauge_index = int(order[c.ba_fixed_keyframes - 1])
        fixed = ~seen
        fixed[:gauge_index + 1] = True
        return fixed, gauge_index

    def _wide_enough(self, X: np.ndarray, cam_idx: np.ndarray, pt_idx: np.ndarray
                     ) -> np.ndarray:
        """Points whose rays from their first and last keyframe of the window span
        ba_min_parallax_deg: below the triangulation gate a point's depth is noise. At
        2 deg the young points were left as triangulated and a camera circling a scene
        drifted; at 1 deg the window alone drifted KITTI 06's scale, which the keyframe
        pose prior holds (docs/method.md §12.4, §15.8)."""
        C = np.stack([kf.T_world_cam[:3, 3] for kf in self.keyframes])
        first = np.full(len(X), len(C))
        last = np.full(len(X), -1)
        np.minimum.at(first, pt_idx, cam_idx)
        np.maximum.at(last, pt_idx, cam_idx)
        a, b = X - C[first], X - C[last]
        norms = np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
        angle = np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1) / norms, -1, 1)))
        return angle >= self.cfg.ba_min_parallax_deg

    def _launch(self, frame_index: int, landmarks: LandmarkMap) -> None:
        built = self._problem(landmarks)
        if built is None:
            return
        problem, point_ids, gauge_index = built
        c = self.cfg
        future = ba_process.submit(adjust_window, problem, self.K, c.pixel_sigma_px,
                                   c.ba_huber_px, c.ba_max_iterations)
        self._pending = _Pending(future, frame_index + c.ba_apply_after_frames,
                                 list(self.keyframes), point_ids, gauge_index)

    def harvest(self, frame_index: int, landmarks: LandmarkMap) -> np.ndarray:
        """Apply a finished adjustment that is due (waiting for it if needed).
        Returns the ids of the culled points (empty when nothing was applied)."""
        pend = self._pending
        if pend is None or frame_index < pend.apply_at:
            return np.zeros(0, np.int64)
        if not pend.future.done():
            t = time.perf_counter()
            wait([pend.future])           # a failed job raises below, not here
            self.stats.wait_ms += (time.perf_counter() - t) * 1e3
            self.stats.n_waits += 1
        self._pending = None
        try:
            sol: WindowSolution = pend.future.result()
        except (np.linalg.LinAlgError, FloatingPointError, ValueError,
                ba_process.WorkerGone) as exc:
            # a numerically broken window, or one whose worker process died, is skipped:
            # the map stays as it was
            self.stats.n_failed += 1
            logger.warning('local map: adjustment skipped (%s); %d so far', exc,
                           self.stats.n_failed)
            return np.zeros(0, np.int64)
        return self._apply(sol, pend, landmarks)

    def _apply(self, sol: WindowSolution, pend: _Pending, landmarks: LandmarkMap
               ) -> np.ndarray:
        c = self.cfg
        for j, (kf, T) in enumerate(zip(pend.keyframes, sol.T_world_cam)):
            kf.T_world_cam = T
            if c.ba_pose_prior_weight > 0 and sol.T_cov is not None and np.any(sol.T_cov[j]):
                # what this window said about the pose, kept for the next (§12.2)
                kf.prior_info = c.ba_pose_prior_weight * np.linalg.pinv(sol.T_cov[j])
        # a point whose median error over its keyframes stays large is wrong: cull it
        n = len(pend.point_ids)
        bad = ~(sol.point_median_err_px <= c.ba_outlier_px)
        culled = pend.point_ids[bad]
        landmarks.remove(culled)
        # the refined points are now relative to the window's fixed keyframes: they take
        # the newest fixed one's anchor (docs/method.md §14)
        gauge = pend.keyframes[pend.gauge]
        landmarks.refine(pend.point_ids[~bad], sol.X_world[~bad], sol.X_cov[~bad],
                         gauge.anchor)
        self._anchor_adjusted_keyframes(sol, pend.keyframes, gauge)
        self._correction = self._newest_correction(sol, pend.keyframes)
        s = self.stats
        s.n_runs += 1
        s.last_ms = sol.elapsed_ms
        s.total_ms += sol.elapsed_ms
        s.max_ms = max(s.max_ms, sol.elapsed_ms)
        s.last_points, s.last_keyframes = n, len(pend.keyframes)
        s.last_rms_px = sol.rms_after_px
        s.n_culled += len(culled)
        return culled

    def _anchor_adjusted_keyframes(self, sol: WindowSolution, keyframes: list,
                                   gauge: Keyframe) -> None:
        """A free keyframe's pose is now the adjustment's. Its world error is at most
        the gauge keyframe's (that anchor) plus the adjustment's marginal covariance
        of the pose relative to the fixed keyframes, at the window's own pixel noise
        where that is above the nominal (_variance_factor). Its anchor so far, the
        filter's published covariance when it became a keyframe, bounds it too: the
        adjusted pose is at least as good as the filter's (the window starts from it
        and keeps what earlier windows said as a prior). The smaller bound (by the
        rotation's variance) is kept, and becomes the anchor of the points a later
        window adjusts relative to this keyframe (docs/method.md §14.2).

        Before, that anchor was always the filter's: each keyframe handed on the
        filter's error at the moment it was made, inflated by the health checks, and
        KITTI 06's published rotation was over-cautious (NEES median 0.47, §15.4).
        Always the window's was worse on the orbit and the demo: its marginal, from
        six keyframes' observations alone, is looser there than what the filter knew
        from every frame and its motion model."""
        if sol.T_cov is None or gauge.anchor is None:
            return
        factor = _variance_factor(sol.err_after_px, self.cfg.pixel_sigma_px)
        g_cov, g_c = gauge.anchor
        for kf, T, C in zip(keyframes, sol.T_world_cam, sol.T_cov):
            if not np.any(C):                   # a fixed keyframe
                continue
            c = T[:3, 3].copy()
            bound = carry_pose_covariance(np.asarray(g_cov)[None], g_c, c)[0] + \
                factor * adjusted_pose_covariance(T, C)
            if kf.anchor is not None:
                held = carry_pose_covariance(np.asarray(kf.anchor[0])[None],
                                             kf.anchor[1], c)[0]
                if np.trace(held[3:, 3:]) <= np.trace(bound[3:, 3:]):
                    continue
            kf.anchor = (bound, c)

    def _newest_correction(self, sol: WindowSolution, keyframes: list
                           ) -> 'PoseCorrection | None':
        """The newest keyframe the adjustment moved: its adjusted pose, the filter's pose
        when it became a keyframe, and the adjustment's covariance of the pose relative
        to the window's fixed keyframes (at the window's own pixel noise). Relative, not
        world: the fixed keyframes are the filter's own poses, so the difference between
        the two poses carries none of their error (docs/method.md §12.2)."""
        if sol.T_cov is None:
            return None
        factor = _variance_factor(sol.err_after_px, self.cfg.pixel_sigma_px)
        for kf, T, C in zip(reversed(keyframes), sol.T_world_cam[::-1], sol.T_cov[::-1]):
            if np.any(C) and kf.T_world_cam_filter is not None:
                return PoseCorrection(kf.frame_index, np.array(T, float),
                                      kf.T_world_cam_filter.copy(),
                                      factor * adjusted_pose_covariance(T, C))
        return None


@dataclass
class PoseCorrection:
    """An adjustment's pose of a keyframe beside the filter's (LocalMapper.take_correction)."""

    frame_index: int
    T_world_cam_adjusted: np.ndarray   #: 4x4
    T_world_cam_filter: np.ndarray     #: 4x4, the filter's when it became a keyframe
    cov_relative: np.ndarray           #: 6x6 (position, world rotation vector)


#: median of a chi-square with 2 dof (2 ln 2): |e|^2 / sigma^2 of a pixel residual
_CHI2_2DOF_MEDIAN = 2.0 * np.log(2.0)


def _variance_factor(err_px: np.ndarray, sigma_px: float) -> float:
    """A window's a-posteriori variance factor from its observations' errors [px]
    after the adjustment, robust (the median squared error against the pixel noise
    sigma_px it was solved with), never below 1: the nominal pixel noise is a floor,
    never lowered from the residuals."""
    e2 = (np.asarray(err_px, float) / sigma_px) ** 2
    if len(e2) == 0:
        return 1.0
    return max(1.0, float(np.median(e2)) / _CHI2_2DOF_MEDIAN)

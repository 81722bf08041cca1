"""Per-frame visual odometry pipeline: bootstrap, EKF tracking, map growth, loss handling.

docs/method.md §1 and §7, step by step, per frame:
  INITIALISING: keep a reference frame; try the two-view bootstrap against each new frame
                (essential matrix + triangulation) until one has enough parallax and
                inliers; the EKF starts at the second frame's pose with the velocity of
                the pair (docs/method.md §3.6).
  TRACKING:     predict (constant velocity, real dt) -> track features with the predicted
                landmark pixels as the KLT prior -> robust EKF update with the fixed map
                points (1-point RANSAC) -> triangulate tracks with enough parallax between
                their first observation and now, with the EKF poses -> output.
  LOST:         too many failed frames or a covariance blow-up: drop the map and
                re-bootstrap, attaching the new map to the last good pose (odom continuity)
                with the scale carried over from the last velocity.
Speaks numpy arrays, integer nanosecond stamps and named frames; no ROS types.
"""
from __future__ import annotations

import enum
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import VoConfig
from . import geometry as geo
from .bootstrap import H_OVER_E_RATIO, TwoViewBootstrap
from .camera import PinholeCamera
from .ekf import POS, VEL, CameraEKF, FilterError
from .estimators import FrameMatches, make_estimator
from .features import FeatureTracker, Tracks
from .health import Health, HealthMonitor
from .local_map import LocalMapper
from .map import LandmarkMap
from .map_growth import MapGrowth
from .map_uncertainty import WorldCovariance
from .multiview import MultiViewBootstrap
from .noise_model import NoiseSettings, learn_from_update, map_measurement_sigmas
from .refind import MapPointFinder
from .rotation_check import check_rotation
from .point_filter import PointFilter

logger = logging.getLogger(__name__)

#: smallest variance (m^2, rad^2) of a published pose: a zero covariance would read as
#: infinite confidence to robot_localization (docs/ros.md)
MIN_VARIANCE = 1e-9


class TrackingState(enum.Enum):
    INITIALISING = 'initialising'
    TRACKING = 'tracking'
    LOST = 'lost'


@dataclass
class FrameResult:
    """What the pipeline says about one frame. Pose fields are None unless `ok`."""

    stamp_ns: int
    state: TrackingState
    ok: bool = False                        #: a pose worth publishing
    T_world_cam: np.ndarray | None = None   #: 4x4 camera optical frame -> world
    pose_cov: np.ndarray | None = None      #: 6x6 (position, world rotation vector)
    twist_cam: np.ndarray | None = None     #: (6,) v^C [m/s], w^C [rad/s], camera frame
    twist_cov: np.ndarray | None = None     #: 6x6
    n_tracks: int = 0
    n_matches: int = 0                      #: tracks with a landmark used in the update
    n_inliers: int = 0
    n_new_points: int = 0
    n_found_again: int = 0                  #: map points found again (tracks from now)
    nis_per_dof: float = 0.0               #: normalised innovation squared / (2 n)
    map_size: int = 0
    bootstrapped: bool = False              #: this frame completed a (re-)bootstrap
    #: online checks of a tracked frame (health.py): 'ok', 'degraded' or 'lost', and why
    health: str = ''
    health_reason: str = ''
    variance_factor: float = 1.0            #: windowed NIS / dof
    found_share: float = 1.0                #: inliers / map points the prior put in view
    message: str = ''                       #: why not ok / what happened
    timings_ms: dict = field(default_factory=dict)
    track_ids: np.ndarray | None = None     #: (n,) for debug drawing
    track_px: np.ndarray | None = None      #: (n,2) raw pixels
    track_inlier: np.ndarray | None = None  #: (n,) bool, used as an inlier this frame
    track_has_point: np.ndarray | None = None


@dataclass
class _Reference:
    """The first frame of a bootstrap pair."""

    stamp_ns: int
    frame_index: int
    ids: np.ndarray
    px_ideal: np.ndarray
    T_world_cam: np.ndarray | None  # known pose (ground-truth bootstrap) if given


class VisualOdometry:
    """Monocular VO with the hybrid camera-only EKF. One instance per camera."""

    def __init__(self, cfg: VoConfig, camera: PinholeCamera, seed: int = 0) -> None:
        self.cfg = cfg.validate()
        self.camera = camera
        self.tracker = FeatureTracker(cfg)
        self.bootstrapper = TwoViewBootstrap(cfg, camera.K)
        self.multiview = MultiViewBootstrap(cfg, camera.K) \
            if cfg.bootstrap == 'multi_view' else None
        self.ekf = CameraEKF(camera.K)
        self.map = LandmarkMap(cfg.max_map_points, cfg.cull_after_misses)
        # keyframes + windowed adjustment (docs/method.md §12); None = points never refined
        self.local_map = LocalMapper(cfg, camera.K) if cfg.local_map else None
        self._noise = NoiseSettings.from_config(cfg)
        # the map's error in the published covariance (docs/method.md §14)
        self.world_cov = WorldCovariance(cfg.map_in_covariance, camera.K, cfg.pixel_sigma_px)
        # map points found again by descriptor (docs/method.md §12.5); None = off
        self.finder = MapPointFinder(cfg) if cfg.local_map and cfg.refind_map_points \
            else None
        self.rng = np.random.default_rng(seed)
        self.growth = MapGrowth(cfg, camera)        # triangulation candidates (§7.3)
        self.health = HealthMonitor(cfg)            # online consistency checks (§15)
        # in-filter map refinement (docs/method.md §8); None = the hybrid default
        self.points: PointFilter | None = None
        if cfg.map_refinement == 'filter' and cfg.estimator != 'epnp':
            self.points = PointFilter(cfg, camera.K)
        self.estimator = make_estimator(cfg, self.ekf, self.points)
        self.frame_index = -1
        self.n_resets = 0
        self._anchor_T_world_cam = np.eye(4)   # where a new map is attached
        self._anchor_speed = None              # m/s carried over a re-bootstrap
        self._reset_state()

    # ------------------------------------------------------------------ control
    def _reset_state(self) -> None:
        self.state = TrackingState.INITIALISING
        self.tracker.reset()
        self.map.clear()
        if self.local_map is not None:
            self.local_map.reset()
        self._ref: _Reference | None = None
        self._last_stamp_ns: int | None = None
        self._failed_frames = 0
        self.growth.reset()
        self.health.reset()
        self._filter_rejected: set[int] = set()   # left the point filter unconverged
        if self.points is not None:
            self.points.clear()
        if self.multiview is not None:
            self.multiview.reset()

    def reset(self, reason: str = 'requested') -> None:
        """Drop the map and re-bootstrap; keep the world frame at the last good pose."""
        if self.state == TrackingState.TRACKING:
            self._anchor_T_world_cam = self.ekf.T_world_cam
            self._anchor_speed = float(np.linalg.norm(self.ekf.x[VEL]))
            self.world_cov.carry(self.ekf.pose_covariance(), self.ekf.x[POS])
        logger.info('VO reset: %s', reason)
        self.n_resets += 1
        self._reset_state()

    # ------------------------------------------------------------------ main entry
    def process(self, gray: np.ndarray, stamp_ns: int,
                known_T_world_cam: np.ndarray | None = None) -> FrameResult:
        """Process one grey image (uint8 HxW, the camera's size) taken at `stamp_ns`
        (int nanoseconds, increasing): stream.VoStream checks both before calling.

        `known_T_world_cam` is only for the papers' ground-truth bootstrap (docs/method.md §2.3:
        "the first two ground-truth poses fix the scale"); the pipeline never reads it
        once tracking."""
        t0 = time.perf_counter()
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None and self.state == TrackingState.TRACKING and \
                (stamp_ns - self._last_stamp_ns) * 1e-9 > self.cfg.max_dt_s:
            self.reset(f'gap of {(stamp_ns - self._last_stamp_ns) * 1e-9:.2f} s')
        self.frame_index += 1
        if self.state == TrackingState.TRACKING:
            result = self._track(gray, stamp_ns)
        elif self.multiview is not None:
            result = self._initialise_multi_view(gray, stamp_ns, known_T_world_cam)
        else:
            result = self._initialise(gray, stamp_ns, known_T_world_cam)
        self._last_stamp_ns = stamp_ns
        result.map_size = len(self.map)
        result.timings_ms['total'] = (time.perf_counter() - t0) * 1e3
        return result

    # ------------------------------------------------------------------ bootstrap
    def _track_initialising(self, gray: np.ndarray, stamp_ns: int
                            ) -> tuple[Tracks, np.ndarray, FrameResult]:
        """Front end of a frame before tracking: tracks, their ideal pixels, a result."""
        t = time.perf_counter()
        tracks = self.tracker.track(gray)
        timings = {'track': (time.perf_counter() - t) * 1e3}
        px = self.camera.undistort(tracks.px)
        res = FrameResult(stamp_ns, TrackingState.INITIALISING, n_tracks=len(tracks),
                          timings_ms=timings, track_ids=tracks.ids, track_px=tracks.px)
        return tracks, px, res

    def _initialise(self, gray: np.ndarray, stamp_ns: int,
                    known_T: np.ndarray | None) -> FrameResult:
        tracks, px, res = self._track_initialising(gray, stamp_ns)
        timings = res.timings_ms
        ref = self._ref
        too_old = ref is not None and self.frame_index - ref.frame_index > \
            self.cfg.bootstrap_max_frames
        n_common = 0 if ref is None else len(np.intersect1d(ref.ids, tracks.ids))
        if ref is None or too_old or n_common < self.cfg.bootstrap_min_inliers:
            if len(tracks) >= self.cfg.bootstrap_min_inliers:
                self._ref = _Reference(stamp_ns, self.frame_index, tracks.ids.copy(),
                                       px.copy(), known_T)
                res.message = 'bootstrap: new reference frame'
            else:
                res.message = f'bootstrap: only {len(tracks)} features'
            return res

        t = time.perf_counter()
        if ref.T_world_cam is not None and known_T is not None:
            boot = self.bootstrapper.from_known_poses(
                geo.invert_T(ref.T_world_cam), geo.invert_T(known_T),
                ref.ids, ref.px_ideal, tracks.ids, px)
            T_world_ref, T_world_cur = ref.T_world_cam, known_T
            X_world = getattr(boot, 'X_world', None)
        else:
            baseline = None
            if self._anchor_speed is not None and self._anchor_speed > 0:
                # carry the scale over a re-bootstrap: distance = speed * elapsed time
                baseline = self._anchor_speed * (stamp_ns - ref.stamp_ns) * 1e-9
            boot = self.bootstrapper.try_pair(ref.ids, ref.px_ideal, tracks.ids, px,
                                              baseline=baseline)
            if boot.ok:
                T_world_ref = self._anchor_T_world_cam
                T_world_cur = T_world_ref @ geo.invert_T(boot.T_cur_ref)
                X_world = geo.transform_points(T_world_ref, boot.X_ref)
        timings['bootstrap'] = (time.perf_counter() - t) * 1e3
        if not boot.ok:
            res.message = f'bootstrap refused: {boot.reason}'
            return res

        self._start_tracking(res, gray, tracks, px, boot.point_ids, X_world, T_world_ref,
                             T_world_cur, (stamp_ns - ref.stamp_ns) * 1e-9,
                             [(ref.frame_index, ref.ids, ref.px_ideal, T_world_ref)])
        res.message = (f'bootstrapped: {boot.n_inliers} points, parallax '
                       f'{boot.median_parallax_deg:.1f} deg')
        return res

    def _start_tracking(self, res: FrameResult, gray: np.ndarray, tracks: Tracks,
                        px: np.ndarray, point_ids: np.ndarray, X_world: np.ndarray,
                        T_world_prev: np.ndarray, T_world_cur: np.ndarray, dt: float,
                        sources: list) -> None:
        """Start tracking (docs/method.md §3.6) on the image `gray`: the map, the pose of
        the current (last bootstrap) frame, velocities from the difference of the last two bootstrap
        poses `dt` seconds apart. `sources`: earlier bootstrap frames (frame index, ids,
        ideal px, T_world_cam), oldest first, from which tracks without a point become
        triangulation candidates (wider baseline than from now)."""
        anchor = self.world_cov.bootstrap_anchor(sources[0][3], T_world_cur, X_world)
        self.map.add(point_ids, X_world, self.frame_index,
                     cov=self.growth.two_view_covariances(X_world, sources[0][3], T_world_cur),
                     anchor=anchor)
        dt = max(dt, 1e-6)
        v_world = (T_world_cur[:3, 3] - T_world_prev[:3, 3]) / dt
        R_rel = T_world_prev[:3, :3].T @ T_world_cur[:3, :3]
        w_cam = geo.quat_to_rotvec(geo.matrix_to_quat(R_rel)) / dt
        c = self.cfg
        self.ekf.initialise(T_world_cur, v_world, w_cam, c.init_pose_sigma,
                            c.init_velocity_sigma, c.init_angular_velocity_sigma)
        self._published_cov = self.ekf.pose_covariance() + anchor[0]
        self._inflation = 1.0
        self.world_cov.last = (self._published_cov, T_world_cur[:3, 3].copy())
        self.state = TrackingState.TRACKING
        self._failed_frames = 0
        for f, _, _, T in sources:
            self.growth.remember_pose(f, T)
        self.growth.remember_pose(self.frame_index, T_world_cur)
        rows = [{int(i): k for k, i in enumerate(ids)} for _, ids, _, _ in sources]
        has_point = self.map.contains(tracks.ids)
        for k in np.flatnonzero(~has_point):
            tid = int(tracks.ids[k])
            for (f, _, src_px, T), row in zip(sources, rows):
                if tid in row:
                    self.growth.add(tid, f, src_px[row[tid]], T)
                    break
            else:
                self.growth.add(tid, self.frame_index, px[k], T_world_cur)
        if self.local_map is not None:
            for k, (f, ids, src_px, T) in enumerate(sources):
                self.local_map.add_keyframe(f, T, ids, src_px, anchor if k else
                                            self.world_cov.origin_anchor(T))
            self.local_map.add_keyframe(self.frame_index, T_world_cur, tracks.ids, px,
                                        anchor)
        if self.finder is not None:
            self.finder.describe(gray, tracks, self.map)
        res.bootstrapped = True
        res.health = 'ok'
        self._fill_output(res, tracks, has_point, has_point)

    def _initialise_multi_view(self, gray: np.ndarray, stamp_ns: int,
                               known_T: np.ndarray | None) -> FrameResult:
        """`bootstrap: multi_view` (multiview.py): keyframes, PnP, bundle adjustment.
        Frames posed by PnP while the keyframes are collected are published."""
        tracks, px, res = self._track_initialising(gray, stamp_ns)
        timings = res.timings_ms
        mv = self.multiview
        baseline = None
        if self._anchor_speed is not None and self._anchor_speed > 0 and mv.keyframes:
            baseline = self._anchor_speed * (stamp_ns - mv.keyframes[0].stamp_ns) * 1e-9
        t = time.perf_counter()
        step = mv.step(self.frame_index, stamp_ns, tracks.ids, px, known_T,
                       self._anchor_T_world_cam, baseline)
        timings['bootstrap'] = (time.perf_counter() - t) * 1e3
        res.message = step.message
        if step.status != 'done':
            if step.T_world_cam is not None and step.pose_cov is not None:
                # a PnP pose of the collection phase: published with its own covariance,
                # no velocity estimate yet (twist zero, with the prior's uncertainty)
                c = self.cfg
                res.ok = bool(np.all(np.isfinite(step.pose_cov)))
                res.T_world_cam = step.T_world_cam
                res.pose_cov = step.pose_cov + np.eye(6) * MIN_VARIANCE
                res.twist_cam = np.zeros(6)
                res.twist_cov = np.diag([c.init_velocity_sigma ** 2] * 3 +
                                        [c.init_angular_velocity_sigma ** 2] * 3)
            return res
        kfs = step.keyframes
        self._start_tracking(res, gray, tracks, px, step.point_ids, step.X_world,
                             kfs[-2].T_world_cam, kfs[-1].T_world_cam,
                             (kfs[-1].stamp_ns - kfs[-2].stamp_ns) * 1e-9,
                             [(kf.frame_index, kf.ids, kf.px, kf.T_world_cam)
                              for kf in kfs[:-1]])
        res.message = step.message
        return res

    # ------------------------------------------------------------------ tracking
    def _track(self, gray: np.ndarray, stamp_ns: int) -> FrameResult:
        c = self.cfg
        timings = {}
        dt = (stamp_ns - self._last_stamp_ns) * 1e-9
        if not dt > 0:
            dt = c.default_dt_s

        t = time.perf_counter()
        if self.local_map is not None:
            culled = self.local_map.harvest(self.frame_index, self.map)
            self.growth.banned.update(int(i) for i in culled)
        timings['local_map'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        self.estimator.predict(dt)
        predicted = self._predicted_pixels()
        n_in_view = self._map_points_in_view()
        timings['predict'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        tracks = self.tracker.track(gray, predicted)
        px = self.camera.undistort(tracks.px)
        timings['track'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        has_point, X = self.map.lookup(tracks.ids)
        rows = np.flatnonzero(has_point)
        if len(rows) > c.max_update_points:
            keep = np.sort(self.rng.choice(len(rows), c.max_update_points, replace=False))
            rows, X = rows[keep], X[keep]
        res = FrameResult(stamp_ns, TrackingState.TRACKING, n_tracks=len(tracks),
                          n_matches=len(rows), timings_ms=timings)
        sigma = map_measurement_sigmas(self.cfg, self._noise, self.map, tracks.ids[rows],
                                       X, self.ekf.T_world_cam, self.camera.K)
        try:
            inlier_rows = self._update(tracks, px, rows, X, sigma)
        except (FilterError, np.linalg.LinAlgError) as exc:
            self.reset(f'filter failure: {exc}')
            res.state, res.message = self.state, f'lost: {exc}'
            return res
        timings['update'] = (time.perf_counter() - t) * 1e3
        res.n_inliers = len(inlier_rows)

        # ---- tracking quality, and the published covariance (docs/method.md §14-15)
        n_found = res.n_inliers / max(len(rows), 1) * np.count_nonzero(has_point)
        if self._judge(res, n_found, n_in_view):
            return res
        mi = self._map_inliers
        self._published_cov = self.world_cov.compose(
            self.ekf.pose_covariance(), self.ekf.T_world_cam, self.map, tracks.ids[rows][mi],
            X[mi], None if sigma is None else sigma[mi], self._inflation,
            remember=self._failed_frames == 0)

        # ---- map growth, keyframes
        t = time.perf_counter()
        inlier_mask = np.zeros(len(tracks), bool)
        inlier_mask[inlier_rows] = True
        res.n_new_points += self._after_update(gray, tracks, px, rows, X, has_point,
                                               inlier_mask)
        timings['map'] = (time.perf_counter() - t) * 1e3
        res.ok = self._failed_frames == 0
        self._fill_output(res, tracks, has_point, inlier_mask)
        if self.finder is not None:
            t = time.perf_counter()
            found = self.finder.find_again(gray, tracks, self.map, self.ekf, self.camera,
                                           self.tracker, self.rng)
            res.n_found_again = len(found)
            self._prev_ids = np.union1d(self._prev_ids, found)
            timings['refind'] = (time.perf_counter() - t) * 1e3
        return res

    def _judge(self, res: FrameResult, n_found: float, n_in_view: int) -> bool:
        """Failed frames and loss (docs/method.md §7.4), then the online consistency
        checks (health.py, §15) that may inflate the published covariance. True when
        tracking was lost (the pipeline has reset)."""
        c = self.cfg
        pos_sigma = float(np.sqrt(np.max(np.diag(self.ekf.P)[POS])))
        upd = self.ekf.last_update
        nis_per_dof = upd.nis / (2 * upd.n_used) if upd.n_used else 0.0
        res.nis_per_dof = nis_per_dof
        if res.n_inliers < c.min_tracking_inliers:
            self._failed_frames += 1
            res.message = f'only {res.n_inliers} inliers'
        elif nis_per_dof > c.max_nis_per_dof:
            # the innovations disagree with the filter's own covariance: inconsistent
            self._failed_frames += 1
            res.message = f'innovation out of bounds (NIS per dof {nis_per_dof:.1f})'
        else:
            self._failed_frames = 0
        if self._failed_frames >= c.max_failed_frames or pos_sigma > c.max_position_sigma_m:
            why = res.message or f'position sigma {pos_sigma:.2f} m'
            self.reset(f'tracking lost ({why})')
            res.state, res.message = self.state, f'lost: {why}'
            res.health, res.health_reason = Health.LOST.value, why
            return True
        report = self.health.assess(upd.nis, 2 * upd.n_used, n_found, n_in_view)
        self._inflation = report.inflation
        res.health, res.health_reason = report.status.value, report.reason
        res.variance_factor, res.found_share = report.variance_factor, report.found_share
        return False

    def _check_rotation(self) -> None:
        """A new keyframe: its rotation from the last one against the two-view geometry
        (rotation_check.py, docs/method.md §15.2). A disagreement beyond the two views'
        covariance is evidence the published covariance must hold, and DEGRADED."""
        c = self.cfg
        kfs = self.local_map.keyframes
        if not c.rotation_check or len(kfs) < 2:
            return
        a, b = kfs[-2], kfs[-1]
        check = check_rotation(self.camera.K, a.ids, a.px, a.T_world_cam_filter, b.ids,
                               b.px, b.T_world_cam_filter, c.bootstrap_ransac_px,
                               c.rotation_check_min_parallax_deg, H_OVER_E_RATIO,
                               self.ekf.pose_covariance()[3:, 3:], seed=self.frame_index)
        self.last_rotation_check = check
        if check is not None and check.nees > c.rotation_check_max_nees:
            self.world_cov.add_rotation_evidence(check.discrepancy_world)
            self.health.flag(f'rotation {check.angle_deg:.2f} deg off the two-view geometry '
                             f'(NEES {check.nees:.0f})')

    def _map_points_in_view(self) -> int:
        """Map points the prior puts inside the image (in front, within its bounds)."""
        if not len(self.map):
            return 0
        px, front, _ = self.ekf.observe(self.map.X_world, with_jacobian=False)
        ok = front & np.all(np.isfinite(px), axis=1)
        return int(np.count_nonzero(self.camera.in_image(self.camera.distort(px[ok]))))

    def _predicted_pixels(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(ids, raw pixels) where the prior puts the last frame's tracks that have a map
        or in-filter point: the KLT initial guess (active search, Davison 2003)."""
        prev_ids = self._prev_ids
        mask, X_prev = self.map.lookup(prev_ids)
        predicted = None
        if np.any(mask):
            px_pred, front, _ = self.ekf.observe(X_prev, with_jacobian=False)
            ok = front & np.all(np.isfinite(px_pred), axis=1)
            predicted = (prev_ids[mask][ok], self.camera.distort(px_pred[ok]))
        if self.points is not None and len(self.points):
            predicted = self._add_filter_predictions(predicted)
        return predicted

    def _after_update(self, gray: np.ndarray, tracks: Tracks, px: np.ndarray,
                      rows: np.ndarray, X: np.ndarray, has_point: np.ndarray,
                      inlier_mask: np.ndarray) -> int:
        """Map growth (in-filter points, triangulation) and the keyframe decision of a
        tracked frame. Returns the number of new map points."""
        T_world_cam = self.ekf.T_world_cam
        self.growth.remember_pose(self.frame_index, T_world_cam)
        grow_mask, n_new = has_point, 0
        if self.points is not None:
            n_new, grow_mask = self._refine_points(tracks, px, rows, X, T_world_cam)
        n_new += self.growth.grow(self.map, self.frame_index, tracks.ids, px, grow_mask,
                                  T_world_cam, self.world_cov.last)
        if self.local_map is not None:
            # a keyframe keeps the update's inliers and the tracks that had no point
            # then (new points, candidates); the update's outliers stay out of the window
            keep = inlier_mask | ~has_point
            if self.local_map.consider(self.frame_index, T_world_cam, tracks.ids[keep],
                                       px[keep], self.map.contains(tracks.ids[keep]),
                                       self.map, self.world_cov.last):
                self._check_rotation()
                if self.finder is not None:
                    self.finder.describe(gray, tracks, self.map)
        return n_new

    # ------------------------------------------------------------------ point filter
    def _add_filter_predictions(self, predicted):
        """Append the predicted pixels of the in-filter points to the KLT prior."""
        X = self.points.X_world()
        ok = np.all(np.isfinite(X), axis=1)
        if not np.any(ok):
            return predicted
        px_pred, front, _ = self.ekf.observe(X[ok], with_jacobian=False)
        good = front & np.all(np.isfinite(px_pred), axis=1)
        ids = self.points.ids[ok][good]
        px_pred = self.camera.distort(px_pred[good])
        if predicted is None:
            return ids, px_pred
        return np.concatenate((predicted[0], ids)), np.concatenate((predicted[1], px_pred))

    def _update(self, tracks: Tracks, px: np.ndarray, rows: np.ndarray,
                X: np.ndarray, sigma: np.ndarray | None) -> np.ndarray:
        """The estimator's update (estimators.py) with the map matches `rows` (pixel std
        `sigma`, None = pixel_sigma_px) and, with map_refinement: filter, the tracked
        in-filter points; records the map points' verdicts (culling). Returns the inlier
        track rows."""
        matches = FrameMatches(px[rows], X, sigma_map=sigma)
        f_tracks = np.zeros(0, np.int64)
        if self.points is not None:
            pt_rows = self.points.rows_of(tracks.ids)
            f_tracks = np.flatnonzero(pt_rows >= 0)
            matches.z_points, matches.point_rows = px[f_tracks], pt_rows[f_tracks]
        out = self.estimator.update(matches, self.rng)
        self._map_inliers = out.map_inliers
        if self.cfg.measurement_noise == 'adaptive':
            inl = out.map_inliers
            learn_from_update(self.map, self.ekf, tracks.ids[rows][inl], px[rows][inl],
                              X[inl], self.cfg.pixel_sigma_px)
        if len(rows):
            culled = self.map.record_observations(tracks.ids[rows], out.map_inliers,
                                                  self.frame_index)
            self.growth.banned.update(int(i) for i in culled)
        return np.concatenate((rows[out.map_inliers], f_tracks[out.point_inliers]))

    def _refine_points(self, tracks: Tracks, px: np.ndarray, rows: np.ndarray,
                       X: np.ndarray, T_world_cam: np.ndarray) -> tuple[int, np.ndarray]:
        """Freeze / drop in-filter points (docs/method.md §8), then fill the free slots with
        new tracks. Returns (points frozen into the map, mask of tracks that are either
        in the map or in the filter: those are not triangulation candidates)."""
        pts = self.points
        out = pts.retire(tracks.ids, T_world_cam[:3, 3])
        if len(out.frozen_ids):
            self.map.add(out.frozen_ids, out.frozen_X, self.frame_index,
                         n_obs=int(np.min(out.frozen_n_obs)), anchor=self.world_cov.last)
        self._filter_rejected.update(int(i) for i in out.dropped_ids)
        in_map = self.map.contains(tracks.ids)
        in_filter = pts.rows_of(tracks.ids) >= 0
        if pts.free_slots > 0 and len(X):
            R, r = T_world_cam[:3, :3], T_world_cam[:3, 3]
            depth = (X - r) @ R[:, 2]
            depth = depth[depth > 0]
            free = ~in_map & ~in_filter
            new = [k for k in np.flatnonzero(free)[::-1]       # newest tracks first
                   if int(tracks.ids[k]) not in self.growth.banned
                   and int(tracks.ids[k]) not in self._filter_rejected]
            new = np.array(new[:pts.free_slots], np.int64)
            if len(new) and len(depth):
                pts.add(tracks.ids[new], px[new], T_world_cam, float(np.median(depth)),
                        self.frame_index)
                in_filter[new] = True
                for tid in tracks.ids[new]:
                    self.growth.drop(int(tid))
        return len(out.frozen_ids), in_map | in_filter

    # ------------------------------------------------------------------ output
    def _fill_output(self, res: FrameResult, tracks: Tracks, has_point: np.ndarray,
                     inlier_mask: np.ndarray) -> None:
        self._prev_ids = tracks.ids.copy()
        res.track_ids, res.track_px = tracks.ids, tracks.px
        res.track_has_point, res.track_inlier = has_point, inlier_mask
        res.T_world_cam = self.ekf.T_world_cam
        cov = self._published_cov
        twist, twist_cov = self.ekf.twist_cam()
        # floor the variances: never publish a zero (infinitely confident) covariance
        res.pose_cov = cov + np.eye(6) * MIN_VARIANCE
        res.twist_cam = twist
        res.twist_cov = twist_cov * self._inflation + np.eye(6) * MIN_VARIANCE
        if res.bootstrapped:
            res.ok = True
        if not (np.all(np.isfinite(res.T_world_cam)) and np.all(np.isfinite(res.pose_cov))):
            res.ok = False
            res.message = 'non-finite estimate suppressed'

    _prev_ids = np.zeros(0, np.int64)
    _published_cov = np.zeros((6, 6))
 
    last_rotation_check = None     #: the last keyframe pair's rotation_check.RotationCheck
    _inflation = 1.0               #: the health checks' factor on the published covariance

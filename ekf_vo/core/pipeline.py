"""Per-frame visual odometry pipeline: bootstrap, EKF tracking, map growth, loss handling.

docs/method.md §1 and §7, step by step, per frame:
  INITIALISING: keep a reference frame; try the two-view bootstrap against each new frame
                (essential matrix + triangulation) until one has enough parallax and
                inliers; the EKF starts at the second frame's pose with the velocity of
                the pair (docs/method.md §3.6). In initialisation.py (a mixin).
  TRACKING:     predict (constant velocity, real dt) -> track features with the predicted
                landmark pixels as the KLT prior -> robust EKF update with the fixed map
                points (1-point RANSAC) -> triangulate tracks with enough parallax between
                their first observation and now, with the EKF poses -> output.
  LOST:         too many failed frames, a gap in the stream or a covariance blow-up: keep
                the map and find the camera in it again (relocalise.py, §15.6); after
                relocalise_timeout_s drop the map and re-bootstrap, attaching the new map
                to the last good pose (odom continuity) with the scale carried over from
                the last velocity and the covariance from the last published pose.
Each tracked frame is judged (health.py: OK / DEGRADED) and its published covariance
holds the map's error (map_uncertainty.py, §14-15).
Speaks numpy arrays, integer nanosecond stamps and named frames; no ROS types.
"""
from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from ..config import VoConfig
from . import geometry as geo
from .bearing import BearingMeasurements, depth_spread_px2
from .bootstrap import H_OVER_E_RATIO, TwoViewBootstrap
from .camera import PinholeCamera
from .ekf import ANG, POS, VEL, CameraEKF, FilterError
from .estimators import FrameMatches, make_estimator
from .features import FeatureTracker, Tracks
from .frame_result import MIN_VARIANCE, FrameResult, TrackingState
from .health import Health, HealthMonitor, found_share
from .initialisation import Initialisation
from .loss import LossHandling
from .local_map import LocalMapper, PoseCorrection
from .map import LandmarkMap
from .map_growth import MapGrowth
from .map_uncertainty import WorldCovariance, carry_pose_covariance
from .multiview import MultiViewBootstrap
from .noise_model import NoiseSettings, learn_from_update, map_measurement_sigmas
from .orientation_only import OrientationChain
from .refind import MapPointFinder
from .readout import ReadoutEstimate, correction_rate, interaction_matrix
from .relocalise import Relocaliser

#: A frame whose tracks landed a median of more than this [px] from their prediction
#: (after the plain-KLT retry) is a jolt the motion model did not follow (docs/method.md
#: §7.5): a brightness flicker misses by 2-7 px, a jolt by 18-58 px. Fixed in pixels, not
#: a share of the KLT window: the window is chosen for the tracks' precision (§5.1), and a
#: smaller one must not turn a flicker into a loss.
JOLT_MISS_PX = 10.5
from .rolling_shutter import (points_on_rays, rotation_to_stamp_time,
                              translation_to_stamp_time)
from .rotation_check import KeyframePairCheck, KeyframeRotationJudge
from .point_filter import PointFilter

logger = logging.getLogger(__name__)

class VisualOdometry(Initialisation, LossHandling):
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
        # (the keyframes' descriptors also serve relocalisation)
        self.finder = MapPointFinder(cfg) if cfg.local_map and (
            cfg.refind_map_points or cfg.relocalise) \
            else None
        self.rng = np.random.default_rng(seed)
        # after a loss, the camera is found again in the kept map (§15.6); None = off
        self.relocaliser = Relocaliser(cfg, camera) if cfg.local_map and cfg.relocalise \
            else None
        self.growth = MapGrowth(cfg, camera)        # triangulation candidates (§7.3)
        # a rolling shutter's readout, estimated (§15.17); kept over map resets
        self.readout = ReadoutEstimate(cfg.rolling_shutter_s, cfg.rolling_shutter_max_s,
                                       cfg.rolling_shutter_estimate)
        self.health = HealthMonitor(cfg)            # online consistency checks (§15)
        # keyframes' rotation check and drift (§15.2, §15.11)
        self._rotation_job = KeyframeRotationJudge(
            cfg.rotation_check_max_nees, cfg.rotation_drift_window, cfg.rotation_drift_lost_deg)
        # in-filter map refinement (docs/method.md §8); None = the hybrid default
        self.points: PointFilter | None = None
        if cfg.map_refinement == 'filter' and cfg.estimator != 'epnp':
            self.points = PointFilter(cfg, camera.K)
        self.estimator = make_estimator(cfg, self.ekf, self.points)
        self.frame_index = -1
        self.n_resets = 0
        self.n_maps = 0                        # bootstraps that started tracking
        self._anchor_T_world_cam = np.eye(4)   # where a new map is attached
        self._anchor_speed = None              # m/s carried over a re-bootstrap
        self._last_frame_ms: float | None = None   # the last frame's time in process()
        # the orientation before a map (docs/method.md §15.9); its own random stream, so
        # that it does not move the draws of the estimator's RANSACs
        self.orientation = OrientationChain(
            camera, cfg.pixel_sigma_px, cfg.orientation_only_max_px,
            cfg.orientation_only_translation_sigma_deg, np.random.default_rng([seed, 15, 9]),
            max_deg=cfg.orientation_only_max_deg) \
            if cfg.orientation_before_map and cfg.bootstrap == 'two_view' else None
        self._reset_state()

    # ------------------------------------------------------------------ control
    def _reset_state(self) -> None:
        self.state = TrackingState.INITIALISING
        self.tracker.reset()
        self.map.clear()
        if self.local_map is not None:
            self.local_map.reset()
        self._ref = None                # the bootstrap's reference frame (initialisation.py)
        self._last_initialising = None  # (stamp, ids, ideal px) of the last such frame
        self._orientation_published = False
        # the rotation rate before the map over the last frame step (camera frame,
        # rad/s): a rolling shutter's rows are brought to the stamp with it
        self._initialising_rate = np.zeros(3)
        if self.orientation is not None:
            self.orientation.restart(self._anchor_T_world_cam[:3, :3],
                                     self.world_cov.carried_covariance[3:, 3:])
        self._last_stamp_ns: int | None = None
        self._failed_frames = 0
        self._last_published_state = None
        self.growth.reset()
        self.health.reset()
        self._rotation_job.reset()
        self.world_cov.new_map()
        self._filter_rejected: set[int] = set()   # left the point filter unconverged
        if self.points is not None:
            self.points.clear()
        if self.multiview is not None:
            self.multiview.reset()

    def close(self) -> None:
        """Stop the worker threads (adjustment, rotation check, detection); a running job
        finishes and its result is dropped. The estimator is not used after this."""
        if self.local_map is not None:
            self.local_map.close(wait=False)
        self._rotation_job.close()
        self.tracker.close()

    def reset(self, reason: str = 'requested') -> None:
        """Drop the map and re-bootstrap; keep the world frame at the last good pose."""
        self._take_check()
        if self.state == TrackingState.TRACKING:
            self._keep_anchor()
        logger.info('VO reset: %s', reason)
        self.n_resets += 1
        self._reset_state()

    # ------------------------------------------------------------------ main entry
    def process(self, gray: np.ndarray, stamp_ns: int,
                known_T_world_cam: np.ndarray | None = None,
                on_pose: Callable[[FrameResult], None] | None = None,
                pose_first: bool | None = None) -> FrameResult:
        """Process one grey image (uint8 HxW, the camera's size) taken at `stamp_ns`
        (int nanoseconds, increasing): stream.VoStream checks both before calling.

        `known_T_world_cam` is only for the papers' ground-truth bootstrap (docs/method.md §2.3:
        "the first two ground-truth poses fix the scale"); the pipeline reads it only until
        its first map. After a loss it relocalises or bootstraps again from the images,
        as it would live: ground truth handed again would favour whichever method loses
        track more often (§9.4).

        `on_pose`: called with the frame's result as soon as its pose, covariance, twist,
        ok and health are final — in a tracked frame before the map work (growth,
        keyframe, rotation check), which then fills in the rest of the same object
        (docs/method.md §17.3). A node publishes odometry from it; frames that do not
        track (bootstrap, relocalisation, lost) do not call it. Its time from the start
        of this call is the result's `timings_ms['to_pose']`.

        `pose_first` (None: whether `on_pose` is given): someone waits for on_pose, so
        while the frames leave time to spare (the last one took under half the frame
        interval) the large window's retry of lost tracks without a map point waits for
        after it too, though it then costs two KLT calls of its own (about 2 ms at
        1226x370; docs/method.md §17.3). The results are the same either way."""
        t0 = time.perf_counter()
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None and self.state == TrackingState.TRACKING and \
                (stamp_ns - self._last_stamp_ns) * 1e-9 > self.cfg.max_dt_s:
            self._lose(f'gap of {(stamp_ns - self._last_stamp_ns) * 1e-9:.2f} s',
                       self._last_stamp_ns)
        self.frame_index += 1
        if self.n_maps:
            known_T_world_cam = None
        if self.state == TrackingState.TRACKING:
            def pose_final(res: FrameResult) -> None:
                # the latency a consumer of the odometry sees in this process (§17.3)
                res.timings_ms['to_pose'] = (time.perf_counter() - t0) * 1e3
                if on_pose is not None:
                    on_pose(res)
            result = self._track(gray, stamp_ns, pose_final,
                                 on_pose is not None if pose_first is None else pose_first)
        elif self.state == TrackingState.LOST:
            result = self._relocalise(gray, stamp_ns)
        elif self.multiview is not None:
            result = self._initialise_multi_view(gray, stamp_ns, known_T_world_cam)
        else:
            result = self._initialise(gray, stamp_ns, known_T_world_cam)
        self._last_stamp_ns = stamp_ns
        result.map_size = len(self.map)
        result.camera_fixed_share = self.tracker.stats.camera_fixed_share
        result.lens_falloff_drop = self.tracker.falloff.applied_drop
        result.klt_window_px = self.tracker.stats.klt_window_px
        result.klt_log_gain = self.tracker.stats.klt_log_gain
        result.klt_wide_kept = self.tracker.stats.n_wide_kept
        result.sensor_noise_grey = self.tracker.noise.estimate_grey
        result.denoised = self.tracker.noise.smoothing
        result.readout_s = self.readout.applied_s
        estimate = self.readout.estimate_s
        result.readout_estimate_s = float('nan') if estimate is None else estimate
        self._last_frame_ms = (time.perf_counter() - t0) * 1e3
        result.timings_ms['total'] = self._last_frame_ms
        return result

    # ------------------------------------------------------------------ tracking
    def _track(self, gray: np.ndarray, stamp_ns: int,
               on_pose: Callable[[FrameResult], None] | None = None,
               pose_first: bool = False) -> FrameResult:
        c = self.cfg
        timings = {}
        dt = (stamp_ns - self._last_stamp_ns) * 1e-9
        if not dt > 0:
            dt = c.default_dt_s

        t = time.perf_counter()
        if self.local_map is not None:
            culled = self.local_map.harvest(self.frame_index, self.map)
            self.growth.banned.update(int(i) for i in culled)
            correction = self.local_map.take_correction()
            if correction is not None and c.ba_pose_feedback:
                self._feed_back(correction)
        timings['local_map'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        self.estimator.predict(dt)
        predicted = self._predicted_pixels()
        n_in_view = self._map_points_in_view()
        timings['predict'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        # the tracks KLT kept; the new corners come after the pose is out (top_up below),
        # and, when someone waits for the pose, so does the large window's retry of lost
        # tracks without a map point, while the update cannot need them as rays (§17.3)
        needed = None
        spare = self._last_frame_ms is not None and self._last_frame_ms < 0.5e3 * dt
        if pose_first and spare and self.points is None and \
                c.max_update_points >= c.bearing_max_map_points:
            live = self.tracker.live_ids
            needed = live[self.map.contains(live)]
        tracks = self.tracker.track(gray, predicted, finish=False, needed_ids=needed,
                                    min_needed=c.bearing_max_map_points)
        px = self.camera.undistort(tracks.px)
        timings['track'] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        has_point, X = self.map.lookup(tracks.ids)
        readout_s = self.readout.applied_s
        prior = None
        if readout_s > 0.0:
            T = self.ekf.T_world_cam
            prior = (T, self.ekf.x[ANG].copy(), self.ekf.x[VEL].copy(),
                     geo.median_depth(X, T))
            px = self._to_stamp_time(tracks.px, px, has_point, X, readout_s, prior)
        rows = np.flatnonzero(has_point)
        if len(rows) > c.max_update_points:
            keep = np.sort(self.rng.choice(len(rows), c.max_update_points, replace=False))
            rows, X = rows[keep], X[keep]
        res = FrameResult(stamp_ns, TrackingState.TRACKING, n_tracks=len(tracks),
                          n_matches=len(rows), timings_ms=timings)
        sigma = map_measurement_sigmas(self.cfg, self._noise, self.map, tracks.ids[rows],
                                       X, self.ekf.T_world_cam, self.camera.K)
        if self.readout.in_force and len(rows):
            # the estimated readout's own uncertainty, in each pixel's noise (§15.17)
            T = self.ekf.T_world_cam
            depth = np.maximum((X - T[:3, 3]) @ T[:3, 2], 1e-6)
            L = interaction_matrix(px[rows], depth, self.camera)
            extra = self.readout.extra_pixel_variance(
                correction_rate(L, tracks.px[rows, 1], self._twist_cam(), self.camera))
            nominal = np.full(len(rows), c.pixel_sigma_px) if sigma is None else sigma
            sigma = np.sqrt(nominal ** 2 + extra)
        rays = self._rays_without_depth(tracks, px, has_point, X)
        try:
            inlier_rows = self._update(tracks, px, rows, X, sigma, rays)
        except (FilterError, np.linalg.LinAlgError) as exc:
            self._roll_back(stamp_ns)      # the anchor of the next map: the last good state
            self.reset(f'filter failure: {exc}')
            res.state, res.message = self.state, f'lost: {exc}'
            return res
        timings['update'] = (time.perf_counter() - t) * 1e3
        res.n_inliers = len(inlier_rows)
        res.n_rays = int(np.count_nonzero(self._ray_inliers))
        self._observe_readout(tracks, px, rows, X, readout_s)

        # ---- tracking quality, and the published covariance (docs/method.md §14-15)
        n_found = np.count_nonzero(self._map_inliers) / max(len(rows), 1) * \
            np.count_nonzero(has_point)
        res.keyframe_pair_check = self._take_check()
        if self._judge(res, n_found, n_in_view):
            return res
        mi = self._map_inliers
        self._published_cov = self.world_cov.compose(
            self.ekf.pose_covariance(), self.ekf.T_world_cam, self.map, tracks.ids[rows][mi],
            X[mi], None if sigma is None else sigma[mi], self._inflation,
            remember=self._failed_frames == 0,
            ray_anchors=None if rays is None else (rays.anchor_cov[self._ray_inliers],
                                                   rays.anchor_c[self._ray_inliers]))

        res.ok = self._failed_frames == 0
        self._fill_pose(res)
        if res.ok:
            self._remember_published_state(stamp_ns)
        if on_pose is not None:
            on_pose(res)                # the pose is final: publish before the map work

        # ---- the tracker's new corners, for the frames to come (no map point yet)
        t = time.perf_counter()
        tracks, px, has_point, at = self._top_up(tracks, px, has_point, readout_s, prior)
        rows, inlier_rows = at[rows], at[inlier_rows]
        res.n_tracks = len(tracks)
        timings['top_up'] = (time.perf_counter() - t) * 1e3
        timings['detect'] = self.tracker.stats.detect_ms     # a part of 'top_up'

        # ---- map growth, keyframes
        t = time.perf_counter()
        inlier_mask = np.zeros(len(tracks), bool)
        inlier_mask[inlier_rows] = True
        res.n_new_points += self._after_update(gray, tracks, px, rows, X, has_point,
                                               inlier_mask)
        timings['map'] = (time.perf_counter() - t) * 1e3
        self._fill_tracks(res, tracks, has_point, inlier_mask)
        if self.finder is not None and c.refind_map_points:
            t = time.perf_counter()
            found = self.finder.find_again(gray, tracks, self.map, self.ekf, self.camera,
                                           self.tracker, self.rng)
            res.n_found_again = len(found)
            self._prev_ids = np.union1d(self._prev_ids, found)
            timings['refind'] = (time.perf_counter() - t) * 1e3
        return res

    def _top_up(self, tracks: Tracks, px: np.ndarray, has_point: np.ndarray,
                readout_s: float, prior: tuple | None
                ) -> tuple[Tracks, np.ndarray, np.ndarray, np.ndarray]:
        """The frame's tracks once the tracker has finished it (FeatureTracker.finish):
        `tracks`, the lost ones the large window kept after the pose (in their rows: ids
        ascend) and the new corners (last). Returns all tracks, their ideal pixels (the
        added ones undistorted and, under a rolling shutter, brought to the stamp's time
        by the same prior as the others), which have a map point (no added one does),
        and the row of each of `tracks` among them."""
        full = self.tracker.finish()
        at = np.searchsorted(full.ids, tracks.ids)
        if len(full) == len(tracks):
            return full, px, has_point, at
        added = np.ones(len(full), bool)
        added[at] = False
        added_px = self.camera.undistort(full.px[added])
        no_point = np.zeros(len(added_px), bool)
        if prior is not None:
            added_px = self._to_stamp_time(full.px[added], added_px, no_point,
                                           np.empty((0, 3)), readout_s, prior)
        all_px = np.empty((len(full), 2))
        all_px[at], all_px[added] = px, added_px
        all_has_point = np.zeros(len(full), bool)
        all_has_point[at] = has_point
        return full, all_px, all_has_point, at

    def _to_stamp_time(self, px_raw: np.ndarray, px: np.ndarray, has_point: np.ndarray,
                       X: np.ndarray, readout_s: float, prior: tuple) -> np.ndarray:
        """A rolling shutter's tracked pixels `px` (ideal; raw `px_raw`), each row
        brought to the stamp's time by the prior's motion (rolling_shutter.py,
        docs/method.md §15.14): the rotation for every track, the translation at the
        map point's depth (`X`, of the rows `has_point`), or, for a track without one,
        at the median depth of the map in view. `prior`: the filter's predicted
        (T_world_cam, angular velocity, velocity) and that median depth (None: none)."""
        cam = self.camera
        T, omega, v, depth = prior
        rows_px = px_raw[:, 1]
        px = rotation_to_stamp_time(px, rows_px, omega, readout_s, cam)
        if depth is None:
            return px
        X_all = points_on_rays(px, cam, T, depth)
        X_all[has_point] = X
        return translation_to_stamp_time(px, rows_px, X_all, T, v, readout_s, cam)

    def _observe_readout(self, tracks: Tracks, px: np.ndarray, rows: np.ndarray,
                         X: np.ndarray, used_s: float) -> None:
        """Hand the map points the update kept to the readout estimate (readout.py,
        docs/method.md §15.17): their residuals after the update, and how a readout
        correction moves each, with the updated motion."""
        if not self.readout.enabled:
            return
        mi = self._map_inliers           # too few of them: observe() says nothing
        cam, T = self.camera, self.ekf.T_world_cam
        kept = rows[mi]
        X_cam = (X[mi] - T[:3, 3]) @ T[:3, :3]
        self.readout.observe(px[kept], tracks.px[kept, 1], X_cam[:, 2],
                             px[kept] - cam.project(X_cam), self._twist_cam(), cam, used_s)

    def _twist_cam(self) -> np.ndarray:
        """The filter's velocity and rotation rate, both in the camera frame (6,)."""
        return np.concatenate((self.ekf.T_world_cam[:3, :3].T @ self.ekf.x[VEL],
                               self.ekf.x[ANG]))

    def _judge(self, res: FrameResult, n_found: float, n_in_view: int) -> bool:
        """Failed frames and loss (docs/method.md §7.4), then the online consistency
        checks (health.py, §15) that may inflate the published covariance. True when
        tracking was lost (the pipeline has reset)."""
        c = self.cfg
        pos_sigma = float(np.sqrt(np.max(np.diag(self.ekf.P)[POS])))
        upd = self.ekf.last_update
        nis_per_dof = upd.nis / (2 * upd.n_used) if upd.n_used else 0.0
        res.nis_per_dof = nis_per_dof
        lost_by_motion = self._rotation_job.map_lost or \
            self._motion_model_lost(n_found, n_in_view)
        if lost_by_motion:
            self._failed_frames = c.max_failed_frames
            res.message = lost_by_motion
        elif res.n_inliers < c.min_tracking_inliers:
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
            self._lose(f'tracking lost ({why})', res.stamp_ns)
            res.state, res.message = self.state, f'lost: {why}'
            res.health, res.health_reason = Health.LOST.value, why
            return True
        report = self.health.assess(upd.nis, 2 * upd.n_used, n_found, n_in_view)
        self._inflation = report.inflation
        res.health, res.health_reason = report.status.value, report.reason
        if res.n_rays:
            # the map no longer holds the pose: its position rests on the motion model
            res.health = Health.DEGRADED.value
            res.health_reason = '; '.join(filter(None, (
                report.reason, f'{res.n_rays} tracks without depth hold the orientation '
                f'({res.n_inliers - res.n_rays} map points)')))
        res.variance_factor, res.found_share = report.variance_factor, report.found_share
        return False

    def _feed_back(self, corr: PoseCorrection) -> None:
        """The adjustment's pose of its newest keyframe, as a measurement of the current
        pose: the filter's motion since that keyframe applied to the adjusted keyframe
        (ba_pose_feedback, docs/method.md §12.2). Taken only when it disagrees with the
        filter beyond the filter's own covariance (which holds the map exact): the filter
        has drifted from the map its window refined, and its fresh points would carry
        the drift into the map. Weighed against the published covariance (which counts
        the map's error); the mean moves, the covariance stays."""
        c = self.cfg
        T_now = self.ekf.T_world_cam
        T_meas = corr.T_world_cam_adjusted @ np.linalg.inv(corr.T_world_cam_filter) @ T_now
        cov = carry_pose_covariance(corr.cov_relative[None], corr.T_world_cam_adjusted[:3, 3],
                                    T_meas[:3, 3])[0] + np.eye(6) * MIN_VARIANCE
        stats = self.local_map.stats
        stats.feedback_last_nis = self.ekf.pose_nis(T_meas, cov)
        if stats.feedback_last_nis < c.ba_pose_feedback_min_nis:
            return
        try:
            self.ekf.update_pose(T_meas, cov, keep_covariance=True,
                                 prior_pose_cov=self._published_cov)
        except (FilterError, np.linalg.LinAlgError) as exc:
            logger.warning('local map: pose feedback skipped (%s)', exc)
            return
        stats.n_feedback += 1
        stats.feedback_last_m = float(np.linalg.norm(self.ekf.x[POS] - T_now[:3, 3]))
        stats.feedback_last_deg = geo.rotation_angle_deg(self.ekf.R_world_cam, T_now[:3, :3])

    def _motion_model_lost(self, n_found: float, n_in_view: int) -> str:
        """Why this frame is a jolt the state cannot follow, or '' (docs/method.md
        §7.5, §15.10): the plain KLT retry ran, the tracks kept landed more than
        JOLT_MISS_PX from their prediction (a flicker's miss is 2-7 px), and the map in
        view is not found. Its few inliers would carry a wrong pose on (18 deg, DEGRADED)."""
        c = self.cfg
        klt = self.tracker.stats
        found = found_share(n_found, n_in_view)
        if klt.n_prediction_retried and klt.prediction_miss_px > JOLT_MISS_PX \
                and n_in_view >= 2 * c.min_tracking_inliers \
                and found < c.health_min_found_share:
            return (f'the motion model lost the camera: tracks '
                    f'{klt.prediction_miss_px:.0f} px off their prediction, '
                    f'{100 * found:.0f} % of the {n_in_view} map points in view found')
        return ''

    def _check_rotation(self) -> None:
        """A new keyframe: its rotation from the last one against the two-view geometry
        (rotation_check.py, docs/method.md §15.2). A disagreement beyond the two views'
        covariance is evidence the published covariance must hold, and DEGRADED."""
        c = self.cfg
        kfs = self.local_map.keyframes
        if not c.rotation_check or len(kfs) < 2:
            return
        # the pair from the last keyframe, or the second look at a doubtful pair from
        # that pair's first keyframe (rotation_check.KeyframeRotationJudge.judge)
        longer = self._rotation_job.wants_second_look and len(kfs) >= 3
        span_from = self._rotation_job.span_from
        if longer:
            a = kfs[-3]
        elif span_from is not None and any(kf is span_from for kf in kfs[:-1]):
            a = span_from          # the last pair was not judged: span it and this one
        else:
            a = kfs[-2]
        b = kfs[-1]
        # in a worker thread; its verdict is taken before the next frame's (_take_check)
        self._rotation_job.submit(
            self.camera.K, a.ids, a.px, a.T_world_cam_filter, b.ids, b.px,
            b.T_world_cam_filter, c.bootstrap_ransac_px, c.rotation_check_min_parallax_deg,
            H_OVER_E_RATIO, self.ekf.pose_covariance()[3:, 3:], seed=self.frame_index,
            longer=longer, first=a, frames=(a.frame_index, b.frame_index))

    def _take_check(self) -> KeyframePairCheck | None:
        """The last keyframe's rotation check (_check_rotation), before anything it
        informs: the next frame's verdict and published covariance, a reset, a loss.
        Its record (the pair, as checked), or None without one."""
        if not self._rotation_job.pending:
            return None
        reason, record = self._rotation_job.take(self.world_cov)
        self.last_rotation_check = self._rotation_job.last
        if reason:
            self.health.flag(reason)
        return record

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

    def _rays_without_depth(self, tracks: Tracks, px: np.ndarray, has_point: np.ndarray,
                            X: np.ndarray) -> BearingMeasurements | None:
        """The tracks without a map point to measure as rays of unknown depth (bearing.py,
        docs/method.md §15.8): only in a frame with fewer than bearing_max_map_points
        map matches, and only with the hybrid EKF / IEKF. None = none."""
        c = self.cfg
        T = self.ekf.T_world_cam
        if len(X) >= 3:
            self._depth_guess = geo.median_depth(X, T) or self._depth_guess
        if len(X) >= c.bearing_max_map_points or c.estimator == 'epnp' or \
                self.points is not None or self._depth_guess is None:
            return None
        rows, centres, bearings, a_cov, a_c = self.growth.rays(
            tracks.ids, self.frame_index, T[:3, 3],
            c.bearing_max_baseline_ratio * self._depth_guess, c.bearing_max_points)
        keep = ~has_point[rows]
        if not np.any(keep):
            return None
        rho0 = 1.0 / self._depth_guess
        X_ray, cov = depth_spread_px2(centres[keep], bearings[keep], T, self.camera.K, rho0,
                                      c.bearing_depth_rel_sigma * rho0)
        # the first observation's pixel noise fixed the ray: the update adds this one's
        cov += np.eye(2) * c.pixel_sigma_px ** 2
        return BearingMeasurements(rows[keep], X_ray, cov, a_cov[keep], a_c[keep])

    def _update(self, tracks: Tracks, px: np.ndarray, rows: np.ndarray,
                X: np.ndarray, sigma: np.ndarray | None,
                rays: BearingMeasurements | None = None) -> np.ndarray:
        """The estimator's update (estimators.py) with the map matches `rows` (pixel std
        `sigma`, None = pixel_sigma_px), the rays without depth `rays` and, with
        map_refinement: filter, the tracked in-filter points; records the map points'
        verdicts (culling). Returns the inlier track rows."""
        a = len(rows)
        if rays is None:
            matches = FrameMatches(px[rows], X, sigma_map=sigma)
        else:
            nominal = np.full(a, self.cfg.pixel_sigma_px) if sigma is None else sigma
            matches = FrameMatches(
                np.concatenate((px[rows], px[rays.rows])), np.concatenate((X, rays.X_world)),
                sigma_map=np.concatenate((nominal, np.full(len(rays), self.cfg.pixel_sigma_px))),
                extra_cov_px2=np.concatenate((np.zeros((a, 2, 2)), rays.cov_px2)))
        f_tracks = np.zeros(0, np.int64)
        if self.points is not None:
            pt_rows = self.points.rows_of(tracks.ids)
            f_tracks = np.flatnonzero(pt_rows >= 0)
            matches.z_points, matches.point_rows = px[f_tracks], pt_rows[f_tracks]
        out = self.estimator.update(matches, self.rng)
        self._map_inliers = out.map_inliers[:a]
        self._ray_inliers = out.map_inliers[a:]
        if self.cfg.measurement_noise == 'adaptive':
            inl = self._map_inliers
            learn_from_update(self.map, self.ekf, tracks.ids[rows][inl], px[rows][inl],
                              X[inl], self.cfg.pixel_sigma_px)
        if len(rows):
            culled = self.map.record_observations(tracks.ids[rows], self._map_inliers,
                                                  self.frame_index)
            self.growth.banned.update(int(i) for i in culled)
        ray_rows = np.zeros(0, np.int64) if rays is None else rays.rows[self._ray_inliers]
        return np.concatenate((rows[self._map_inliers], f_tracks[out.point_inliers],
                               ray_rows))

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
            depth = geo.median_depth(X, T_world_cam)
            free = ~in_map & ~in_filter
            new = [k for k in np.flatnonzero(free)[::-1]       # newest tracks first
                   if int(tracks.ids[k]) not in self.growth.banned
                   and int(tracks.ids[k]) not in self._filter_rejected]
            new = np.array(new[:pts.free_slots], np.int64)
            if len(new) and depth is not None:
                pts.add(tracks.ids[new], px[new], T_world_cam, depth, self.frame_index)
                in_filter[new] = True
                for tid in tracks.ids[new]:
                    self.growth.drop(int(tid))
        return len(out.frozen_ids), in_map | in_filter

    # ------------------------------------------------------------------ output
    def _fill_output(self, res: FrameResult, tracks: Tracks, has_point: np.ndarray,
                     inlier_mask: np.ndarray) -> None:
        self._fill_pose(res)
        self._fill_tracks(res, tracks, has_point, inlier_mask)

    def _fill_tracks(self, res: FrameResult, tracks: Tracks, has_point: np.ndarray,
                     inlier_mask: np.ndarray) -> None:
        self._prev_ids = tracks.ids.copy()
        res.track_ids, res.track_px = tracks.ids, tracks.px
        res.track_has_point, res.track_inlier = has_point, inlier_mask

    def _fill_pose(self, res: FrameResult) -> None:
        """The published pose, covariance and twist (and ok) of the filter's state."""
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
    _ray_inliers = np.zeros(0, bool)   #: the last update's verdicts on rays without depth
    _depth_guess: float | None = None  #: median depth of the map in view (bearing.py)
    last_rotation_check = None     #: the last keyframe pair's rotation_check.RotationCheck
    _inflation = 1.0               #: the health checks' factor on the published covariance

"""The initialising state of the pipeline: the bootstrap that starts tracking.

docs/method.md §2 and §3.6. A mixin of core.pipeline.VisualOdometry (it shares its state):
the two-view bootstrap (a reference frame, then each new frame tried against it until one
has enough parallax and inliers), the multi-view bootstrap (`bootstrap: multi_view`,
multiview.py), and `_start_tracking`, which turns a bootstrap's map and poses into the
filter's start, the first keyframes and the triangulation candidates.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import geometry as geo
from .bootstrap import BootstrapResult
from .features import Tracks
from .frame_result import MIN_VARIANCE, FrameResult, TrackingState
from .map_uncertainty import point_consider_covariance, pose_point_jacobians
from .orientation_only import fit_rotation
from .pnp import solve_epnp
from .rolling_shutter import rotation_to_stamp_time

#: chi-square 3 dof, 99 %: a bootstrap rotation the orientation chain contradicts, or a
#: resection of a frame it knew (Initialisation._attach_pose)
_CHI2_3DOF_99 = 11.34
#: the bootstrap pair's motion took less than this share of its time: the camera stood
#: still before (Initialisation._motion_time)
_STOOD_STILL_SHARE = 0.5


def _contradicts(d: np.ndarray, C: np.ndarray) -> bool:
    """Whether two rotations that differ by the rotation vector d disagree beyond the
    covariance C of that difference (chi-square 3 dof, 99 %)."""
    return float(d @ np.linalg.solve(C, d)) > _CHI2_3DOF_99


@dataclass
class _Reference:
    """The first frame of a bootstrap pair."""

    stamp_ns: int
    frame_index: int
    ids: np.ndarray
    px_ideal: np.ndarray
    T_world_cam: np.ndarray | None  # known pose (ground-truth bootstrap) if given
    #: tracks it shared with the last frame tried against it (its own count at first)
    n_shared: int = 0


#: before the map, a track within this of where the bootstrap reference saw it [px],
#: while the reference's tracks moved by a median of STUCK_MEDIAN_PX or more, is taken
#: for something fixed to the camera (Initialisation._moving)
STUCK_PX = 0.2
STUCK_MEDIAN_PX = 10.0
#: a rolling shutter's rate fit before the map first accepts bearings this many times
#: farther from a rotation than the chain does (rolling_shutter.py)
RATE_FIT_LOOSENESS = 5.0


class Initialisation:
    """The bootstrap methods of VisualOdometry (see the module docstring)."""

    # ------------------------------------------------------------------ bootstrap
    def _track_initialising(self, gray: np.ndarray, stamp_ns: int
                            ) -> tuple[Tracks, np.ndarray, FrameResult]:
        """Front end of a frame before tracking: tracks, their ideal pixels, a result."""
        t = time.perf_counter()
        tracks = self.tracker.track(gray)
        timings = {'track': (time.perf_counter() - t) * 1e3,
                   'detect': self.tracker.stats.detect_ms}     # a part of 'track'
        px = self.camera.undistort(tracks.px)
        if self.readout.applied_s > 0.0:
            px = self._initialising_to_stamp_time(tracks, px, stamp_ns)
        res = FrameResult(stamp_ns, TrackingState.INITIALISING, n_tracks=len(tracks),
                          timings_ms=timings, track_ids=tracks.ids, track_px=tracks.px)
        return tracks, px, res

    def _initialising_to_stamp_time(self, tracks: Tracks, px: np.ndarray, stamp_ns: int
                                    ) -> np.ndarray:
        """Before the map, a rolling shutter's rows are brought to the stamp's time by
        the rotation alone (rolling_shutter.py, docs/method.md §15.14), at the rate of
        the step from the last frame: fitted to this frame's pixels corrected at the
        last step's rate (a hand-held camera's rate changes within a few frames), or
        that rate when the step has no rotation fit."""
        readout_s, rows_px = self.readout.applied_s, tracks.px[:, 1]
        moved = rotation_to_stamp_time(px, rows_px, self._initialising_rate,
                                       readout_s, self.camera)
        prev = self._last_initialising
        if prev is None or self.orientation is None:
            return moved
        _, i_prev, i_cur = np.intersect1d(prev[1], tracks.ids, assume_unique=True,
                                          return_indices=True)
        dt = (stamp_ns - prev[0]) * 1e-9
        if not dt > 0.0:
            return moved
        chain = self.orientation
        b_prev = self.camera.unproject(prev[2][i_prev])
        rng = np.random.default_rng([self.frame_index, 15, 14])
        # first with a loose threshold (the skew left at the last step's rate can be
        # many pixels), then at the chain's own on the pixels that rate corrects
        for max_rad in (RATE_FIT_LOOSENESS * chain.max_rad, chain.max_rad):
            fit = fit_rotation(b_prev, self.camera.unproject(moved[i_cur]), chain.sigma_rad,
                               max_rad, rng)
            if fit is None:
                break
            self._initialising_rate = \
                geo.quat_to_rotvec(geo.matrix_to_quat(fit.R_cur_ref.T)) / dt
            moved = rotation_to_stamp_time(px, rows_px, self._initialising_rate,
                                           readout_s, self.camera)
        return moved

    def _initialise(self, gray: np.ndarray, stamp_ns: int,
                    known_T: np.ndarray | None) -> FrameResult:
        tracks, px, res = self._track_initialising(gray, stamp_ns)
        timings = res.timings_ms
        prev, self._last_initialising = self._last_initialising, (stamp_ns, tracks.ids, px)
        if self.readout.applied_s > 0.0 and prev is None and known_T is None:
            # a rolling shutter's first frame keeps its skew (no turn rate yet): a
            # reference made of it would show the skew as parallax in every later pair
            res.message = 'bootstrap: rolling shutter, the first frame only gives the turn rate'
            return res
        chain = self.orientation if known_T is None else None
        ref = self._ref
        ids, px_m = self._moving(tracks.ids, px)
        est = None if chain is None else chain.track(stamp_ns, ids, px_m)
        too_old = ref is not None and self.frame_index - ref.frame_index > \
            self.cfg.bootstrap_max_frames
        n_common = 0 if ref is None else len(np.intersect1d(ref.ids, ids))
        if ref is None or too_old or n_common < self.cfg.bootstrap_min_inliers:
            if len(tracks) >= self.cfg.bootstrap_min_inliers:
                self._ref = _Reference(stamp_ns, self.frame_index, tracks.ids.copy(),
                                       px.copy(), known_T, len(tracks))
                if chain is not None:
                    chain.new_reference(est)
                res.message = 'bootstrap: new reference frame'
            else:
                res.message = f'bootstrap: only {len(tracks)} features'
            self._orientation_only(res, est)
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
            # once the orientation alone is published and the camera still turns,
            # nothing is lost by waiting for a pair that conditions the map well and
            # agrees with it; a camera that translates is the essential matrix's case
            # (docs/method.md §15.9)
            slow = chain is not None and self._orientation_published and \
                not chain.translating
            strict = slow and not chain.translation_seen
            gate = self.cfg.orientation_only_bootstrap_parallax_deg if slow else None
            boot = self.bootstrapper.try_pair(ref.ids, ref.px_ideal, ids, px_m,
                                              baseline=baseline, min_parallax_deg=gate,
                                              kept_share=n_common / max(ref.n_shared, 1))
            if chain is not None:
                # a pair's parallax means something only with its points triangulated
                # (an arbitrary essential matrix gives 15-40 deg with few of them)
                sound = boot.n_inliers >= self.cfg.bootstrap_min_inliers
                chain.judge_pair(est, boot.median_parallax_deg if sound else float('nan'))
                if not boot.ok:
                    # a translation the bootstrap never confirms was a turn (§15.13)
                    est = chain.reconsider(boot.rotation_like) or est
            if boot.ok and strict:
                boot = self._against_chain(boot, est)
            if boot.ok:
                T_world_ref = self._attach_pose(boot, ref.stamp_ns)
                T_world_cur = T_world_ref @ geo.invert_T(boot.T_cur_ref)
                X_world = geo.transform_points(T_world_ref, boot.X_ref)
        timings['bootstrap'] = (time.perf_counter() - t) * 1e3
        ref.n_shared = n_common
        if not boot.ok:
            res.message = f'bootstrap refused: {boot.reason}'
            self._orientation_only(res, est)
            return res

        self._start_tracking(res, gray, tracks, px, boot.point_ids, X_world, T_world_ref,
                             T_world_cur, self._motion_time(ref, prev, tracks.ids, px,
                                                            stamp_ns, boot.median_flow_px),
                             [(ref.frame_index, ref.ids, ref.px_ideal, T_world_ref)])
        self._check_bootstrap_rotation(res, boot, est)
        self._cover_rivals(res, boot.rival_rotvecs, T_world_ref[:3, :3])
        res.message = (f'bootstrapped: {boot.n_inliers} points, parallax '
                       f'{boot.median_parallax_deg:.1f} deg')
        return res

    def _moving(self, ids: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tracks (ids, ideal px) the bootstrap and the orientation chain use: all but
        those that stayed within STUCK_PX of where the bootstrap reference saw them while
        the reference's tracks moved by a median of STUCK_MEDIAN_PX or more. Such a track
        is on something fixed to the camera (the vehicle's body, a burned-in clock) that
        the front end has not yet been shown long enough to mask (camera_fixed.py,
        docs/method.md §6.10): it says "no motion", and a zero flow satisfies every
        essential matrix with little rotation. A world point that stays put (where a
        straight drive heads) carries next to nothing for the pair either."""
        ref = self._ref
        if ref is None or not len(ids):
            return ids, px
        common, i_ref, i_cur = np.intersect1d(ref.ids, ids, assume_unique=True,
                                              return_indices=True)
        if len(common) < self.cfg.bootstrap_min_inliers:
            return ids, px
        d = np.linalg.norm(px[i_cur] - ref.px_ideal[i_ref], axis=1)
        if float(np.median(d)) < STUCK_MEDIAN_PX:
            return ids, px
        keep = np.ones(len(ids), bool)
        keep[i_cur[d < STUCK_PX]] = False
        return ids[keep], px[keep]

    @staticmethod
    def _motion_time(ref: _Reference, prev, ids: np.ndarray, px: np.ndarray,
                     stamp_ns: int, flow_pair: float) -> float:
        """Over how long the bootstrap pair's motion happened [s]: the time since the
        reference, unless the camera stood still for most of it (a car at a light, a
        robot that waits): then the motion is that of the last frame interval scaled by
        its share of the pair's flow (`flow_pair`, the pair's median flow [px], as the
        bootstrap measured it). The filter's first velocities are the pair's motion
        over this time (§3.6): over the whole wait they would be several times too slow,
        and the first predictions would miss the tracks."""
        dt = (stamp_ns - ref.stamp_ns) * 1e-9
        if prev is None or prev[0] <= ref.stamp_ns or not flow_pair > 0:
            return dt
        _, i_prev, j_cur = np.intersect1d(prev[1], ids, return_indices=True)
        flow_last = np.median(np.linalg.norm(px[j_cur] - prev[2][i_prev], axis=1)) \
            if len(j_cur) else 0.0
        moving = min((stamp_ns - prev[0]) * 1e-9 * flow_pair / max(flow_last, 1e-9), dt)
        # a steady motion gives about dt: kept as is unless the wait is clear
        return moving if moving < _STOOD_STILL_SHARE * dt else dt

    # ------------------------------------------------------------------ before the map
    def _orientation_only(self, res: FrameResult, est) -> None:
        """Publish the orientation of a frame before the map (orientation_only.py,
        docs/method.md §15.9), once the bootstrap has waited orientation_only_after_s:
        the position is the attach point's, unknown (unknown_position_sigma)."""
        chain = self.orientation
        if chain is not None and chain.translation_seen:
            # the chain's rotation is (partly) a translation: nothing to publish until
            # the map (docs/method.md §15.9)
            return
        if est is None and chain is not None and self._orientation_published:
            # a frame whose fit against the reference failed, in a run that already
            # publishes its orientation (a hand-held camera's few centimetres): carried
            # on from the last frame with an orientation when that step is a rotation
            est = chain.carried()
        if est is None or chain is None or \
                (est.stamp_ns - chain.started_ns) * 1e-9 < self.cfg.orientation_only_after_s:
            return
        sigma_u2 = self.cfg.unknown_position_sigma ** 2
        T = self._anchor_T_world_cam.copy()
        T[:3, :3] = est.R_world_cam
        cov = np.zeros((6, 6))
        cov[:3, :3] = sigma_u2 * np.eye(3)
        cov[3:, 3:] = chain.published_covariance(est)
        twist_cov = np.zeros((6, 6))
        twist_cov[:3, :3] = sigma_u2 * np.eye(3)
        w = np.zeros(3)
        if chain.previous is not None:
            w, twist_cov[3:, 3:] = chain.angular_rate(chain.previous, est,
                                                      chain.model_sigma_rad ** 2)
        else:
            twist_cov[3:, 3:] = self.cfg.init_angular_velocity_sigma ** 2 * np.eye(3)
        res.ok, res.orientation_only = True, True
        self._orientation_published = True
        res.T_world_cam = T
        res.pose_cov = cov + MIN_VARIANCE * np.eye(6)
        res.twist_cam = np.concatenate((np.zeros(3), w))
        res.twist_cov = twist_cov + MIN_VARIANCE * np.eye(6)
        res.health = 'degraded'
        res.health_reason = ('no map yet (too little parallax to triangulate): '
                             'orientation only, position unknown')

    def _chain_disagreement(self, boot, est):
        """The bootstrap pair's rotation against the orientation chain's for the same
        two frames (from the same tracks, by two models; docs/method.md §15.9): the
        difference d (rotation vector, current camera frame) and the chain's covariance
        of it (its fits since the reference, and its translation prior); None when the
        chain has no orientation for one of the frames."""
        chain = self.orientation
        ref = None if chain is None else chain.reference
        if est is None or ref is None:
            return None
        R_cur_ref = est.R_world_cam.T @ ref.R_world_cam
        d = geo.quat_to_rotvec(geo.matrix_to_quat(boot.R_cur_ref @ R_cur_ref.T))
        Rc = est.R_world_cam.T
        C = Rc @ (est.cov_world - ref.cov_world) @ Rc.T + \
            chain.model_sigma_rad ** 2 * np.eye(3)
        return d, C

    def _against_chain(self, boot, est):
        """Once orientation-only poses are published and the current frame is still a
        rotation, a bootstrap pair whose rotation contradicts the chain's (chi-square 3
        dof, 99 %) is refused, and so is one whose reference frame has no orientation of
        its own: the published orientation holds, and waiting costs nothing
        (docs/method.md §15.9). Measured on the rendered hand-held camera: a pair at 4 deg
        of parallax 3.4 deg off."""
        found = self._chain_disagreement(boot, est)
        if found is None:
            boot.ok = False
            boot.reason = 'its reference frame has no orientation from the tracks'
            return boot
        d, C = found
        if _contradicts(d, C):
            boot.ok = False
            boot.reason = (f'its rotation is {np.degrees(np.linalg.norm(d)):.1f} deg off '
                           f'the orientation published before the map')
        return boot

    def _check_bootstrap_rotation(self, res: FrameResult, boot, est) -> None:
        """A bootstrap made before any orientation-only pose was published, checked
        against the chain all the same (docs/method.md §15.9). When the two rotations
        disagree by more than both covariances allow (chi-square 3 dof, 99 %), one is
        grossly wrong (an essential matrix decomposed into the wrong pose, a rotation
        fitted to a scene that moved): the disagreement is kept as evidence of an error
        the published covariance does not hold, for the life of this map (as the
        keyframes' rotation check does, rotation_check.py). Within the chain's
        translation prior the two cannot be told apart, and the bootstrap is the better
        model once there is parallax (measured: §15.9)."""
        found = self._chain_disagreement(boot, est)
        if found is None or self.orientation.translation_seen:
            # a chain seen to absorb a translation measured no rotation to judge by
            return
        d, C = found
        R = res.T_world_cam[:3, :3]
        if _contradicts(d, C + R.T @ res.pose_cov[3:, 3:] @ R):
            before = self.world_cov.evidence.copy()
            self.world_cov.add_rotation_evidence(R @ d)
            self._publish_evidence_since(res, before)

    def _cover_rivals(self, res: FrameResult, rotvecs: np.ndarray, R_world_ref: np.ndarray
                      ) -> None:
        """The other poses of a flat scene that fit the bootstrap pair better than the
        one taken (rotation vectors in the reference camera's frame, `rotvecs`): the map
        may be either, so its covariance holds their difference for its life, as
        evidence (docs/method.md §2.1.2); one pose reached from several starts counts
        once."""
        before = self.world_cov.evidence.copy()
        for d in rotvecs:
            self.world_cov.cover_rotation(R_world_ref @ d)
        self._publish_evidence_since(res, before)

    def _publish_evidence_since(self, res: FrameResult, before: np.ndarray) -> None:
        """The bootstrap frame's published covariance (and the one new points take)
        holds the evidence added to world_cov since `before` (later frames get all of
        it from WorldCovariance.compose)."""
        added = self.world_cov.evidence - before
        self._published_cov = self._published_cov + added
        res.pose_cov = res.pose_cov + added

    def _attach_pose(self, boot: BootstrapResult, ref_stamp_ns: int) -> np.ndarray:
        """Where a two-view bootstrap attaches its map: the anchor (the world origin, or
        where a re-bootstrap keeps the pose). Once orientation-only poses have been
        published, turned to the orientation the chain gave the reference frame; when
        the camera was translating then (the reference has none), through a frame the
        chain knew, resected against the new map (`_resect_known`), or else the
        orientation stepped on to the reference or the last one known (uncertain by a
        turn at init_angular_velocity_sigma since), whichever is the more certain. What
        the chain did not measure is added to the anchor's covariance: its rotation
        covariance, and for each reference it went through a translation below the
        bootstrap's parallax gate. Before any was published the map goes where it always
        went (docs/method.md §15.9)."""
        T = self._anchor_T_world_cam.copy()
        chain = self.orientation
        if chain is None or not self._orientation_published:
            return T
        R_ref, cov_ref = chain.reference_or_last(ref_stamp_ns,
                                                 self.cfg.init_angular_velocity_sigma)
        if chain.reference is None:
            resected = self._resect_known(boot)
            if resected is not None and np.trace(resected[1]) < np.trace(cov_ref):
                # a resection the stepped orientation contradicts is not trusted over it
                # (a degenerate map can resect a frame wrongly with a small covariance)
                d = geo.quat_to_rotvec(geo.matrix_to_quat(resected[0] @ R_ref.T))
                if not _contradicts(d, cov_ref + resected[1]):
                    R_ref, cov_ref = resected
        extra = np.zeros((6, 6))
        T[:3, :3] = R_ref
        extra[3:, 3:] = cov_ref - chain.start_covariance
        depth = geo.median_depth(boot.X_ref, np.eye(4)) or 0.0
        gate = np.radians(self.cfg.bootstrap_min_parallax_deg)
        extra[:3, :3] = chain.n_references * (np.tan(gate) * depth) ** 2 * np.eye(3)
        self.world_cov.widen_carried(extra)
        return T

    def _resect_known(self, boot: BootstrapResult) -> tuple[np.ndarray, np.ndarray] | None:
        """The reference frame's orientation (R_world_ref, 3x3 world covariance) through
        a frame the orientation chain knew (OrientationChain.resectable), resected
        against the bootstrap's map (EPnP in RANSAC + LM on the tracks it shares with the
        map's points): the one that gives the smallest covariance, or None when none
        shares enough tracks or every resection fails."""
        c = self.cfg
        K = self.camera.K
        X_cov = None
        best = None
        for ids_k, b_k, R_world_k, cov_k in self.orientation.resectable():
            _, i_k, i_p = np.intersect1d(ids_k, boot.point_ids, assume_unique=True,
                                         return_indices=True)
            front = b_k[i_k, 2] > 1e-6
            i_k, i_p = i_k[front], i_p[front]
            if len(i_k) < c.bootstrap_min_inliers:
                continue
            z = b_k[i_k, :2] / b_k[i_k, 2:3] @ K[:2, :2].T + K[:2, 2]
            X = boot.X_ref[i_p]
            pnp = solve_epnp(z, X, K, c.pixel_sigma_px, c.ransac_inlier_px)
            if not pnp.ok or np.count_nonzero(pnp.inliers) < c.bootstrap_min_inliers:
                continue
            # the map's points are not exact: their triangulation noise (poses held)
            # moves the resected pose too (map_uncertainty.py, item 1)
            if X_cov is None:
                X_cov = self.growth.two_view_covariances(boot.X_ref, np.eye(4),
                                                          geo.invert_T(boot.T_cur_ref))
            inl = pnp.inliers
            J_pose, J_X, _ = pose_point_jacobians(K, pnp.T_world_cam, X[inl])
            points = point_consider_covariance(J_pose, J_X,
                                               np.full(len(J_X), c.pixel_sigma_px),
                                               X_cov[i_p][inl])
            R_world_ref = R_world_k @ pnp.T_world_cam[:3, :3].T
            cov_resected = pnp.pose_cov[3:, 3:] + points[3:, 3:]      # reference frame
            cov = cov_k + R_world_ref @ cov_resected @ R_world_ref.T
            if best is None or np.trace(cov) < np.trace(best[1]):
                best = (R_world_ref, cov)
        return best

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
        res.reference_frame_index = int(sources[0][0])
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
        self.estimator.set_map_speed(float(np.linalg.norm(v_world)))
        self._published_cov = self.ekf.pose_covariance() + anchor[0]
        self._inflation = 1.0
        self.world_cov.last = (self._published_cov, T_world_cur[:3, 3].copy())
        self.state = TrackingState.TRACKING
        self.n_maps += 1
        self._failed_frames = 0
        self._remember_published_state(res.stamp_ns)
        for f, _, _, T in sources:
            self.growth.remember_pose(f, T)
        self.growth.remember_pose(self.frame_index, T_world_cur)
        rows = [{int(i): k for k, i in enumerate(ids)} for _, ids, _, _ in sources]
        has_point = self.map.contains(tracks.ids)
        for k in np.flatnonzero(~has_point):
            tid = int(tracks.ids[k])
            for (f, _, src_px, T), row in zip(sources, rows):
                if tid in row:
                    self.growth.add(tid, f, src_px[row[tid]], T, anchor)
                    break
            else:
                self.growth.add(tid, self.frame_index, px[k], T_world_cur, anchor)
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

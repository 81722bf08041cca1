"""The lost state of the pipeline: where tracking ends, and the camera found again.

docs/method.md §7.4 and §15.6. A mixin of core.pipeline.VisualOdometry (it shares its
state): `_lose` keeps the map and looks for the camera in it (relocalise.py) for
relocalise_timeout_s, `_relocalise` runs per frame meanwhile, and `_keep_anchor` notes
where a re-bootstrap attaches its new map (pose, speed, covariance) when that fails.
"""
from __future__ import annotations

import logging

import numpy as np

from .ekf import ANG, POS, VEL
from .frame_result import FrameResult, TrackingState
from .health import Health

logger = logging.getLogger(__name__)


class LossHandling:
    """The loss and relocalisation methods of VisualOdometry (see the module docstring)."""

    _reloc_failed_s = 0.0          #: textured frames' time spent relocalising in vain
    _lost_velocity = (np.zeros(3), np.zeros(3))
    #: the filter's (x, P, stamp_ns) at the last published frame (_remember_published_state)
    _last_published_state: tuple[np.ndarray, np.ndarray, int] | None = None

    def _remember_published_state(self, stamp_ns: int) -> None:
        """A frame was published: its state is the one a loss goes back to."""
        self._last_published_state = (self.ekf.x.copy(), self.ekf.P.copy(), int(stamp_ns))

    def _roll_back(self, stamp_ns: int) -> None:
        """Tracking is lost at `stamp_ns` after failed frames: the filter goes back to
        the last published frame's state and is predicted from there. The failed
        frames' updates rest on a handful of inliers; one of them turned the
        angular velocity from 19 to 197 deg/s on the rendered walk, and the second of
        prediction while relocalising then carried the anchor of the next map 165 deg
        round (docs/method.md §7.4)."""
        good = self._last_published_state
        if good is None or good[2] >= stamp_ns:
            return
        self.ekf.x, self.ekf.P = good[0].copy(), good[1].copy()
        if self.points is not None:
            # in-filter points (map_refinement: filter) hold cross-covariances with the
            # state just dropped; their tracks end with the loss anyway
            self.points.clear()
        self.estimator.predict((stamp_ns - good[2]) * 1e-9)

    def _keep_anchor(self) -> None:
        """Where a later bootstrap attaches its map: the filter's pose now, its speed
        (the scale) and its covariance (map_uncertainty.WorldCovariance.carry)."""
        self._anchor_T_world_cam = self.ekf.T_world_cam
        self._anchor_speed = float(np.linalg.norm(self.ekf.x[VEL]))
        self.world_cov.carry(self.ekf.pose_covariance(), self.ekf.x[POS])

    def _lose(self, reason: str, stamp_ns: int | None = None) -> None:
        """Tracking lost: keep the map and look for the camera in it (relocalise.py) for
        relocalise_timeout_s; without a relocaliser or a described map, re-bootstrap.
        `stamp_ns`: the frame the filter's state is at; it goes back to the last published
        frame's state first (_roll_back)."""
        self._take_check()
        if self.state == TrackingState.TRACKING and stamp_ns is not None:
            self._roll_back(stamp_ns)
        if self.relocaliser is None or self.state != TrackingState.TRACKING or \
                not len(self.map.described()[0]) or self._rotation_job.map_lost:
            self.reset(reason)
            return
        logger.info('VO lost: %s; relocalising', reason)
        self._keep_anchor()      # what a re-bootstrap needs if relocalisation fails
        self._lost_velocity = (self.ekf.x[VEL].copy(), self.ekf.x[ANG].copy())
        self._reloc_failed_s = 0.0
        self.state = TrackingState.LOST
        self.tracker.reset()
        self.health.reset()
        self.growth.reset()
        self._failed_frames = 0
        self._prev_ids = np.zeros(0, np.int64)

    def _relocalise(self, gray: np.ndarray, stamp_ns: int) -> FrameResult:
        """A frame while lost: pose it in the kept map, or re-bootstrap after
        relocalise_timeout_s. The filter restarts at the PnP pose and covariance with the
        velocities it had when it lost track."""
        tracks = self.tracker.track(gray)
        res = FrameResult(stamp_ns, TrackingState.LOST, n_tracks=len(tracks),
                          health=Health.LOST.value, health_reason='relocalising')
        dt = (stamp_ns - self._last_stamp_ns) * 1e-9 if self._last_stamp_ns else 0.0
        if 0.0 < dt <= self.cfg.max_dt_s:
            # the motion model goes on, unobserved: where a re-bootstrap would attach its
            # map, with the uncertainty the time lost has added
            self.estimator.predict(dt)
        found = self.relocaliser.attempt(gray, self.map)
        if found is None:
            # only frames with texture count: a covered lens may last, a map that is not
            # recognised in good images is given relocalise_timeout_s
            if len(tracks) >= self.cfg.bootstrap_min_inliers and self._last_stamp_ns:
                self._reloc_failed_s += (stamp_ns - self._last_stamp_ns) * 1e-9
            res.message = f'lost: relocalising ({self._reloc_failed_s:.1f} s in vain)'
            if self._reloc_failed_s > self.cfg.relocalise_timeout_s:
                self._keep_anchor()  # the pose predicted through the time lost
                self.reset(f'not relocalised in {self._reloc_failed_s:.1f} s of images')
                res.state = self.state
            return res
        tracks = self.tracker.adopt(found.ids, found.px)
        c = self.cfg
        v_world, w_cam = self._lost_velocity
        # the velocities are stale by the time lost: uncertain by twice their size
        self.ekf.initialise(found.T_world_cam, v_world, w_cam, c.init_pose_sigma,
                            max(c.init_velocity_sigma, 2 * float(np.linalg.norm(v_world))),
                            max(c.init_angular_velocity_sigma,
                                2 * float(np.linalg.norm(w_cam))))
        self.ekf.set_pose(found.T_world_cam, found.pose_cov)
        self.state = TrackingState.TRACKING
        self.growth.remember_pose(self.frame_index, found.T_world_cam)
        self._inflation = 1.0
        self._published_cov = self.world_cov.compose(
            found.pose_cov, found.T_world_cam, self.map, found.ids,
            self.map.lookup(found.ids)[1], None)
        res.state, res.ok, res.n_inliers = TrackingState.TRACKING, True, len(found.ids)
        self._remember_published_state(stamp_ns)
        res.health, res.health_reason = Health.OK.value, ''
        res.message = f'relocalised on {len(found.ids)} map points'
        has_point = self.map.contains(tracks.ids)
        self._fill_output(res, tracks, has_point, np.isin(tracks.ids, found.ids))
        return res

"""Metric scale: the map's units in metres, with an uncertainty (docs/method.md §16).

A monocular map has an arbitrary scale. With `scale_source` other than `none`, the
published odometry is in metres: p_odom = s * p_map + o, with s = exp(lambda) metres per
map unit and o an offset. lambda is filtered here, beside the 13-state EKF, which keeps
running in map units (the tracker, the map and the adjustment are unchanged).

The filter has one state. Its prediction grows lambda's variance with the distance
travelled and the angle turned (monocular scale drift: `scale_drift_per_sqrt_m`,
`scale_drift_per_sqrt_rad`), and by REBOOTSTRAP_LOG_SIGMA^2 at a re-bootstrap. Its
measurements, each weighted by a Huber rule on its normalised innovation (a wrong plane
or a slip moves the scale by a bounded step), come from
- `camera_height`: the camera's height above the ground plane fitted to map points
  (ground_plane.py) against `camera_height_m`: z = log(camera_height_m / h_map);
- `odometry`: an external (wheel) odometry: over windows of at least
  `scale_odom_window_s` and `scale_odom_min_distance_m`, the distance it travelled against
  ours: z = log of the median of the sub-segments' ratios.

Publishing. Until the first measurement nothing is published (the frame is not `ok`;
`~/status` says 'waiting'): metres were asked for. Until lambda's sigma first falls below
SETTLED_LOG_SIGMA, a new scale rescales the whole path and map about the world origin;
whenever it rises above UNSETTLED_LOG_SIGMA again (a re-bootstrap, a long turn without
measurements), the path since then about the camera's position at that moment (the
pivot). Once settled, every change rescales about the current camera (o absorbs it): the
published pose is continuous, and the map, transformed by the same (s, o), stays
consistent with it.

Covariance. Position: s^2 P_pp plus the covariance of e_p, the position error the scale
has made, a Schmidt consider term kept with its cross-covariance c to lambda: each
published step d adds d_lambda * d to e_p (its covariance grows by d c^T + c d^T +
var d d^T, c by var d), and each measurement shrinks c by the factor it shrinks lambda's
variance, so errors made before it no longer cancel those after (on a loop, a fully
correlated model would let the covariance shrink back as the robot returns). Twist: the
linear part is scaled and gains sigma_lambda^2 v v^T. With `camera_height`, the height's
own uncertainty (camera_height_sigma_m) is a bias no averaging removes: it is added to
the published sigma.

Map units (`scale_source: none`, docs/method.md §16.7). The published pose stays in
map units, but the map's scale drifts away from the bootstrap baseline that defines the
unit, and the filter's covariance (relative to the map, plus §14's terms) does not carry
that: lambda is then the log of the scale error, zero at the first bootstrap, its variance
growing by `scale_drift_per_sqrt_depth`^2 per median scene depth travelled (the unit is
arbitrary, depths are not) and `scale_drift_per_sqrt_rad`^2 per radian turned; the same
consider terms add the position error it makes, and sigma^2 v v^T to the twist.

Pure numpy; no ROS types. Stamps are integer nanoseconds.
"""
from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass

import numpy as np

from ..config import NodeConfig, VoConfig
from . import geometry as geo
from .frame_result import FrameResult
from .frames import optical_to_body_extrinsic
from .ground_plane import fit_ground_plane, ground_candidates

logger = logging.getLogger(__name__)

#: lambda's standard deviation before any measurement (a factor e either way)
PRIOR_LOG_SIGMA = 1.0
#: a re-bootstrap starts a new map whose scale is carried over from the speed: it is
#: this uncertain (log) relative to the old one
REBOOTSTRAP_LOG_SIGMA = 0.3
#: floor of one ground-plane measurement's log-height noise: the fits of consecutive
#: frames share points; their per-frame spread on KITTI 06 is 0.03 (§16.2)
GROUND_FIT_LOG_SIGMA = 0.05
#: until the filter's log-scale sigma first falls below this, a new scale rescales the
#: whole path about the origin; afterwards about the current camera (no jumps)
SETTLED_LOG_SIGMA = 0.03
#: once settled, a sigma above this (a re-bootstrap, a long turn without measurements)
#: unsettles it: the path from where the camera is then is rescaled as a whole again
UNSETTLED_LOG_SIGMA = 0.06
#: Huber threshold on a measurement's normalised innovation
HUBER_K = 2.0
#: sub-segments of an odometry window (the median survives two slipping ones)
ODOM_SUBSEGMENTS = 5
#: a window whose odometry stays under scale_odom_min_distance_m for this many window
#: lengths starts afresh (the robot stands)
STILL_WINDOWS = 5
#: `~/status` says 'coasting' after this long without a scale measurement [s]
COASTING_AFTER_S = 2.0
#: external odometry samples kept [s]
ODOM_HISTORY_S = 30.0


@dataclass
class ScaleStatus:
    """What `~/status` says about the scale."""

    source: str
    scale: float             #: metres per map unit
    sigma_pct: float         #: published 1-sigma of the scale [%]
    updates: int             #: measurements used
    downweighted: int        #: measurements the Huber rule down-weighted
    state: str               #: 'map units', 'waiting', 'metric' or 'coasting'

    def as_status(self) -> dict:
        return {'scale_source': self.source, 'scale': round(self.scale, 5),
                'scale_sigma_pct': round(self.sigma_pct, 2), 'scale_updates': self.updates,
                'scale_downweighted': self.downweighted, 'scale_state': self.state}


class ScaleFilter:
    """lambda = log(metres per map unit), one state, its variance, Huber-weighted updates."""

    def __init__(self) -> None:
        self.log_scale = 0.0
        self.var = PRIOR_LOG_SIGMA ** 2
        self.updates = 0
        self.downweighted = 0

    def predict(self, var_increase: float) -> None:
        self.var += max(var_increase, 0.0)

    def update(self, z: float, r: float) -> bool:
        """Fuse z = lambda + noise(r). Returns False when Huber down-weighted it."""
        s = self.var + r
        nu = z - self.log_scale
        norm = abs(nu) / math.sqrt(s)
        full = norm <= HUBER_K
        if not full:               # Huber: the innovation counts as HUBER_K sigma at most
            r = s * norm / HUBER_K - self.var
            s = self.var + r
            self.downweighted += 1
        gain = self.var / s
        self.log_scale += gain * nu
        self.var *= 1.0 - gain
        self.updates += 1
        return full


class OdometryWindows:
    """Scale measurements from an external odometry's travelled distance (see module)."""

    def __init__(self, window_s: float, min_distance_m: float, sigma_rel: float) -> None:
        self.window_ns = int(window_s * 1e9)
        self.min_distance_m = min_distance_m
        self.sigma_rel = sigma_rel
        self._odom: collections.deque = collections.deque()      # (stamp_ns, xyz)
        self._frames: list = []       # (stamp_ns, p_cam_map, base lever in world [m])
        self.restart()

    def add_odometry(self, stamp_ns: int, xyz: np.ndarray) -> bool:
        """False (not used) when `stamp_ns` is not after the last one."""
        if self._odom and stamp_ns <= self._odom[-1][0]:
            return False
        self._odom.append((int(stamp_ns), np.asarray(xyz, float)))
        while self._odom and self._odom[0][0] < stamp_ns - ODOM_HISTORY_S * 1e9:
            self._odom.popleft()
        return True

    def restart(self) -> None:
        """A new map (new units): the frames so far no longer compare."""
        self._frames = []

    def add_frame(self, stamp_ns: int, p_cam_map: np.ndarray, lever_world_m: np.ndarray
                  ) -> tuple[float, float] | None:
        """Record an ok frame; returns (z, r) when a window is complete."""
        self._frames.append((int(stamp_ns), p_cam_map.copy(), lever_world_m.copy()))
        if len(self._odom) < 2:
            return None
        last_odom = self._odom[-1][0]
        done = [f for f in self._frames if f[0] <= last_odom]
        if len(done) < ODOM_SUBSEGMENTS + 1 or done[-1][0] - done[0][0] < self.window_ns:
            return None
        first, last = self._odom_at(done[0][0]), self._odom_at(done[-1][0])
        if first is None or last is None or \
                np.linalg.norm(last - first) < self.min_distance_m:
            # too little motion yet: the window grows (a slow robot), or starts afresh
            # when the robot stands for STILL_WINDOWS window lengths
            if done[-1][0] - done[0][0] > STILL_WINDOWS * self.window_ns:
                self._frames = self._frames[len(done) - 1:]
            return None
        self._frames = self._frames[len(done) - 1:]     # the next window starts here
        return self._measure(done)

    def _odom_at(self, stamp_ns: int) -> np.ndarray | None:
        """The odometry position at `stamp_ns`, linearly interpolated; None outside."""
        stamps = np.fromiter((o[0] for o in self._odom), np.int64, len(self._odom))
        if not stamps[0] <= stamp_ns <= stamps[-1]:
            return None
        xyz = np.array([o[1] for o in self._odom])
        return np.array([np.interp(stamp_ns, stamps, xyz[:, k]) for k in range(3)])

    def _measure(self, window: list) -> tuple[float, float] | None:
        cuts = np.linspace(0, len(window) - 1, ODOM_SUBSEGMENTS + 1).round().astype(int)
        ratios = []
        for i, j in zip(cuts[:-1], cuts[1:]):
            (t1, p1, l1), (t2, p2, l2) = window[i], window[j]
            o1, o2 = self._odom_at(t1), self._odom_at(t2)
            if o1 is None or o2 is None or j <= i:
                continue
            d = float(np.linalg.norm(o2 - o1))
            if d < 0.5 * self.min_distance_m / ODOM_SUBSEGMENTS:
                continue                       # (nearly) standing: no scale in it
            s = _scale_for_chord(p2 - p1, l2 - l1, d)
            if s is not None:
                ratios.append(math.log(s))
        if len(ratios) < 3:
            return None
        ratios = np.array(ratios)
        logger.debug('odometry window: sub-segment scales %s', np.round(np.exp(ratios), 4))
        z = float(np.median(ratios))
        mad = 1.4826 * float(np.median(np.abs(ratios - z)))
        return z, self.sigma_rel ** 2 + mad ** 2 / len(ratios)


def _scale_for_chord(a: np.ndarray, b: np.ndarray, d: float) -> float | None:
    """s > 0 with |s a + b| = d: the camera moved a (map units), the base's lever arm
    turned by b (metres), the base travelled d metres in a straight line."""
    aa, ab, bb = a @ a, a @ b, b @ b
    if aa <= 0:
        return None
    disc = ab * ab - aa * (bb - d * d)
    if disc < 0:
        return None
    s = (-ab + math.sqrt(disc)) / aa
    return s if s > 0 else None


class MetricScale:
    """The map's scale for one estimator's world, and FrameResults converted to metres."""

    def __init__(self, cfg: VoConfig, T_base_cam: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.source = cfg.scale_source
        if T_base_cam is None:           # vo_node's default extrinsic (config.NodeConfig)
            node = NodeConfig()
            T_base_cam = optical_to_body_extrinsic(node.T_base_cam_xyz, node.T_base_cam_xyzw)
        T_bc = np.asarray(T_base_cam, float)
        #: gravity in the camera optical frame (the base's -z) and the base origin there
        self.down_cam = T_bc[:3, :3].T @ np.array([0.0, 0.0, -1.0])
        self.base_in_cam = -T_bc[:3, :3].T @ T_bc[:3, 3]
        self._rng = np.random.default_rng(0)
        self.odometry = OdometryWindows(cfg.scale_odom_window_s,
                                        cfg.scale_odom_min_distance_m, cfg.scale_odom_sigma)
        self.reset()

    @property
    def active(self) -> bool:
        return self.source != 'none'

    def reset(self) -> None:
        """A new world (new estimator): the scale is unknown again."""
        self.filter = ScaleFilter()
        if not self.active:
            self.filter.var = 0.0        # map units: the bootstrap baseline IS the unit
        self.scale = 1.0                 # published metres per map unit
        self.offset = np.zeros(3)        # published p = scale * p_map + offset
        self._down_world: np.ndarray | None = None
        self._last_p_map: np.ndarray | None = None
        self._last_R = np.eye(3)
        #: the published position's error from the scale (Schmidt consider terms): its
        #: covariance [m^2] and its cross-covariance with lambda [m]
        self._P_pp = np.zeros((3, 3))
        self._c_lp = np.zeros(3)
        #: rescaled about the camera from now on (map units: nothing is ever rescaled)
        self._settled = not self.active
        #: while unsettled, the scale changes about this map point (map units), which
        #: stays where it was published (metres); with the two terms at that moment
        self._pivot = (np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3))
        self.last_fix_ns: int | None = None
        self.last_frame_ns: int | None = None
        self.odometry.restart()

    def add_odometry(self, stamp_ns: int, xyz: np.ndarray) -> bool:
        """An external odometry's position; False when its stamp is not after the last."""
        return self.odometry.add_odometry(stamp_ns, xyz)

    @property
    def bias_var(self) -> float:
        if self.source != 'camera_height':
            return 0.0
        return (self.cfg.camera_height_sigma_m / self.cfg.camera_height_m) ** 2

    @property
    def published_sigma(self) -> float:
        return math.sqrt(self.filter.var + self.bias_var)

    def points(self, X_map: np.ndarray) -> np.ndarray:
        """Map points in the published (metric) frame."""
        return self.scale * np.asarray(X_map, float) + self.offset

    # ------------------------------------------------------------------ per frame
    def apply(self, res: FrameResult, X_world: np.ndarray, n_obs: np.ndarray) -> None:
        """Update the scale with this frame and convert `res` to metres in place (map
        units: add the scale drift's error to its covariance)."""
        if not (res.ok and res.T_world_cam is not None):
            return
        if res.orientation_only:
            # before a map: no position to scale (it is the attach point, published as
            # unknown); put it where later frames will be published
            if self.active and self.filter.updates:
                res.T_world_cam = res.T_world_cam.copy()
                res.T_world_cam[:3, 3] = self.points(res.T_world_cam[:3, 3])
            return
        if not self.active:
            self._drift_in_map_units(res, X_world)
            return
        T = res.T_world_cam
        p_map = T[:3, 3].copy()
        if self._down_world is None:
            self._down_world = T[:3, :3] @ self.down_cam
        if res.bootstrapped and self._last_p_map is not None:
            # a new map, attached where the camera is, in units carried over from the
            # speed (the sigma rise unsettles the scale, below)
            self.filter.predict(REBOOTSTRAP_LOG_SIGMA ** 2)
            self.odometry.restart()
        if self._last_p_map is not None:
            # the map's scale drifts as it is renewed: with the distance travelled, and
            # with the angle turned (a turn in place replaces the points in view)
            step_m = self.scale * float(np.linalg.norm(p_map - self._last_p_map))
            self.filter.predict(self.cfg.scale_drift_per_sqrt_m ** 2 * step_m +
                                self.cfg.scale_drift_per_sqrt_rad ** 2 *
                                self._turn_rad(T[:3, :3]))
            if self._settled and math.sqrt(self.filter.var) > UNSETTLED_LOG_SIGMA:
                # the scale is uncertain again: settle it anew, about where the camera is
                self._pivot = (p_map, self.points(p_map), self._P_pp.copy(),
                               self._c_lp.copy())
                self._settled = False
        self._last_R = T[:3, :3].copy()
        self._measure(res, T, X_world, n_obs)
        self.last_frame_ns = res.stamp_ns
        self._publish_scale(p_map)
        if not self.filter.updates:
            # odometry in metres was asked for: nothing is published in map units
            res.ok = False
            res.message = f'tracking; waiting for the metric scale ({self.source})'
            # ~/status: WARN with the reason (DEGRADED), not an error
            res.health, res.health_reason = 'degraded', res.message
            return
        self._convert(res)

    def _drift_in_map_units(self, res: FrameResult, X_world: np.ndarray) -> None:
        """scale_source none: the scale error's variance grows per scene depth travelled
        and per radian turned; its position error is published (module docstring)."""
        T = res.T_world_cam
        p_map = T[:3, 3].copy()
        if res.bootstrapped and self._last_p_map is not None:
            self.filter.predict(REBOOTSTRAP_LOG_SIGMA ** 2)   # scale carried by the speed
        if self._last_p_map is not None:
            # distance in median scene depths: the map unit is arbitrary, depths are not
            ahead = geo.median_depth(X_world, T)
            step = float(np.linalg.norm(p_map - self._last_p_map))
            depths = step / ahead if ahead else 0.0
            self.filter.predict(self.cfg.scale_drift_per_sqrt_depth ** 2 * depths +
                                self.cfg.scale_drift_per_sqrt_rad ** 2 *
                                self._turn_rad(T[:3, :3]))
        self._last_R = T[:3, :3].copy()
        self.last_frame_ns = res.stamp_ns
        if self._last_p_map is None:
            self._last_p_map = p_map          # the first pose: the error starts here
        self._publish_scale(p_map)
        self._convert(res)

    def _turn_rad(self, R_world_cam: np.ndarray) -> float:
        """Angle turned since the last frame [rad]."""
        cos_turn = (np.trace(self._last_R.T @ R_world_cam) - 1.0) / 2.0
        return math.acos(min(max(cos_turn, -1.0), 1.0))

    def _measure(self, res: FrameResult, T: np.ndarray, X_world: np.ndarray,
                 n_obs: np.ndarray) -> None:
        z_r = None
        if self.source == 'camera_height':
            rel = ground_candidates(X_world, n_obs, T, self._down_world)
            plane = fit_ground_plane(rel, self._down_world, self.cfg.ground_max_tilt_deg,
                                     self._rng)
            if plane is not None:
                r = max(plane.spread ** 2 / plane.n_inliers, GROUND_FIT_LOG_SIGMA ** 2)
                z_r = (math.log(self.cfg.camera_height_m / plane.height), r)
        elif self.source == 'odometry':
            z_r = self.odometry.add_frame(res.stamp_ns, T[:3, 3], T[:3, :3] @
                                          self.base_in_cam)
        if z_r is not None and all(math.isfinite(v) for v in z_r):
            before = self.published_sigma ** 2
            full = self.filter.update(*z_r)
            # the update decorrelates lambda from the position errors made so far
            shrink = self.published_sigma ** 2 / before
            self._c_lp = self._c_lp * shrink
            self._pivot = self._pivot[:3] + (self._pivot[3] * shrink,)
            logger.debug('scale measurement %.4f (sigma %.4f)%s -> scale %.4f', math.exp(
                z_r[0]), math.sqrt(z_r[1]), '' if full else ' down-weighted',
                math.exp(self.filter.log_scale))
            self.last_fix_ns = res.stamp_ns

    def _publish_scale(self, p_map: np.ndarray) -> None:
        new = math.exp(self.filter.log_scale)
        var = self.published_sigma ** 2
        if not self._settled:
            # the scale is still settling: the path since the pivot (the world origin, or
            # a re-bootstrap's attach point) is rescaled as a whole about it, so its
            # error is the pivot's plus d lambda times the metres since it
            pivot_map, pivot_published, P_pp, c_lp = self._pivot
            self.offset = pivot_published - new * pivot_map
            d = new * (p_map - pivot_map)
            self._P_pp = P_pp + np.outer(d, c_lp) + np.outer(c_lp, d) + var * np.outer(d, d)
            self._c_lp = c_lp + var * d
        else:
            # later: about the current camera, so the published pose does not jump; each
            # step's error is d lambda times the step, correlated with the earlier ones as
            # far as lambda has not been measured since
            self.offset = self.offset + (self.scale - new) * p_map
            d = new * (p_map - self._last_p_map)
            self._P_pp = self._P_pp + np.outer(d, self._c_lp) + np.outer(self._c_lp, d) + \
                var * np.outer(d, d)
            self._c_lp = self._c_lp + var * d
        self._settled = self._settled or math.sqrt(self.filter.var) < SETTLED_LOG_SIGMA
        self.scale = new
        self._last_p_map = p_map

    def _convert(self, res: FrameResult) -> None:
        s, sigma = self.scale, self.published_sigma
        T = res.T_world_cam.copy()
        T[:3, 3] = self.points(T[:3, 3])
        res.T_world_cam = T
        S = np.diag([s, s, s, 1.0, 1.0, 1.0])
        res.pose_cov = S @ res.pose_cov @ S
        res.pose_cov[:3, :3] += 0.5 * (self._P_pp + self._P_pp.T)
        if res.twist_cam is not None:
            twist = res.twist_cam.copy()
            twist[:3] *= s
            res.twist_cam = twist
            res.twist_cov = S @ res.twist_cov @ S
            res.twist_cov[:3, :3] += sigma ** 2 * np.outer(twist[:3], twist[:3])

    def status(self) -> ScaleStatus:
        if not self.active:
            state = 'map units'
        elif self.filter.updates == 0:
            state = 'waiting'
        elif self.last_frame_ns - self.last_fix_ns > COASTING_AFTER_S * 1e9:
            state = 'coasting'          # no measurement lately: the uncertainty grows
        else:
            state = 'metric'
        return ScaleStatus(self.source, self.scale, 100.0 * self.published_sigma,
                           self.filter.updates, self.filter.downweighted, state)

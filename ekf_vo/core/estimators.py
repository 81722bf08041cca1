"""The one place that chooses how a tracked frame moves the filter: ekf | iekf | joint | epnp.

Every estimator owns the prediction and the update of the filter state behind one
interface, so the pipeline (pipeline.py) never branches on the estimator:

    predict(dt)            propagate the state over dt seconds (docs/method.md §3)
    update(matches, rng)   use this frame's 2D-3D matches; returns which were inliers

- EkfEstimator   `estimator: ekf | iekf`, `map_refinement: none`: the hybrid camera-only
                 filter, the robust update (robust_update.py) over the fixed map points
                 (§5, §6); iekf = iterated update.
- JointEstimator `map_refinement: filter`: the same robust update on the joint state
                 camera + in-filter inverse depths (point_filter.py, §8).
- EpnpEstimator  `estimator: epnp`: the paper's baseline; each frame's pose is
                 overwritten by EPnP + refinement on that frame alone (pnp.py, §9).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import VoConfig
from .ekf import VEL, CameraEKF
from .observation import ReprojectionModel, whitening
from .pnp import solve_epnp
from .point_filter import PointFilter
from .robust_update import RansacSettings, robust_update


@dataclass
class FrameMatches:
    """One frame's measurements: map points, then in-filter points (ideal pixels)."""

    z_map: np.ndarray                 #: (a,2) pixels of the matched map points
    X_map: np.ndarray                 #: (a,3) their fixed world positions
    z_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  #: (b,2)
    point_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  #: (b,)
    #: (a,) pixel std of each map measurement (pixel noise + the point's own uncertainty,
    #: docs/method.md §12.3); None = pixel_sigma_px for all
    sigma_map: np.ndarray | None = None
    #: (a,2,2) [px^2] noise added to each map measurement's pixel noise: the spread of a
    #: point without depth along its epipolar line (bearing.py); None = none
    extra_cov_px2: np.ndarray | None = None

    def map_sigmas(self, pixel_sigma_px: float) -> np.ndarray:
        """(a,) pixel std of the map measurements."""
        if self.sigma_map is None:
            return np.full(len(self.X_map), float(pixel_sigma_px))
        return np.asarray(self.sigma_map, float)

    def map_measurements(self, intrinsics: np.ndarray, pixel_sigma_px: float
                         ) -> tuple[ReprojectionModel, np.ndarray, np.ndarray]:
        """(model, pixels (a,2), pixel std (a,)) of the map measurements for the robust
        update. With extra noise, each measurement's sigma_i^2 I + C_i is whitened to
        pixel_sigma_px: the model and the pixels both carry W_i (observation.py)."""
        model = ReprojectionModel.of_map_points(intrinsics, self.X_map)
        sigma = self.map_sigmas(pixel_sigma_px)
        z = np.asarray(self.z_map, float).reshape(-1, 2)
        if self.extra_cov_px2 is None or not len(z):
            return model, z, sigma
        R = self.extra_cov_px2 + (sigma ** 2)[:, None, None] * np.eye(2)
        model.whiten = whitening(R, pixel_sigma_px)
        z = np.einsum('nij,nj->ni', model.whiten, z)
        return model, z, np.full(len(z), float(pixel_sigma_px))


@dataclass
class UpdateOutcome:
    """Inlier verdicts of one update, in the order of FrameMatches."""

    map_inliers: np.ndarray           #: (a,) bool
    point_inliers: np.ndarray         #: (b,) bool


class EkfEstimator:
    """Hybrid camera-only EKF / IEKF with the robust update over fixed map points."""

    def __init__(self, cfg: VoConfig, ekf: CameraEKF) -> None:
        self.cfg, self.ekf = cfg, ekf
        self.settings = RansacSettings.from_config(cfg)
        #: linear acceleration impulse std in this map's units [u/s^2] (set_map_speed)
        self.accel_sigma = float(cfg.accel_sigma)

    def set_map_speed(self, speed: float) -> None:
        """A new map, in which the camera moved at `speed` [map units/s] over its
        bootstrap pair: the acceleration noise is at least accel_sigma_per_speed times
        that (docs/method.md §3.2). A map's unit is the bootstrap baseline, so an
        acceleration in m/s^2 is a different motion in each map."""
        c = self.cfg
        self.accel_sigma = max(float(c.accel_sigma),
                               float(c.accel_sigma_per_speed) * max(float(speed), 0.0))

    def predict(self, dt: float) -> None:
        c = self.cfg
        self.ekf.predict(dt, self.accel_sigma, c.angular_accel_sigma, c.fading_memory,
                         c.stamp_sigma_s)

    def update(self, matches: FrameMatches, rng: np.random.Generator) -> UpdateOutcome:
        model, z, sigma = matches.map_measurements(self.ekf.intrinsics,
                                                   self.cfg.pixel_sigma_px)
        x, P, out = robust_update(self.ekf.x, self.ekf.P, z, model, sigma, rng,
                                  self.settings)
        self.ekf.x, self.ekf.P, self.ekf.last_update = x, P, out.stats
        return UpdateOutcome(out.inliers, np.zeros(0, bool))


class JointEstimator(EkfEstimator):
    """Camera + in-filter inverse-depth points, one robust update on the joint state."""

    def __init__(self, cfg: VoConfig, ekf: CameraEKF, points: PointFilter) -> None:
        super().__init__(cfg, ekf)
        self.points = points

    def predict(self, dt: float) -> None:
        # the camera-point cross-covariance uses F at the prior state: before the camera
        self.points.predict(self.ekf.x, dt, self.cfg.fading_memory)
        super().predict(dt)

    def update(self, matches: FrameMatches, rng: np.random.Generator) -> UpdateOutcome:
        pts = self.points
        map_model, z_map, sigma_map = matches.map_measurements(self.ekf.intrinsics,
                                                               self.cfg.pixel_sigma_px)
        model = pts.measurements(matches.X_map, matches.point_rows)
        b = len(matches.point_rows)
        if map_model.whiten is not None:       # the filter points' noise is isotropic
            model.whiten = np.concatenate((map_model.whiten,
                                           np.broadcast_to(np.eye(2), (b, 2, 2))))
        z = np.concatenate((z_map, np.asarray(matches.z_points, float).reshape(-1, 2)))
        x, P = pts.joint(self.ekf)
        sigma = np.concatenate((sigma_map, np.full(b, self.cfg.pixel_sigma_px)))
        x, P, out = robust_update(x, P, z, model, sigma, rng, self.settings)
        pts.set_joint(self.ekf, x, P)
        self.ekf.last_update = out.stats
        a = len(matches.X_map)
        pts.record_verdicts(matches.point_rows, out.inliers[a:])
        return UpdateOutcome(out.inliers[:a], out.inliers[a:])


class EpnpEstimator(EkfEstimator):
    """Baseline: the pose is overwritten by per-frame EPnP + LM; velocity by difference."""

    def __init__(self, cfg: VoConfig, ekf: CameraEKF) -> None:
        super().__init__(cfg, ekf)
        self._T_world_cam_prev: np.ndarray | None = None
        self._dt = cfg.default_dt_s

    def predict(self, dt: float) -> None:
        self._T_world_cam_prev, self._dt = self.ekf.T_world_cam, dt
        super().predict(dt)

    def update(self, matches: FrameMatches, rng: np.random.Generator) -> UpdateOutcome:
        c = self.cfg
        pnp = solve_epnp(matches.z_map, matches.X_map, self.ekf.intrinsics,
                         c.pixel_sigma_px, c.ransac_inlier_px)
        if not pnp.ok:
            return UpdateOutcome(np.zeros(len(matches.z_map), bool), np.zeros(0, bool))
        if self._T_world_cam_prev is not None:
            self.ekf.x[VEL] = (pnp.T_world_cam[:3, 3] - self._T_world_cam_prev[:3, 3]) \
                / self._dt
        self.ekf.set_pose(pnp.T_world_cam, pnp.pose_cov)
        return UpdateOutcome(pnp.inliers, np.zeros(0, bool))


def make_estimator(cfg: VoConfig, ekf: CameraEKF, points: PointFilter | None
                   ) -> EkfEstimator:
    """The estimator the configuration asks for (`estimator`, `map_refinement`)."""
    if cfg.estimator == 'epnp':
        return EpnpEstimator(cfg, ekf)
    if points is not None:
        return JointEstimator(cfg, ekf, points)
    return EkfEstimator(cfg, ekf)

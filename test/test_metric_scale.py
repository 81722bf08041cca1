"""Metric scale (core/metric_scale.py, core/ground_plane.py, docs/method.md §16)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ekf_vo.config import ConfigError, VoConfig
from ekf_vo.core.frame_result import FrameResult, TrackingState
from ekf_vo.core.frames import optical_to_body_extrinsic
from ekf_vo.core.ground_plane import fit_ground_plane, ground_candidates
from ekf_vo.core.metric_scale import MetricScale, OdometryWindows, ScaleFilter
from ekf_vo.tools.run import run_bag
from ekf_vo.tools.synth import SynthConfig, write_bag
from ekf_vo.tools.synth_scene import GROUND_ROBOT_T_BASE_CAM_XYZ
from ekf_vo.tools.wheel_odometry import WheelNoise

from .support.data import need_shared_data


def _cfg(**kw) -> VoConfig:
    return VoConfig.from_mapping({**dataclasses.asdict(VoConfig()), **kw})


def test_camera_height_source_needs_the_height():
    with pytest.raises(ConfigError, match='camera_height_m'):
        _cfg(scale_source='camera_height')
    assert _cfg(scale_source='camera_height', camera_height_m=1.65).camera_height_m == 1.65


def test_the_scale_filter_converges_and_bounds_an_outlier_step():
    rng = np.random.default_rng(1)
    f = ScaleFilter()
    true = math.log(2.5)
    for _ in range(200):
        f.update(true + 0.05 * rng.standard_normal(), 0.05 ** 2)
    assert abs(f.log_scale - true) < 3 * math.sqrt(f.var)
    before, n_down = f.log_scale, f.downweighted
    assert n_down < 20                                 # ~5 % of Gaussian ones beyond 2 sigma
    assert not f.update(true + 5.0, 0.05 ** 2)          # 100 sigma away: Huber
    # a full update would move it by 5 * var / (var + r) ~ 0.025; Huber: 2 sigma at most
    assert abs(f.log_scale - before) < 2.0 * math.sqrt(f.var + 0.05 ** 2) * 0.05
    assert f.downweighted == n_down + 1


def _camera_over_plane(height: float, rng: np.random.Generator):
    """Points on a road `height` below a level camera (optical y down) from 1.5 to 30
    heights ahead, clutter above it nearby (a car) and a verge out of the corridor."""
    T = np.eye(4)
    road = np.column_stack((rng.uniform(-1, 1, 300) * height, np.full(300, height),
                            rng.uniform(1.5, 30, 300) * height))
    road[:, 1] += 0.01 * height * rng.standard_normal(300)
    car = np.column_stack((rng.uniform(-1, 1, 60), rng.uniform(0.3, 0.8, 60),
                           rng.uniform(3, 4, 60))) * height
    verge = np.column_stack((rng.uniform(2, 4, 60), np.full(60, 0.8),
                             rng.uniform(1.5, 5, 60))) * height
    X = np.vstack((road, car, verge))
    return T, X, np.full(len(X), 5)


def test_the_ground_plane_is_the_road_not_the_clutter():
    rng = np.random.default_rng(2)
    T, X, n_obs = _camera_over_plane(0.7, rng)
    down = np.array([0.0, 1.0, 0.0])
    rel = ground_candidates(X, n_obs, T, down)
    plane = fit_ground_plane(rel, down, 15.0, np.random.default_rng(0))
    assert plane is not None
    assert plane.height == pytest.approx(0.7, rel=0.01)
    assert plane.normal @ down > math.cos(math.radians(2))
    # too few observations: no candidates, no plane
    assert fit_ground_plane(ground_candidates(X, np.ones(len(X)), T, down), down, 15.0,
                            np.random.default_rng(0)) is None


def test_odometry_windows_survive_a_slip_episode():
    """Map units are 1/2.0 m; one of five sub-segments reads 30 % too far."""
    win = OdometryWindows(window_s=2.0, min_distance_m=0.3, sigma_rel=0.02)
    stamps = np.arange(0, 3.0, 1 / 30)
    speed = 0.5                                        # m/s along x
    slip = (stamps > 0.5) & (stamps < 0.9)
    odom_x = np.cumsum(np.where(slip, 1.3, 1.0) * speed / 30)
    for t, x in zip(stamps, odom_x):
        win.add_odometry(int(t * 1e9), np.array([x, 0.0, 0.0]))
    out = None
    for t in stamps:
        p_map = np.array([0.0, 0.0, speed * t / 2.0])  # camera z forward, map units
        out = win.add_frame(int(t * 1e9), p_map, np.zeros(3)) or out
    assert out is not None
    z, r = out
    assert math.exp(z) == pytest.approx(2.0, rel=0.02)
    assert 0 < r < 0.05 ** 2


def _frame(stamp_ns: int, p: np.ndarray, v: np.ndarray) -> FrameResult:
    T = np.eye(4)
    T[:3, 3] = p
    return FrameResult(stamp_ns, TrackingState.TRACKING, ok=True, T_world_cam=T,
                       pose_cov=np.eye(6) * 1e-4, twist_cam=np.concatenate((v, np.zeros(3))),
                       twist_cov=np.eye(6) * 1e-4)


def test_published_odometry_waits_for_the_scale_then_never_jumps():
    """A camera at 0.4 m/s (map units of 0.5 m) with wheel odometry of the base."""
    cfg = _cfg(scale_source='odometry', scale_odom_window_s=1.0)
    T_bc = optical_to_body_extrinsic((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5))
    scale = MetricScale(cfg, T_bc)
    rng = np.random.default_rng(3)
    published, first_ok = [], None
    for k in range(300):
        t = k / 30
        scale.add_odometry(int(t * 1e9), np.array([0.4 * t * (1 + 0.01 * rng.standard_normal()),
                                                   0.0, 0.0]))
        res = _frame(int(t * 1e9), np.array([0.0, 0.0, 0.8 * t]), np.array([0, 0, 0.8]))
        scale.apply(res, np.zeros((0, 3)), np.zeros(0, int))
        if res.ok:
            first_ok = k if first_ok is None else first_ok
            published.append((res.T_world_cam[:3, 3].copy(), res.pose_cov.copy(),
                              res.twist_cam.copy(), scale.points(np.array([[0, 0, 0.8 * t]]))))
        else:
            assert 'waiting for the metric scale' in res.message
            assert res.health == 'degraded'          # ~/status: WARN, with the reason
    assert first_ok is not None and first_ok >= 30           # a window of 1 s first
    assert scale.status().state == 'metric'
    assert scale.scale == pytest.approx(0.5, rel=0.02)
    steps = np.diff([p[2] for p, *_ in published[-100:]])
    assert np.all(np.abs(steps - 0.4 / 30) < 0.002)          # continuous, about 1.3 cm
    for p, cov, twist, X in published:
        assert np.allclose(X[0], p)                          # the map moves with the pose
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert published[-1][2][2] == pytest.approx(0.4, rel=0.02)   # twist in m/s
    # the position covariance carries the scale's uncertainty along the path
    assert published[-1][1][2, 2] > published[0][1][2, 2]


def test_kitti_camera_height_gives_metres():
    """KITTI 06 f0-50 through ekf-vo-run with the camera 1.65 m above the road (the
    bench: figures in docs/method.md §16.5; margins here are wider)."""
    folder = need_shared_data('kitti06_f0-50', 'metric scale test')
    import tempfile
    from pathlib import Path

    from ekf_vo.tools.convert import convert
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'kitti'
        convert('kitti', folder, bag)
        s = run_bag(bag, None, {'scale_source': 'camera_height', 'camera_height_m': 1.65})
    assert s.eval is not None
    assert abs(s.eval.scale_error_pct) < 5.0
    assert s.eval.ate_se3_pct_of_path < 2.0
    assert s.scale['scale_state'] == 'metric' and s.n_resets == 0


def test_synthetic_wheel_odometry_gives_metres(tmp_path):
    """The ground robot's first edge (no turn) with slipping wheel odometry in the bag."""
    bag = tmp_path / 'robot'
    write_bag(SynthConfig(trajectory='ground_robot', frames=170), bag,
              wheel_odom=WheelNoise(slip_share=0.2))
    params = {'T_base_cam_xyz': list(GROUND_ROBOT_T_BASE_CAM_XYZ)}
    s = run_bag(bag, params, {'scale_source': 'odometry'})
    assert s.eval is not None and s.scale['scale_updates'] >= 1
    assert abs(s.eval.scale_error_pct) < 3.0
    assert s.eval.ate_se3_pct_of_path < 3.0


def test_a_turn_or_a_rebootstrap_unsettles_the_scale_about_the_camera():
    """Turning in place grows the scale's uncertainty; a re-bootstrap lifts it past 6 %,
    and the path from there is rescaled about that point (which stays where it was
    published) until it settles again. Map units of 0.5 m."""
    cfg = _cfg(scale_source='odometry', scale_odom_window_s=1.0)
    scale = MetricScale(cfg, optical_to_body_extrinsic((0.0, 0.0, 0.0),
                                                       (-0.5, 0.5, -0.5, 0.5)))
    state = {'k': 0, 'z': 0.0, 'yaw': 0.0}

    def drive(n: int, speed_map: float, yaw_rate: float = 0.0, bootstrapped=False):
        for i in range(n):
            t = state['k'] / 30
            state['z'] += speed_map / 30
            state['yaw'] += yaw_rate / 30
            scale.add_odometry(int(t * 1e9), np.array([0.5 * state['z'], 0.0, 0.0]))
            res = _frame(int(t * 1e9), np.array([0.0, 0.0, state['z']]),
                         np.array([0, 0, speed_map]))
            c, s_ = math.cos(state['yaw']), math.sin(state['yaw'])
            res.T_world_cam[:3, :3] = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])
            res.bootstrapped = bootstrapped and i == 0
            scale.apply(res, np.zeros((0, 3)), np.zeros(0, int))
            state['k'] += 1
    drive(150, 0.8)                                  # 5 s straight: measured, settled
    assert scale.status().state == 'metric' and scale.published_sigma < 0.035
    sigma_before = scale.published_sigma
    drive(90, 0.0, yaw_rate=math.radians(30))        # 90 deg in place, nothing measured
    assert scale.published_sigma > sigma_before      # the turn renewed the map
    drive(1, 0.8, bootstrapped=True)                 # a new map: sigma + 30 %
    pivot_map, pivot_published = scale._pivot[:2]
    assert not scale._settled and scale.published_sigma > 0.06
    drive(45, 0.8)                                   # measured again
    assert np.allclose(scale.points(pivot_map), pivot_published)   # rescaled about it
    assert scale.scale == pytest.approx(0.5, rel=0.05)


def test_a_slow_robot_gets_its_scale_from_longer_windows():
    """0.1 m/s: a 1 s window holds 0.1 m, under scale_odom_min_distance_m (0.3 m): the
    window grows until the odometry has travelled that far."""
    win = OdometryWindows(window_s=1.0, min_distance_m=0.3, sigma_rel=0.02)
    out, first_at = None, None
    for k in range(300):
        t = k / 30
        win.add_odometry(int(t * 1e9), np.array([0.1 * t, 0.0, 0.0]))
        got = win.add_frame(int(t * 1e9), np.array([0.0, 0.0, 0.1 * t / 0.5]), np.zeros(3))
        if got is not None and first_at is None:
            first_at, out = t, got
    assert first_at is not None and 2.9 < first_at < 3.5
    assert math.exp(out[0]) == pytest.approx(0.5, rel=0.01)


def test_the_scale_error_does_not_cancel_on_a_loop_once_measured():
    """A loop back to the start: with scale measurements along the way, the position
    covariance from the scale does not shrink back to zero at the start point (a fully
    correlated model would say the loop closed exactly)."""
    cfg = _cfg(scale_source='odometry', scale_odom_window_s=1.0)
    scale = MetricScale(cfg, optical_to_body_extrinsic((0.0, 0.0, 0.0),
                                                       (-0.5, 0.5, -0.5, 0.5)))
    radius, n = 2.0, 900                         # a 2 m circle in map units, 30 s
    for k in range(n + 1):
        t = k / 30
        phi = 2 * math.pi * k / n
        p = radius * np.array([math.sin(phi), 0.0, 1 - math.cos(phi)])
        scale.add_odometry(int(t * 1e9), np.array([0.5 * p[0], 0.5 * p[2], 0.0]))
        res = _frame(int(t * 1e9), p, np.array([0, 0, 0.4]))
        scale.apply(res, np.zeros((0, 3)), np.zeros(0, int))
        if k == n // 2:
            halfway = np.trace(res.pose_cov[:3, :3])
    assert scale.filter.updates > 10
    end = np.trace(res.pose_cov[:3, :3])
    floor = np.trace(np.eye(3) * 1e-4) * scale.scale ** 2     # the EKF's own part
    assert end - floor > 0.1 * (halfway - floor) > 0


def test_bad_scale_odometry_is_rejected_and_counted():
    from ekf_vo.core.stream import VoStream
    stream = VoStream(_cfg(scale_source='odometry'))
    assert stream.add_scale_odometry(1_000, np.zeros(3)) is None
    r = stream.add_scale_odometry(2_000, np.array([np.nan, 0.0, 0.0]))
    assert r is not None and r.key == 'bad_scale_odom'
    r = stream.add_scale_odometry(500, np.zeros(3))
    assert r is not None and r.key == 'scale_odom_out_of_order'
    assert stream.add_scale_odometry(3_000, np.ones(3)) is None
    assert stream.counters['bad_scale_odom'] == 1
    assert stream.counters['scale_odom_out_of_order'] == 1


def test_in_map_units_the_covariance_carries_the_scale_drift():
    """scale_source none: the pose stays in map units, untouched; the scale error is
    zero at the first pose and grows with the depths travelled and the angle turned, and
    the published position and velocity covariances carry the error it makes."""
    X_ahead = np.array([[0.0, 0.0, 10.0 + z] for z in range(0, 400, 4)], float)

    def run(**kw):
        scale = MetricScale(_cfg(scale_source='none', **kw))
        out = []
        for k in range(200):                        # 20 map units straight ahead
            res = _frame(int(k * 1e8), np.array([0.0, 0.0, 0.1 * k]), np.array([0, 0, 1.0]))
            scale.apply(res, X_ahead, np.full(len(X_ahead), 3))
            out.append(res)
        return scale, out
    scale, out = run()
    assert all(np.allclose(r.T_world_cam[:3, 3], [0.0, 0.0, 0.1 * k]) for k, r in
               enumerate(out))
    assert out[0].pose_cov[0, 0] == pytest.approx(1e-4)        # the gauge: exact
    growth = [r.pose_cov[2, 2] - 1e-4 for r in out]
    assert all(b >= a for a, b in zip(growth, growth[1:])) and growth[-1] > 0
    # the median depth ahead is ~ 200 units: 20 units are 0.1 depths, sigma 0.02 * 0.32;
    # the position error ~ that times the distance / sqrt(3) (a random walk's integral)
    assert math.sqrt(growth[-1]) == pytest.approx(20 * 0.02 * math.sqrt(0.1) / math.sqrt(3),
                                                  rel=0.3)
    assert out[-1].twist_cov[2, 2] > 1e-4
    assert scale.status().state == 'map units' and scale.status().sigma_pct > 0
    _, still = run(scale_drift_per_sqrt_depth=0.0, scale_drift_per_sqrt_rad=0.0)
    assert all(np.allclose(r.pose_cov, np.eye(6) * 1e-4) for r in still)

"""A rolling shutter's readout estimated from the update's residuals (core/readout.py,
docs/method.md §15.17), on map points seen through a simulated rolling shutter."""
import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.core.readout import (MIN_APPLIED_S, MIN_FRAMES_APPLIED, SIGNIFICANCE,
                                 ReadoutEstimate, correction_rate, interaction_matrix)
from ekf_vo.core.rolling_shutter import rotation_to_stamp_time, translation_to_stamp_time

from .test_rolling_shutter import CAMERA, _project, _rolling_shutter_pixels


def _frame(rng, readout_s, omega_deg_s=60.0, noise_px=0.3):
    """One frame of 80 map points through a rolling shutter of `readout_s`: the stamp's
    pose, the motion, the points and their pixels as seen (with noise)."""
    T0 = geo.make_T(geo.rotvecs_to_matrices(rng.normal(0, 0.3, (1, 3)))[0], rng.normal(size=3))
    axis = rng.normal(size=3)
    omega = np.radians(omega_deg_s) * axis / np.linalg.norm(axis)
    v = rng.uniform(-1.0, 1.0, 3)
    X_c = np.column_stack((rng.uniform(-3, 3, 80), rng.uniform(-2, 2, 80),
                           rng.uniform(3, 8, 80)))
    X = X_c @ T0[:3, :3].T + T0[:3, 3]
    seen = _rolling_shutter_pixels(T0, omega, v, X, readout_s) + \
        rng.normal(0.0, noise_px, (len(X), 2))
    return T0, omega, v, X, seen


def _twist(T, omega, v):
    """(v_cam, omega_cam) of a camera at T moving at v (world) turning at omega (camera)."""
    return np.concatenate((T[:3, :3].T @ v, omega))


def _observe(est, T_est, omega, v, X, seen, used_s):
    """What the pipeline hands the estimate: the pixels corrected with `used_s` and their
    residuals from the estimated pose."""
    rows = seen[:, 1]
    px = translation_to_stamp_time(rotation_to_stamp_time(seen, rows, omega, used_s, CAMERA),
                                   rows, X, T_est, v, used_s, CAMERA)
    X_c = (X - T_est[:3, 3]) @ T_est[:3, :3]
    return est.observe(px, rows, X_c[:, 2], px - _project(T_est, X), _twist(T_est, omega, v),
                       CAMERA, used_s)


def test_the_rate_is_what_the_correction_does_per_second_of_readout():
    """correction_rate (the interaction matrix) against rolling_shutter.py's correction
    at a small readout: the same sign and size, to first order."""
    rng = np.random.default_rng(1)
    T0, omega, v, X, seen = _frame(rng, 0.0, omega_deg_s=90.0, noise_px=0.0)
    rows, step = seen[:, 1], 1e-3
    moved = translation_to_stamp_time(rotation_to_stamp_time(seen, rows, omega, step, CAMERA),
                                      rows, X, T0, v, step, CAMERA)
    X_c = (X - T0[:3, 3]) @ T0[:3, :3]
    L = interaction_matrix(seen, X_c[:, 2], CAMERA)
    d = correction_rate(L, rows, _twist(T0, omega, v), CAMERA)
    np.testing.assert_allclose(d, (seen - moved) / step, rtol=0.02, atol=0.5)
    assert np.max(np.abs(d)) > 100.0                       # px/s: the test says something


@pytest.mark.parametrize('used_s', [0.0, 0.01, 0.03])
def test_one_frame_measures_the_readout_whatever_the_pose_error(used_s):
    """A 20 ms readout, the pixels corrected with another, and a pose off by 0.3 deg and
    2 cm (what the update leaves): the pose's part is projected out, the readout's is
    not."""
    rng = np.random.default_rng(3)
    T0, omega, v, X, seen = _frame(rng, 0.02)
    off = geo.make_T(geo.rotvecs_to_matrices(np.radians([[0.3, -0.2, 0.1]]))[0],
                     np.array([0.02, -0.01, 0.015]))
    est = ReadoutEstimate(prior_s=0.0, max_s=0.05)
    frame = _observe(est, T0 @ off, omega, v, X, seen, used_s)
    assert frame == pytest.approx(0.02, abs=0.002)


def test_a_rolling_shutter_is_found_and_applied_once_significant():
    rng = np.random.default_rng(5)
    est = ReadoutEstimate(prior_s=0.0, max_s=0.05)
    assert est.applied_s == 0.0 and est.estimate_s is None
    for _ in range(30):
        T0, omega, v, X, seen = _frame(rng, 0.015)
        _observe(est, T0, omega, v, X, seen, est.applied_s)
    assert est.estimate_s == pytest.approx(0.015, abs=0.0015)
    assert est.estimate_s > SIGNIFICANCE * est.sigma_s
    # significant, but not yet applied: a young map's errors can look like a readout
    assert est.applied_s == 0.0
    for _ in range(MIN_FRAMES_APPLIED - 30):
        T0, omega, v, X, seen = _frame(rng, 0.015)
        _observe(est, T0, omega, v, X, seen, est.applied_s)
    assert est.estimate_s == pytest.approx(0.015, abs=0.0015)
    assert est.applied_s == est.estimate_s


def test_a_global_shutter_keeps_the_configured_readout():
    rng = np.random.default_rng(7)
    est = ReadoutEstimate(prior_s=0.0, max_s=0.05)
    for _ in range(100):
        T0, omega, v, X, seen = _frame(rng, 0.0, noise_px=0.5)
        _observe(est, T0, omega, v, X, seen, est.applied_s)
    assert abs(est.estimate_s) < MIN_APPLIED_S
    assert est.applied_s == 0.0


def test_a_camera_that_does_not_turn_or_move_says_nothing():
    rng = np.random.default_rng(9)
    est = ReadoutEstimate(prior_s=0.01, max_s=0.05)
    T0, _, _, X, seen = _frame(rng, 0.0, omega_deg_s=0.0)
    assert _observe(est, T0, np.zeros(3), np.zeros(3), X, seen, 0.01) is None
    assert est.estimate_s is None and est.applied_s == 0.01


def test_switched_off_it_keeps_the_configured_readout():
    rng = np.random.default_rng(11)
    est = ReadoutEstimate(prior_s=0.0, max_s=0.05, enabled=False)
    T0, omega, v, X, seen = _frame(rng, 0.02)
    assert _observe(est, T0, omega, v, X, seen, 0.0) is None
    assert est.applied_s == 0.0


def test_the_estimate_applied_is_bounded():
    rng = np.random.default_rng(13)
    est = ReadoutEstimate(prior_s=0.0, max_s=0.01)
    for _ in range(MIN_FRAMES_APPLIED):
        T0, omega, v, X, seen = _frame(rng, 0.03)
        _observe(est, T0, omega, v, X, seen, est.applied_s)
    assert est.applied_s == 0.01


def test_a_ground_robot_turning_in_place_finds_its_10_ms_readout():
    """The rendered ground robot through a 10 ms rolling shutter, `rolling_shutter_s`
    left at 0, past its first turn in place: the pipeline estimates the readout from its
    map and corrects the pixels with it once the turn shows it (measured: nothing
    applied while it drives straight, 6.4 ms from frame ~175 in the turn, 8.7 ms from
    the next turn's start at ~340, 10.1 ms at the end of the loop; docs/method.md
    §15.17)."""
    from ekf_vo.config import VoConfig
    from ekf_vo.core.camera import PinholeCamera
    from ekf_vo.core.stream import VoStream
    from ekf_vo.tools.synth import SynthConfig, SequenceRenderer
    cfg = SynthConfig(frames=760, seed=1, trajectory='ground_robot', rolling_shutter_s=0.01)
    renderer = SequenceRenderer(cfg)
    stream = VoStream(VoConfig().validate(), seed=0)
    stream.set_camera(PinholeCamera.from_camera_info(
        {'width': cfg.width, 'height': cfg.height, 'K': cfg.K(), 'D': cfg.D(),
         'distortion_model': 'plumb_bob'}))
    applied = []
    for k in range(360):
        stamp, img, _ = renderer.frame(k)
        res = stream.process(img, stamp)
        applied.append(res.readout_s)
    stream.vo.close()
    assert applied[:150] == [0.0] * 150                   # no turn yet: no evidence
    assert applied[-1] == pytest.approx(0.01, rel=0.3)
    assert res.readout_estimate_s == applied[-1]

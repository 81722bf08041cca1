"""Map growth (core/map_growth.py): candidates become points with the filter's poses, and
each new point's depth is corrected for the bias of a small parallax (docs/method.md §7.2.1)."""
import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.map import LandmarkMap
from ekf_vo.core.map_growth import NOISE_WINDOW_POINTS, MapGrowth

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _grow(debias: bool, sigma_px: float, n: int = 3000, seed: int = 1):
    """n tracks first seen at frame 0 and again at frame 1 after a 0.25 m sideways step
    (about 1.4 deg of parallax at 10 m), with Gaussian pixel noise: the new points
    and the true ones."""
    cfg = dataclasses.replace(VoConfig(), triangulation_depth_debias=debias)
    cam = PinholeCamera(640, 480, K)
    growth, landmarks = MapGrowth(cfg, cam), LandmarkMap(100000, 3)
    rng = np.random.default_rng(seed)
    X = np.column_stack((rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), np.full(n, 10.0)))
    ids = np.arange(n)
    anchor = (np.eye(6) * 1e-6, np.zeros(3))
    for frame, centre in enumerate(([0.0, 0, 0], [0.25, 0, 0])):
        T_world_cam = geo.make_T(np.eye(3), np.array(centre))
        px = (X - centre)[:, :2] / 10.0 * K[0, 0] + K[:2, 2] + rng.normal(0, sigma_px, (n, 2))
        growth.remember_pose(frame, T_world_cam)
        growth.grow(landmarks, frame, ids, px, np.zeros(n, bool), T_world_cam, anchor)
    got_ids, got = landmarks.ids, landmarks.X_world
    return growth, got, X[got_ids]


def test_new_points_are_not_too_far_on_average():
    """Without the correction the new points are too far on average (by about
    var(depth) / depth); with it the mean depth error is within a few standard errors
    of zero, at the pixel noise the growth measured from the points' own residuals."""
    sigma = 1.0
    _, raw, truth = _grow(False, sigma)
    growth, fixed, truth_f = _grow(True, sigma)
    raw_err = raw[:, 2] / truth[:, 2] - 1.0
    fixed_err = fixed[:, 2] / truth_f[:, 2] - 1.0
    stderr = fixed_err.std() / np.sqrt(len(fixed_err))
    assert len(raw) == len(fixed) > 1000
    assert raw_err.mean() > 5 * stderr
    assert abs(fixed_err.mean()) < 3 * stderr
    assert growth.pixel_noise_px() == pytest.approx(sigma, rel=0.15)


def test_noise_estimate_follows_the_images_not_the_nominal_sigma():
    """Sharp rendered tracks (0.2 px) are corrected by their own noise, not by the
    nominal pixel_sigma_px (1 px), which would pull them 25 times too far."""
    growth, fixed, truth = _grow(True, 0.2)
    assert growth.pixel_noise_px() == pytest.approx(0.2, rel=0.15)
    assert abs(np.mean(fixed[:, 2] / truth[:, 2] - 1.0)) < 1e-3


def test_noise_estimate_forgets_old_points():
    """The estimate pools the last NOISE_WINDOW_POINTS new points: after a change of
    images (a JPEG stream starting, the light falling) it is the new images' noise."""
    growth = MapGrowth(VoConfig(), PinholeCamera(640, 480, K))
    for _ in range(10):
        growth._note_residuals(np.full(100, 4.0))           # 2 px
    for _ in range(NOISE_WINDOW_POINTS // 100):
        growth._note_residuals(np.full(100, 0.25))          # 0.5 px
    assert growth.pixel_noise_px() == pytest.approx(0.5)
    growth._note_residuals(np.array([np.inf, np.nan]))      # nothing usable: unchanged
    assert growth.pixel_noise_px() == pytest.approx(0.5)


def test_before_any_point_the_estimate_is_the_nominal_sigma():
    growth = MapGrowth(VoConfig(), PinholeCamera(640, 480, K))
    assert growth.pixel_noise_px() == VoConfig().pixel_sigma_px

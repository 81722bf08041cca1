"""The tracker-precision bench's ground-truth triangulation (bench/track_precision.py), and
the jolt rule that no longer depends on the KLT window (core/pipeline.py JOLT_MISS_PX)."""
from __future__ import annotations

import numpy as np
import pytest

from bench.track_precision import floor
from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import JOLT_MISS_PX, VisualOdometry

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA = PinholeCamera.from_camera_info({'width': 640, 'height': 480, 'K': K,
                                         'D': np.zeros(5), 'distortion_model': 'plumb_bob'})


def _sideways(n_frames: int) -> np.ndarray:
    """T_world_cam of a camera stepping 0.1 m to the right per frame, looking along +z."""
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, 0, 3] = 0.1 * np.arange(n_frames)
    return T


def _observations(X: np.ndarray, T: np.ndarray, noise_px: float, rng) -> dict:
    obs = {}
    for i, x in enumerate(X):
        views = []
        for k, T_wc in enumerate(T):
            p = np.linalg.inv(T_wc) @ np.append(x, 1.0)
            uv = K[:2, :2] @ (p[:2] / p[2]) + K[:2, 2]
            views.append((k, uv + rng.normal(0.0, noise_px, 2)))
        obs[i] = views
    return obs


def test_exact_tracks_have_no_residual_and_noise_shows_at_its_size() -> None:
    rng = np.random.default_rng(0)
    T = _sideways(6)
    X = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200),
                         rng.uniform(4, 8, 200)])
    exact = floor(_observations(X, T, 0.0, rng), T, CAMERA)
    assert exact['tracks_scored'] == 200
    assert exact['residual_p90_px'] < 1e-6
    assert exact['precise_share_mean'] == 1.0
    noisy = floor(_observations(X, T, 0.5, rng), T, CAMERA)
    # 6 views, 3 unknowns: the residual keeps ~sqrt(9/12) of the 0.5 px noise per axis,
    # so its norm's median is ~0.5 px (Rayleigh median 1.18 sigma x 0.87)
    assert 0.35 < noisy['residual_median_px'] < 0.65
    assert 0.7 < noisy['precise_share_mean'] < 1.0


def test_tracks_without_parallax_or_views_are_not_scored() -> None:
    rng = np.random.default_rng(1)
    T = _sideways(6)
    far = np.array([[0.0, 0.0, 200.0]])              # 0.14 deg of parallax over 0.5 m
    obs = _observations(far, T, 0.0, rng)
    obs[1] = obs[0][:2]                               # two views only
    assert floor(obs, T, CAMERA) == {'tracks_scored': 0}


@pytest.mark.parametrize('window_px', [13, 21, 31])
def test_the_jolt_rule_is_in_pixels_whatever_the_klt_window(window_px) -> None:
    """A prediction missed by less than JOLT_MISS_PX is not a loss with any window: with
    a 13 px window a half-window rule declared the dino lost at a 10 px miss."""
    vo = VisualOdometry(VoConfig(klt_window_px=window_px), CAMERA, seed=0)
    stats = vo.tracker.stats
    stats.n_prediction_retried = 50
    stats.prediction_miss_px = JOLT_MISS_PX - 0.5
    assert vo._motion_model_lost(n_found=2.0, n_in_view=200) == ''
    stats.prediction_miss_px = JOLT_MISS_PX + 0.5
    assert 'motion model lost the camera' in vo._motion_model_lost(n_found=2.0,
                                                                    n_in_view=200)

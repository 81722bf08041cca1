"""Per-landmark measurement noise learned online (core/noise_model.py, docs/method.md §13)."""
import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.ekf import CameraEKF
from ekf_vo.core.noise_model import (NoiseSettings, explained_px2, noise_scales,
                                     normalised_squares)

K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])


def _static_run(sigma_px, bias_px, frames=300, nominal=1.0, seed=0):
    """A static camera watching points with their own noise sigma_px (n,) and a
    constant pixel bias bias_px (n,2); the filter is told `nominal` and learns."""
    rng = np.random.default_rng(seed)
    n = len(sigma_px)
    X = np.column_stack((rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n),
                         rng.uniform(4, 8, n)))
    clean = X[:, :2] / X[:, 2:] @ K[:2, :2].T + K[:2, 2]
    ekf = CameraEKF(K)
    ekf.initialise(np.eye(4), np.zeros(3), np.zeros(3), 1e-3, 1e-3, 1e-3)
    settings = NoiseSettings.from_config(VoConfig())
    dof, ssum = np.zeros(n), np.zeros(n)
    for _ in range(frames):
        z = clean + bias_px + rng.normal(size=clean.shape) * sigma_px[:, None]
        sigma = nominal * noise_scales(dof, ssum, settings)
        ekf.predict(1 / 30, 1e-3, 1e-3, 1.0)
        ekf.update(z, X, sigma, 1)
        px, _, H = ekf.observe(X)
        dof += 2.0
        ssum += normalised_squares(z - px, explained_px2(H, ekf.P), nominal)
    return noise_scales(dof, ssum, settings), ekf


def test_the_noise_estimate_converges_to_each_points_sigma():
    true = np.repeat([0.3, 1.0, 2.0, 4.0], 10)
    scales, _ = _static_run(true, np.zeros((len(true), 2)))
    ratio = scales / true
    assert np.all(np.abs(ratio - 1) < 0.15), ratio.round(2)


def test_a_landmark_with_a_constant_bias_is_down_weighted():
    """One point 5 px off (a track on the wrong corner): its sigma grows toward the bias
    (its weight falls by more than 9x; the a posteriori residual is a little smaller than
    the bias, which the pose absorbed in part while the point was trusted), the others
    stay at their 1 px, and the pose is not pulled by the bad point."""
    true = np.ones(30)
    bias = np.zeros((30, 2))
    bias[0] = (3.0, 4.0)                      # 5 px
    scales, ekf = _static_run(true, bias)
    assert scales[0] > 3.0
    assert np.all(np.abs(scales[1:] - 1) < 0.2)
    assert np.linalg.norm(ekf.T_world_cam[:3, 3]) < 5e-3


def test_a_young_landmark_stays_near_the_nominal():
    settings = NoiseSettings(prior_dof=2.0, min_scale=0.1, max_scale=10.0)
    assert noise_scales(np.array([0.0]), np.array([0.0]), settings)[0] == 1.0
    # one huge residual on a young landmark is capped, not trusted blindly
    big = noise_scales(np.array([2.0]), np.array([1e6]), settings)[0]
    assert big == 10.0

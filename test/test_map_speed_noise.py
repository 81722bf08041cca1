"""The acceleration noise follows the map's units (docs/method.md §3.2).

A map's unit is its bootstrap baseline, so a camera that bootstraps over a third of the
time moves three times as fast in map units. `accel_sigma_per_speed` makes the linear
acceleration noise at least that many times the bootstrap pair's speed.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import VisualOdometry
from ekf_vo.tools.synth import SynthConfig, render_sequence


def _bootstrapped(trajectory: str, **overrides) -> VisualOdometry:
    cfg = SynthConfig(frames=40, seed=0, trajectory=trajectory)
    camera = PinholeCamera.from_camera_info({'width': cfg.width, 'height': cfg.height,
                                             'K': cfg.K(), 'D': cfg.D(),
                                             'distortion_model': 'plumb_bob'})
    vo = VisualOdometry(dataclasses.replace(VoConfig(), **overrides), camera, seed=0)
    for stamp, img, _ in render_sequence(cfg):
        if vo.process(img, stamp).bootstrapped:
            return vo
    vo.close()
    raise AssertionError('no bootstrap in 40 frames')


@pytest.mark.parametrize('per_speed', [0.0, 3.0])
def test_the_acceleration_noise_is_set_by_the_bootstrap_speed(per_speed: float) -> None:
    vo = _bootstrapped('walk', accel_sigma_per_speed=per_speed)
    try:
        speed = float(np.linalg.norm(vo.ekf.x[7:10]))
        assert speed > 0
        expected = max(vo.cfg.accel_sigma, per_speed * speed)
        assert vo.estimator.accel_sigma == pytest.approx(expected)
        # and the prediction uses it: the velocity variance grows by sigma^2 dt^2
        P_before = vo.ekf.P.copy()
        vo.estimator.predict(0.1)
        grown = np.trace(vo.ekf.P[7:10, 7:10] - P_before[7:10, 7:10])
        assert grown == pytest.approx(3 * (expected * 0.1) ** 2, rel=1e-6)
    finally:
        vo.close()

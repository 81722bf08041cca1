"""A velocity that turns with the camera (docs/method.md §3.2).

The motion model keeps the world velocity constant; a car, a robot or an orbiting camera
turns its velocity with its heading, at |omega x v|. `accel_sigma_turn` adds that many
times this rate to the linear acceleration noise (in quadrature).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.ekf import VEL, CameraEKF
from ekf_vo.core.estimators import make_estimator

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _velocity_variance_growth(turn: float, v_world, w_cam, dt: float = 0.1) -> float:
    cfg = dataclasses.replace(VoConfig(), accel_sigma_turn=turn).validate()
    ekf = CameraEKF(K)
    ekf.initialise(np.eye(4), np.asarray(v_world, float), np.asarray(w_cam, float),
                   1e-3, 0.5, 0.5)
    before = ekf.P[VEL, VEL].copy()
    make_estimator(cfg, ekf, None).predict(dt)
    return float(np.trace(ekf.P[VEL, VEL] - before)) / 3.0


@pytest.mark.parametrize('turn', [1.0, 2.0])
def test_a_turning_velocity_adds_its_rate(turn: float) -> None:
    sigma_a = VoConfig().accel_sigma
    # moving forward (z) while turning about y at 1.5 rad/s: |omega x v| = 1.5 * 4
    grown = _velocity_variance_growth(turn, [0.0, 0.0, 4.0], [0.0, 1.5, 0.0])
    assert grown == pytest.approx((sigma_a ** 2 + (turn * 6.0) ** 2) * 0.01, rel=1e-9)


def test_a_velocity_along_the_turn_axis_or_off_adds_nothing() -> None:
    sigma_a = VoConfig().accel_sigma
    expected = sigma_a ** 2 * 0.01
    assert _velocity_variance_growth(2.0, [0.0, 4.0, 0.0], [0.0, 1.5, 0.0]) == \
        pytest.approx(expected, rel=1e-9)
    assert _velocity_variance_growth(0.0, [0.0, 0.0, 4.0], [0.0, 1.5, 0.0]) == \
        pytest.approx(expected, rel=1e-9)

"""Camera model: distortion models round trip, rectified P, validation errors."""
import numpy as np
import pytest

from ekf_vo.core.camera import CameraModelError, PinholeCamera

K = np.array([[500.0, 0, 320], [0, 505.0, 240], [0, 0, 1]])
MODELS = {
    'plumb_bob': [0.12, -0.05, 0.001, 0.002, 0.01],
    'rational_polynomial': [0.1, -0.05, 0.001, 0.002, 0.01, 0.02, -0.01, 0.003],
    'equidistant': [0.05, 0.01, -0.002, 0.001],
}


@pytest.mark.parametrize('model', sorted(MODELS))
def test_distort_undistort_round_trip(model):
    cam = PinholeCamera(640, 480, K, np.array(MODELS[model]), model)
    px = np.random.default_rng(0).uniform([20, 20], [620, 460], (500, 2))
    assert np.abs(cam.undistort(cam.distort(px)) - px).max() < 1e-3


def test_plumb_bob_matches_opencv_projection():
    import cv2
    cam = PinholeCamera(640, 480, K, np.array(MODELS['plumb_bob']), 'plumb_bob')
    X = np.random.default_rng(1).uniform([-1, -1, 2], [1, 1, 5], (100, 3))
    raw, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, cam.D)
    assert np.allclose(cam.undistort(raw.reshape(-1, 2)), cam.project(X), atol=1e-3)


def test_project_unproject_are_inverse_and_behind_is_nan():
    cam = PinholeCamera(640, 480, K)
    X = np.array([[0.3, -0.2, 2.0], [0.0, 0.0, -1.0]])
    px = cam.project(X)
    assert np.all(np.isnan(px[1]))
    ray = cam.unproject(px[:1])[0]
    assert np.allclose(ray, X[0] / np.linalg.norm(X[0]))


def test_rectified_uses_p_and_no_distortion():
    P = np.hstack((K * 1.1, np.zeros((3, 1))))
    P[2, 2] = 1.0
    info = {'width': 640, 'height': 480, 'K': K, 'D': MODELS['plumb_bob'],
            'distortion_model': 'plumb_bob', 'P': P}
    cam = PinholeCamera.from_camera_info(info, rectified=True)
    assert cam.model == 'none' and cam.fx == pytest.approx(550.0)
    assert PinholeCamera.from_camera_info(info).model == 'plumb_bob'


def test_all_zero_distortion_skips_undistortion():
    cam = PinholeCamera(640, 480, K, np.zeros(5), 'plumb_bob')
    assert cam.model == 'none'


@pytest.mark.parametrize('kwargs, message', [
    ({'K': np.zeros((3, 3))}, 'uncalibrated'),
    ({'K': np.array([[np.nan, 0, 320], [0, 500, 240], [0, 0, 1]])}, 'NaN'),
    ({'K': np.array([[-500.0, 0, 320], [0, 500, 240], [0, 0, 1]])}, 'positive'),
    ({'width': 0}, 'not positive'),
    ({'D': np.ones(3), 'model': 'plumb_bob'}, 'coefficients'),
    ({'D': np.ones(4), 'model': 'kannala_brandt_9'}, 'unsupported'),
    ({'K': np.array([[500.0, 0, 5000], [0, 500, 240], [0, 0, 1]])}, 'principal point'),
])
def test_invalid_models_raise_a_clear_error(kwargs, message):
    args = {'width': 640, 'height': 480, 'K': K, 'D': np.zeros(0), 'model': 'none'}
    args.update(kwargs)
    with pytest.raises(CameraModelError, match=message):
        PinholeCamera(**args)


def test_same_as_detects_a_calibration_change():
    a = PinholeCamera(640, 480, K)
    assert a.same_as(PinholeCamera(640, 480, K.copy()))
    assert not a.same_as(PinholeCamera(640, 480, K * np.array([[1.01], [1], [1]])))
    assert not a.same_as(PinholeCamera(800, 480, K))

"""Seeded tests of the camera EKF math: Jacobians, covariance health, NEES, RANSAC."""
import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.core.ekf import (ANG, POS, QUAT, STATE_DIM, VEL, CameraEKF, motion_jacobians,
                             motion_model, motion_rate, pose_innovation, pose_update,
                             update)
from ekf_vo.core.observation import ReprojectionModel
from ekf_vo.tools.synth_points import Sequence, project, run_ekf, smooth_orbit

K = np.array([[500.0, 0, 320], [0, 520.0, 240], [0, 0, 1]])


def _random_filter(seed: int) -> tuple[CameraEKF, np.ndarray]:
    rng = np.random.default_rng(seed)
    ekf = CameraEKF(K)
    T = geo.make_T(geo.quat_to_matrix(rng.normal(size=4)), rng.normal(size=3))
    ekf.initialise(T, rng.normal(size=3), 0.3 * rng.normal(size=3), 0.01, 0.1, 0.1)
    X_cam = np.column_stack((rng.uniform(-2, 2, (25, 2)), rng.uniform(2, 9, 25)))
    return ekf, geo.transform_points(T, X_cam)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_observation_jacobian_matches_finite_differences(seed):
    ekf, X = _random_filter(seed)
    _, _, H = ekf.observe(X)
    H_fd = np.zeros_like(H)
    eps = 1e-7
    for i in range(STATE_DIM):
        xp, xm = ekf.x.copy(), ekf.x.copy()
        xp[i] += eps
        xm[i] -= eps
        H_fd[:, i] = (ekf.observe(X, xp, False)[0] - ekf.observe(X, xm, False)[0]
                      ).reshape(-1) / (2 * eps)
    assert np.allclose(H, H_fd, rtol=1e-5, atol=1e-4 * np.abs(H).max())
    assert np.all(H[:, VEL] == 0) and np.all(H[:, ANG] == 0)


def test_motion_jacobians_match_finite_differences():
    ekf, _ = _random_filter(3)
    dt, eps = 0.07, 1e-7
    F, G = motion_jacobians(ekf.x, dt)
    F_fd = np.zeros_like(F)
    for i in range(STATE_DIM):
        d = np.zeros(STATE_DIM)
        d[i] = eps
        F_fd[:, i] = (motion_model(ekf.x + d, dt) - motion_model(ekf.x - d, dt)) / (2 * eps)
    G_fd = np.zeros_like(G)
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        G_fd[:, i] = (motion_model(ekf.x, dt, d) - motion_model(ekf.x, dt, -d)) / (2 * eps)
    assert np.allclose(F, F_fd, atol=1e-7)
    assert np.allclose(G, G_fd, atol=1e-7)


def test_motion_rate_matches_finite_differences_in_the_time_step():
    ekf, _ = _random_filter(4)
    dt, eps = 0.07, 1e-7
    fd = (motion_model(ekf.x, dt + eps) - motion_model(ekf.x, dt - eps)) / (2 * eps)
    assert np.allclose(motion_rate(ekf.x, dt), fd, atol=1e-7)


def test_stamp_error_adds_the_motion_over_it_to_the_prediction():
    """A stamp wrong by sigma_t moves the predicted state by its rate times sigma_t: the
    covariance of the prediction gains exactly sigma_t^2 J_t J_t^T, and nothing for a
    camera that stands still."""
    ekf, _ = _random_filter(6)
    dt, st = 1 / 30, 0.004
    plain, timed = CameraEKF(K), CameraEKF(K)
    for f in (plain, timed):
        f.x, f.P = ekf.x.copy(), ekf.P.copy()
    plain.predict(dt, 2.0, 2.0, 1.0)
    timed.predict(dt, 2.0, 2.0, 1.0, stamp_sigma_s=st)
    J_t = motion_rate(ekf.x, dt)
    # both then pass through the same quaternion normalisation, a linear map of P
    added = timed.P - plain.P
    assert np.linalg.eigvalsh(added).min() > -1e-12
    assert np.allclose(added[POS, POS], st ** 2 * np.outer(J_t[POS], J_t[POS]), atol=1e-12)
    assert np.allclose(timed.x, plain.x)
    still = CameraEKF(K)
    still.x, still.P = ekf.x.copy(), ekf.P.copy()
    still.x[VEL] = 0.0
    still.x[ANG] = 0.0
    plain.x, plain.P = still.x.copy(), still.P.copy()
    still.predict(dt, 2.0, 2.0, 1.0, stamp_sigma_s=st)
    plain.predict(dt, 2.0, 2.0, 1.0)
    assert np.allclose(still.P, plain.P, atol=1e-15)


def test_predict_covariance_matches_monte_carlo():
    """G Q G^T of the acceleration-impulse model against sampled impulses."""
    rng = np.random.default_rng(5)
    ekf, _ = _random_filter(5)
    ekf.P = np.zeros((STATE_DIM, STATE_DIM))
    dt, sa, sw = 0.1, 3.0, 2.0
    f = CameraEKF(K)
    f.x, f.P = ekf.x.copy(), ekf.P.copy()
    f.predict(dt, sa, sw, 1.0)
    samples = []
    for _ in range(4000):
        a, alpha = rng.normal(0, sa, 3), rng.normal(0, sw, 3)
        x = ekf.x
        v, w = x[VEL] + a * dt, x[ANG] + alpha * dt
        samples.append(np.concatenate((x[POS] + v * dt, geo.quat_multiply(
            x[QUAT], geo.rotvec_to_quat(w * dt)), v, w)))
    cov = np.cov(np.array(samples).T)
    assert np.allclose(f.P, cov, atol=0.08 * np.abs(cov).max())


def test_information_form_update_equals_textbook_kalman_update():
    """The update's Woodbury / information form gives the textbook gain's state and the
    Joseph-form covariance, P+ = (I-KH) P (I-KH)^T + K R K^T with K = P H^T S^-1."""
    ekf, X = _random_filter(7)
    ekf.P = ekf.P + np.diag(np.linspace(0.01, 0.1, STATE_DIM))
    px, _, H = ekf.observe(X)
    sigma = np.linspace(0.5, 2.0, len(X))
    z = px + np.random.default_rng(7).normal(0, 1, px.shape) * sigma[:, None]
    R = np.diag(np.repeat(sigma ** 2, 2))
    P0, x0 = ekf.P.copy(), ekf.x.copy()
    gain_text = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    x_text = x0 + gain_text @ (z - px).reshape(-1)
    I_KH = np.eye(STATE_DIM) - gain_text @ H
    P_text = I_KH @ P0 @ I_KH.T + gain_text @ R @ gain_text.T
    x_new, P_new, _ = update(x0, P0, z, ReprojectionModel.of_map_points(K, X), sigma, 1)
    # the update renormalises q and maps P through d(q/|q|)/dq: do the same to the text's
    q = x_text[QUAT].copy()
    n = np.linalg.norm(q)
    J = np.eye(STATE_DIM)
    J[QUAT, QUAT] = (np.eye(4) - np.outer(q, q) / n ** 2) / n
    x_text[QUAT] = q / n
    assert np.allclose(x_new, x_text, atol=1e-9)
    assert np.allclose(P_new, J @ P_text @ J.T, atol=1e-9)


def _loose_filter(seed: int) -> CameraEKF:
    """A filter whose pose is known to 0.1 (m, rad), with no variance along the
    quaternion's norm (as the filter keeps it)."""
    rng = np.random.default_rng(seed)
    ekf = CameraEKF(K)
    T = geo.make_T(geo.quat_to_matrix(rng.normal(size=4)), rng.normal(size=3))
    ekf.initialise(T, rng.normal(size=3), 0.3 * rng.normal(size=3), 0.1, 0.2, 0.1)
    return ekf


def _moved(T: np.ndarray, dp: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """T moved by dp and turned by the world rotation vector dtheta."""
    R = geo.quat_to_matrix(geo.rotvec_to_quat(dtheta)) @ T[:3, :3]
    return geo.make_T(R, T[:3, 3] + dp)


def test_pose_update_with_an_exact_measurement_lands_on_it():
    """A pose measured far more precisely than the filter knows it becomes the state's
    pose, a 5 deg turn included (the rotation is applied on the manifold)."""
    ekf = _loose_filter(3)
    T_meas = _moved(ekf.T_world_cam, np.array([0.2, -0.1, 0.05]),
                    np.radians([3.0, -4.0, 0.0]))
    x, P = pose_update(ekf.x, ekf.P, T_meas, np.eye(6) * 1e-12, keep_covariance=False)
    assert np.allclose(x[POS], T_meas[:3, 3], atol=1e-6)
    assert geo.rotation_angle_deg(geo.quat_to_matrix(x[QUAT]), T_meas[:3, :3]) < 0.05
    # what the filter knew about the pose is now the measurement's
    ekf.x, ekf.P = x, P
    assert np.all(np.linalg.eigvalsh(ekf.pose_covariance()) < 1e-6)


def test_pose_update_equals_the_textbook_kalman_update():
    """For a small innovation the update is the textbook gain K = P H^T S^-1 with the
    Joseph-form covariance; a measurement equal to the state changes nothing."""
    ekf = _loose_filter(5)
    cov = np.diag([0.02, 0.03, 0.01, 1e-3, 2e-3, 1e-3])
    x0, P0 = ekf.x.copy(), ekf.P.copy()
    x_same, P_same = pose_update(x0, P0, ekf.T_world_cam, cov, keep_covariance=True)
    assert ekf.pose_nis(ekf.T_world_cam, cov) == pytest.approx(0.0, abs=1e-18)
    assert np.allclose(x_same, x0) and np.allclose(P_same, P0, atol=1e-15)
    y = np.array([1e-4, -2e-4, 1e-4, 1e-5, 2e-5, -1e-5])
    T_meas = _moved(ekf.T_world_cam, y[:3], y[3:])
    H = np.zeros((6, STATE_DIM))
    H[0:3, POS] = np.eye(3)
    H[3:6, QUAT] = 2.0 * geo.quat_right_matrix(x0[QUAT]).T[1:, :]
    S = H @ P0 @ H.T + cov
    K_text = P0 @ H.T @ np.linalg.inv(S)
    x, P = pose_update(x0, P0, T_meas, cov, keep_covariance=False)
    assert pose_innovation(x0, P0, T_meas, cov)[2] == pytest.approx(float(y @ np.linalg.solve(S, y)), rel=1e-3)
    assert np.allclose(x[VEL], x0[VEL] + (K_text @ y)[VEL], atol=1e-9)
    assert np.allclose(x[POS], x0[POS] + (K_text @ y)[POS], atol=1e-9)
    I_KH = np.eye(STATE_DIM) - K_text @ H
    P_text = I_KH @ P0 @ I_KH.T + K_text @ cov @ K_text.T
    ekf.x, ekf.P = x, P
    pose_after = ekf.pose_covariance()
    ekf.P = P_text
    assert np.allclose(pose_after, ekf.pose_covariance(), atol=1e-9)


def test_pose_update_against_a_stated_prior_moves_by_its_share_and_the_velocity_follows():
    """With the pose's prior stated (prior_pose_cov: the published covariance, which
    counts the map's error that P leaves out), the pose moves by prior (prior + R)^-1 of
    the innovation: half-way when the two are equal; the velocity follows by its
    regression on the position in P, and P stays as it was."""
    ekf = _loose_filter(9)
    P = ekf.P.copy()
    P[POS, POS] = np.eye(3) * 1e-4
    P[VEL, VEL] = np.eye(3) * 4e-4
    P[POS, VEL] = P[VEL, POS] = np.eye(3) * 1e-4        # velocity regresses 1:1 on position
    ekf.P = P
    dp = np.array([0.4, 0.0, -0.2])
    T_meas = _moved(ekf.T_world_cam, dp, np.zeros(3))
    cov = np.eye(6) * 0.5
    x, P_new = pose_update(ekf.x, P, T_meas, cov, keep_covariance=True,
                              prior_pose_cov=np.eye(6) * 0.5)
    assert np.allclose(x[POS] - ekf.x[POS], dp / 2, atol=1e-9)
    assert np.allclose(x[VEL] - ekf.x[VEL], dp / 2, atol=1e-9)
    ekf.P = P
    before = ekf.pose_covariance()
    ekf.x, ekf.P = x, P_new
    assert np.allclose(ekf.pose_covariance(), before, atol=1e-15)


def test_covariance_stays_symmetric_positive_definite_over_long_run():
    rng = np.random.default_rng(11)
    X = rng.uniform([-3, -3, -1], [3, 3, 2], (200, 3))
    T, t = smooth_orbit(900, 30.0, seed=11)
    out = run_ekf(Sequence(K, X, T, t), 1.0, rng, one_point_ransac=True)
    for cov in out['cov'][::10]:
        assert np.allclose(cov, cov.T, atol=1e-12)
        assert np.linalg.eigvalsh(cov).min() > 0
    P = out['P_final']
    assert np.allclose(P, P.T, atol=1e-12)
    # PSD with a single (quaternion norm) null direction
    assert np.linalg.eigvalsh(P)[1] > 0


def test_mean_nees_is_consistent_over_ten_runs():
    """Mean pose NEES (6 dof) over 10 seeded runs must lie in [3, 12]; 6 is ideal."""
    means = []
    for run in range(10):
        rng = np.random.default_rng(100 + run)
        X = rng.uniform([-3, -3, -1], [3, 3, 2], (200, 3))
        T, t = smooth_orbit(120, 30.0, seed=run)
        means.append(run_ekf(Sequence(K, X, T, t), 1.0, rng)['nees'].mean())
    mean_nees = float(np.mean(means))
    print(f'mean NEES over 10 runs: {mean_nees:.2f}')
    assert 3.0 <= mean_nees <= 12.0


def test_one_point_ransac_rejects_thirty_percent_outliers():
    rng = np.random.default_rng(21)
    X = rng.uniform([-3, -3, -1], [3, 3, 2], (200, 3))
    T, t = smooth_orbit(60, 30.0, seed=21)
    out = run_ekf(Sequence(K, X, T, t), 1.0, rng, one_point_ransac=True,
                  outlier_fraction=0.3)
    accepted_outliers = sum(int(np.count_nonzero(inl & out_)) for inl, out_ in out['inliers'])
    n_outliers = sum(int(np.count_nonzero(out_)) for _, out_ in out['inliers'])
    kept_inliers = sum(int(np.count_nonzero(inl & ~out_)) for inl, out_ in out['inliers'])
    n_inliers = sum(int(np.count_nonzero(~out_)) for _, out_ in out['inliers'])
    assert n_outliers > 1000
    assert accepted_outliers / n_outliers < 0.01
    assert kept_inliers / n_inliers > 0.95
    # and the pose stays accurate
    err = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(out['T_est'], T[2:])]
    assert np.max(err) < 0.05


def test_outliers_without_ransac_corrupt_the_plain_update():
    """Guard that the RANSAC test is meaningful: the same outliers hurt a gate-free EKF."""
    rng = np.random.default_rng(21)
    X = rng.uniform([-3, -3, -1], [3, 3, 2], (200, 3))
    T, t = smooth_orbit(60, 30.0, seed=21)
    ekf = CameraEKF(K)
    T0, T1 = T[0], T[1]
    ekf.initialise(T1, (T1[:3, 3] - T0[:3, 3]) * 30, np.zeros(3), 1e-4, 0.05, 0.05)
    errs = []
    for k in range(2, 30):
        ekf.predict(1 / 30, 2.0, 2.0, 1.0)
        px, _ = project(K, T[k], X)
        z = px + rng.normal(0, 1, px.shape)
        out = rng.random(len(z)) < 0.3
        z[out] += rng.uniform(15, 80, (out.sum(), 2))
        ekf.update(z, X, 1.0, iterations=1)
        errs.append(np.linalg.norm(ekf.x[POS] - T[k][:3, 3]))
    assert max(errs) > 0.05


def test_iterated_update_is_at_least_as_close_on_a_large_innovation():
    ekf, X = _random_filter(9)
    ekf.P += np.eye(STATE_DIM) * 1e-3
    T_true = ekf.T_world_cam.copy()
    T_true[:3, 3] += np.array([0.1, -0.05, 0.08])
    z, _ = project(K, T_true, X)
    plain = CameraEKF(K)
    plain.x, plain.P = ekf.x.copy(), ekf.P.copy()
    plain.update(z, X, 0.5, iterations=1)
    itr = CameraEKF(K)
    itr.x, itr.P = ekf.x.copy(), ekf.P.copy()
    itr.update(z, X, 0.5, iterations=3)
    assert itr.last_update.rms_residual_px <= plain.last_update.rms_residual_px + 1e-9


def test_pose_covariance_maps_quaternion_to_rotation_vector():
    """Sampled world-frame rotation errors reproduce the published 6x6 block."""
    rng = np.random.default_rng(4)
    ekf = CameraEKF(K)
    T = geo.make_T(geo.quat_to_matrix(np.array([0.9, 0.1, -0.3, 0.2])), np.ones(3))
    ekf.initialise(T, np.zeros(3), np.zeros(3), 0.02, 0.1, 0.1)
    cov = ekf.pose_covariance()
    assert np.allclose(cov[3:, 3:], np.eye(3) * 0.02 ** 2, rtol=1e-6)
    assert np.allclose(cov[:3, :3], np.eye(3) * 0.02 ** 2, rtol=1e-6)
    assert np.allclose(cov[:3, 3:], 0)


def test_robust_update_with_no_supported_hypothesis_does_not_raise():
    """Every match an outlier: no hypothesis has support; nothing is used, no exception."""
    from ekf_vo.core.robust_update import RansacSettings, robust_update
    ekf, X = _random_filter(13)
    px, _, _ = ekf.observe(X)
    rng = np.random.default_rng(0)
    z = px + rng.uniform(200, 400, px.shape) * rng.choice([-1, 1], px.shape)
    x_before = ekf.x.copy()
    settings = RansacSettings(one_point=True, inlier_px=2.0, probability=0.99,
                              max_hypotheses=50, gate_probability=0.99, iterations=1)
    x, _, res = robust_update(ekf.x, ekf.P, z, ReprojectionModel.of_map_points(K, X), 1.0,
                              rng, settings)
    assert res.n_inliers == 0 and res.n_hypotheses > 0
    assert np.allclose(x, x_before)

"""Windowed bundle adjustment (core/local_ba.py): Jacobian, convergence, honest covariances."""
import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.core.local_ba import WindowProblem, _Window, adjust_window, point_covariances

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _scene(rng, n_kf=6, n_pts=200):
    """Keyframes moving forward along z past points 4-12 units ahead; every point seen
    by every keyframe (ideal pixels), the truth and the problem with noisy inputs."""
    T = []
    for k in range(n_kf):
        R = geo.rotvecs_to_matrices(np.array([[0.0, 0.02 * k, 0.0]]))[0]
        T.append(geo.make_T(R, np.array([0.3 * k, 0.0, 0.5 * k])))
    T = np.stack(T)
    X = np.column_stack((rng.uniform(-4, 4, n_pts), rng.uniform(-3, 3, n_pts),
                         rng.uniform(7, 15, n_pts)))
    cam_idx = np.repeat(np.arange(n_kf), n_pts)
    pt_idx = np.tile(np.arange(n_pts), n_kf)
    px = np.concatenate([(X @ geo.invert_T(Tk)[:3, :3].T + geo.invert_T(Tk)[:3, 3])
                         for Tk in T])
    px = px[:, :2] / px[:, 2:] @ K[:2, :2].T + K[:2, 2]
    return T, X, cam_idx, pt_idx, px


def _perturbed(T, rng, fixed, pos_sigma=0.02, rot_sigma=0.003):
    out = T.copy()
    for k in np.flatnonzero(~fixed):
        dR = geo.rotvecs_to_matrices(rng.normal(0, rot_sigma, (1, 3)))[0]
        out[k, :3, :3] = dR @ T[k, :3, :3]
        out[k, :3, 3] += rng.normal(0, pos_sigma, 3)
    return out


def test_the_normal_equations_match_finite_differences_of_the_cost():
    """The gradient of the Gauss-Newton system is the derivative of the robust cost."""
    rng = np.random.default_rng(0)
    T, X, ci, pi, px = _scene(rng, n_kf=4, n_pts=20)
    fixed = np.array([True, True, False, False])
    win = _Window(WindowProblem(_perturbed(T, rng, fixed), fixed, X + 0.1, ci, pi, px),
                  K, 1.0, huber_px=3.0)
    ne = win.normal_equations()
    assert np.isclose(ne.cost, win.cost())
    grad = np.concatenate((ne.gc, ne.gp.ravel()))
    num = np.zeros_like(grad)
    n_cam = win.nc
    for j in range(len(grad)):
        step = []
        for sign in (1, -1):
            saved = win.state()
            d_cam, d_pts = np.zeros(n_cam), np.zeros((len(X), 3))
            if j < n_cam:
                d_cam[j] = sign * 1e-6
            else:
                d_pts.ravel()[j - n_cam] = sign * 1e-6
            win.apply(d_cam, d_pts)
            step.append(win.cost())
            win.restore(saved)
        num[j] = (step[0] - step[1]) / 2e-6
    assert np.max(np.abs(grad - num)) < 1e-4 * max(1.0, np.max(np.abs(num)))


def test_adjustment_recovers_the_window_and_its_points():
    rng = np.random.default_rng(1)
    T, X, ci, pi, px = _scene(rng)
    fixed = np.zeros(len(T), bool)
    fixed[:2] = True
    noisy = px + rng.normal(0, 0.5, px.shape)
    X0 = X + rng.normal(0, 0.05, X.shape)
    sol = adjust_window(WindowProblem(_perturbed(T, rng, fixed), fixed, X0, ci, pi, noisy),
                        K, sigma_px=0.5, huber_px=1.0, max_iterations=30)
    # the 2-D error of sigma 0.5 px per axis: rms 0.5 sqrt(2), less the fitted dof
    assert sol.rms_after_px < 0.5 * np.sqrt(2) < np.sqrt(np.mean(sol.err_before_px ** 2))
    pos_err = np.linalg.norm(sol.T_world_cam[:, :3, 3] - T[:, :3, 3], axis=1)
    assert np.all(pos_err[:2] == 0)                        # the gauge stays put
    assert np.max(pos_err) < 0.01
    assert np.median(np.linalg.norm(sol.X_world - X, axis=1)) < \
        0.75 * np.median(np.linalg.norm(X0 - X, axis=1))


def _noise_draws(scene_seed: int, first_draw: int, n_draws: int = 20,
                 T_world_scene: np.ndarray | None = None):
    """The truth (T, X, fixed) and the adjusted windows of n_draws draws of 1 px pixel
    noise and perturbed starts (a plain least-squares cost: Huber width 100 px).
    `T_world_scene`: the whole scene moved rigidly into the world by it (the pixels do
    not change)."""
    T, X, ci, pi, px = _scene(np.random.default_rng(scene_seed), n_pts=60)
    if T_world_scene is not None:
        T = T_world_scene @ T
        X = X @ T_world_scene[:3, :3].T + T_world_scene[:3, 3]
    fixed = np.zeros(len(T), bool)
    fixed[:2] = True
    sols = []
    for seed in range(first_draw, first_draw + n_draws):
        rng = np.random.default_rng(seed)
        noisy = px + rng.normal(0, 1.0, px.shape)
        sols.append(adjust_window(
            WindowProblem(_perturbed(T, rng, fixed), fixed, X + rng.normal(0, 0.05, X.shape),
                          ci, pi, noisy), K, sigma_px=1.0, huber_px=100.0, max_iterations=50))
    return T, X, fixed, sols


def test_point_covariances_are_consistent():
    """NEES of the refined points against the truth over noise draws: 3 dof -> mean ~3."""
    _, X, _, sols = _noise_draws(2, 100)
    nees = [np.einsum('mi,mij,mj->m', s.X_world - X, np.linalg.inv(s.X_cov), s.X_world - X)
            for s in sols]
    mean = float(np.mean(nees))
    assert 2.2 < mean < 4.0, mean


def test_two_view_point_covariance_grows_with_depth():
    T_a = np.eye(4)
    T_b = geo.make_T(np.eye(3), np.array([-1.0, 0.0, 0.0]))      # camera 1 unit to the right
    X = np.array([[0.5, 0.0, 5.0], [0.5, 0.0, 20.0]])
    cov = point_covariances(X, [T_a, T_b], K, 1.0)
    assert cov[1, 2, 2] > 10 * cov[0, 2, 2] > 0


def _pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(dtheta, dC) of the adjustment's parametrisation: R_cw = exp(dtheta) R_cw_true."""
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    w = geo.quat_to_rotvec(geo.matrix_to_quat(dR))
    return np.concatenate((w, T_est[:3, 3] - T_true[:3, 3]))


def test_keyframe_covariances_are_consistent():
    """NEES of the free keyframes' poses (the information kept as the next window's
    prior) against the truth over noise draws: 6 dof -> mean ~6."""
    T, _, fixed, sols = _noise_draws(3, 200)
    nees = []
    for sol in sols:
        assert np.all(sol.T_cov[fixed] == 0)
        for k in np.flatnonzero(~fixed):
            e = _pose_error(sol.T_world_cam[k], T[k])
            nees.append(e @ np.linalg.solve(sol.T_cov[k], e))
    mean = float(np.mean(nees))
    assert 4.5 < mean < 8.0, mean


def test_a_pose_prior_enters_the_cost_and_holds_the_pose():
    """The normal equations with a prior are the cost's derivative (to first order in the
    prior's rotation offset), and a strong prior at the truth keeps a keyframe there while
    the others move."""
    rng = np.random.default_rng(4)
    T, X, ci, pi, px = _scene(rng, n_kf=4, n_pts=20)
    fixed = np.array([True, True, False, False])
    info = np.zeros((4, 6, 6))
    info[2] = info[3] = np.diag([1e4, 1e4, 1e4, 1e2, 1e2, 1e2])
    start = _perturbed(T, rng, fixed, pos_sigma=0.01, rot_sigma=0.001)
    win = _Window(WindowProblem(start, fixed, X + 0.1, ci, pi, px, info), K, 1.0, 3.0)
    # the prior's mean is where the window starts: move it off to test the gradient
    win.C = win.C + np.array([0.0, 0.0, 0.01])
    ne = win.normal_equations()
    assert np.isclose(ne.cost, win.cost())
    num = np.zeros(win.nc)
    for j in range(win.nc):
        costs = []
        for sign in (1, -1):
            saved = win.state()
            d = np.zeros(win.nc)
            d[j] = sign * 1e-6
            win.apply(d, np.zeros((len(X), 3)))
            costs.append(win.cost())
            win.restore(saved)
        num[j] = (costs[0] - costs[1]) / 2e-6
    assert np.max(np.abs(ne.gc - num)) < 1e-3 * max(1.0, np.max(np.abs(num)))
    strong = np.zeros((4, 6, 6))
    strong[3] = np.eye(6) * 1e12
    truth_start = _perturbed(T, rng, np.array([True, True, False, True]))
    sol = adjust_window(WindowProblem(truth_start, fixed, X + 0.05, ci, pi, px, strong),
                        K, 1.0, 3.0, 30)
    assert np.allclose(sol.T_world_cam[3], T[3], atol=1e-6)
    assert np.linalg.norm(sol.T_world_cam[2, :3, 3] - T[2, :3, 3]) < 1e-3


def _mapper_after_a_turn(rng, n_blind):
    """A LocalMapper whose 6-keyframe window starts with `n_blind` keyframes that looked
    elsewhere (they see none of the window's points: the window after a turn in place),
    and a map of the points the others see (ideal pixels, exact poses)."""
    from ekf_vo.config import VoConfig
    from ekf_vo.core.local_map import LocalMapper
    from ekf_vo.core.map import LandmarkMap
    T, X, _, _, _ = _scene(rng, n_kf=6, n_pts=60)
    ids = np.arange(100, 160)
    landmarks = LandmarkMap(1000, 3)
    landmarks.add(ids, X, 0, cov=np.tile(np.eye(3) * 1e-4, (60, 1, 1)))
    mapper = LocalMapper(VoConfig(), K)
    for k, Tk in enumerate(T):
        Xc = X @ geo.invert_T(Tk)[:3, :3].T + geo.invert_T(Tk)[:3, 3]
        px = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
        if k < n_blind:     # other tracks, none of them a window point
            mapper.add_keyframe(k, Tk, np.arange(1000 * (k + 1), 1000 * (k + 1) + 30),
                                rng.uniform(0, 400, (30, 2)))
        else:
            mapper.add_keyframe(k, Tk, ids, px)
    return mapper, landmarks


def test_keyframes_that_see_none_of_the_window_do_not_fix_its_gauge():
    """After a turn in place the oldest keyframes of the window may see none of its
    points. Holding them fixed left the window's gauge free: its marginal covariances
    came out at 10^8 and entered the map and the published covariance. The gauge is
    fixed by the oldest keyframes that see the points."""
    rng = np.random.default_rng(3)
    mapper, landmarks = _mapper_after_a_turn(rng, n_blind=2)
    problem, point_ids, gauge = mapper._problem(landmarks)
    assert gauge == 3                                    # keyframes 2 and 3 fix it
    assert problem.fixed.tolist() == [True, True, True, True, False, False]
    sol = adjust_window(problem, K, 1.0, 2.0, 5)
    # a fixed gauge: every point's covariance stays at the scale of its parallax
    assert np.max(np.linalg.eigvalsh(sol.X_cov)) < 1.0
    assert np.all(np.isfinite(sol.T_cov))


def test_a_window_that_cannot_fix_its_gauge_is_not_adjusted():
    rng = np.random.default_rng(4)
    mapper, landmarks = _mapper_after_a_turn(rng, n_blind=4)   # 2 keyframes see points
    assert mapper._problem(landmarks) is None


def test_a_point_seen_twice_by_one_keyframe_is_refused():
    """The reduced system places one block per (keyframe, point): a second observation
    of a point by the same keyframe would be lost, so the window is refused (ValueError,
    which the local map counts as a skipped adjustment) rather than solved wrongly."""
    rng = np.random.default_rng(6)
    T, X, ci, pi, px = _scene(rng, n_kf=4, n_pts=20)
    fixed = np.array([True, True, False, False])
    dup = np.flatnonzero(ci == 3)[0]
    problem = WindowProblem(T, fixed, X, np.r_[ci, ci[dup]], np.r_[pi, pi[dup]],
                            np.vstack((px, px[dup])))
    with pytest.raises(ValueError, match='twice'):
        adjust_window(problem, K, 1.0, 3.0, 5)


def test_singular_point_information_does_not_raise():
    """Rays all but parallel: the absolute regulariser is lost against 10^8 entries; the
    inverse must not raise in the worker, and must not give the depth a zero variance."""
    from ekf_vo.core.local_ba import _inverse_3x3
    v = np.array([1.0, 2.0, 3.0])
    H = np.stack([np.outer(v, v) * 1e8, np.eye(3)])
    inv = _inverse_3x3(H)
    assert np.all(np.isfinite(inv))
    assert np.linalg.eigvalsh(inv[0])[-1] > 0.1          # the unseen directions stay unsure
    np.testing.assert_allclose(inv[1], np.eye(3))


def test_an_adjustment_that_raises_is_skipped_and_counted():
    from concurrent.futures import Future
    from ekf_vo.core.local_map import _Pending
    rng = np.random.default_rng(5)
    mapper, landmarks = _mapper_after_a_turn(rng, n_blind=0)
    future = Future()
    future.set_exception(np.linalg.LinAlgError('Singular matrix'))
    mapper._pending = _Pending(future, 3, list(mapper.keyframes), np.arange(100, 160), 1)
    X_before = landmarks.X_world.copy()
    assert len(mapper.harvest(3, landmarks)) == 0
    assert mapper.stats.n_failed == 1 and mapper.stats.as_status()['ba_failed'] == 1
    np.testing.assert_array_equal(landmarks.X_world, X_before)


def test_the_adjusted_pose_covariance_is_that_of_the_world_error():
    """The keyframe marginals, carried to the published convention (position, world
    rotation vector: R_wc_est = exp(dphi) R_wc_true), against the truth over noise
    draws: 6 dof -> mean ~6. The scene is turned far from the world's axes, so that a
    rotation vector taken in the camera's frame instead of the world's would show."""
    from ekf_vo.core.map_uncertainty import adjusted_pose_covariance
    G = geo.make_T(geo.rotvecs_to_matrices(np.array([[0.9, -1.2, 0.5]]))[0],
                   np.array([3.0, -2.0, 1.0]))
    T, _, fixed, sols = _noise_draws(3, 200, T_world_scene=G)
    nees = []
    for sol in sols:
        for k in np.flatnonzero(~fixed):
            T_est = sol.T_world_cam[k]
            dphi = geo.quat_to_rotvec(geo.matrix_to_quat(T_est[:3, :3] @ T[k, :3, :3].T))
            e = np.concatenate((T_est[:3, 3] - T[k, :3, 3], dphi))
            nees.append(e @ np.linalg.solve(adjusted_pose_covariance(T_est, sol.T_cov[k]), e))
    mean = float(np.mean(nees))
    assert 4.5 < mean < 8.0, mean


def test_an_adjusted_keyframe_keeps_the_smaller_of_its_two_anchors():
    """After an adjustment a free keyframe's anchor is the gauge keyframe's plus the
    adjustment's covariance of its pose, unless the anchor it had (the filter's when it
    was made) is smaller: both bound the error of the adjusted pose (§14.2)."""
    from concurrent.futures import Future
    from ekf_vo.core.local_map import _Pending
    from ekf_vo.core.map_uncertainty import adjusted_pose_covariance, carry_pose_covariance
    rng = np.random.default_rng(6)
    mapper, landmarks = _mapper_after_a_turn(rng, n_blind=0)
    kfs = mapper.keyframes
    for kf in kfs:                                    # the filter's anchors: 10 deg
        kf.anchor = (np.eye(6) * np.radians(10.0) ** 2, kf.T_world_cam[:3, 3].copy())
    gauge_anchor = (np.eye(6) * 1e-6, kfs[1].T_world_cam[:3, 3].copy())
    kfs[1].anchor = gauge_anchor
    tiny = (np.eye(6) * 1e-12, kfs[5].T_world_cam[:3, 3].copy())
    kfs[5].anchor = tiny
    problem, point_ids, gauge = mapper._problem(landmarks)
    assert gauge == 1 and problem.fixed.tolist() == [True, True, False, False, False, False]
    sol = adjust_window(problem, K, 1.0, 2.0, 10)
    future = Future()
    future.set_result(sol)
    mapper._pending = _Pending(future, 0, list(kfs), point_ids, gauge)
    mapper.harvest(0, landmarks)
    for k in (2, 3, 4):
        c = sol.T_world_cam[k][:3, 3]
        expected = carry_pose_covariance(gauge_anchor[0][None], gauge_anchor[1], c)[0] + \
            adjusted_pose_covariance(sol.T_world_cam[k], sol.T_cov[k])
        np.testing.assert_allclose(kfs[k].anchor[0], expected, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(kfs[k].anchor[1], c)
        assert np.trace(kfs[k].anchor[0][3:, 3:]) < 1e-3 * np.radians(10.0) ** 2
    assert kfs[5].anchor is tiny                      # smaller than the adjustment's
    assert kfs[0].anchor[0][0, 0] == np.radians(10.0) ** 2   # fixed keyframes keep theirs


def test_an_adjustment_hands_the_filter_its_newest_keyframe_once():
    """The newest keyframe the adjustment moved is handed on (LocalMapper.take_correction,
    for ba_pose_feedback): the adjusted pose near the truth where the filter's was 8 cm
    off, the filter's pose as it was, and a positive-definite covariance; once."""
    from concurrent.futures import Future
    from ekf_vo.core.local_map import _Pending
    rng = np.random.default_rng(7)
    mapper, landmarks = _mapper_after_a_turn(rng, n_blind=0)
    kfs = mapper.keyframes
    T_true = kfs[5].T_world_cam.copy()
    T_off = T_true.copy()
    T_off[:3, 3] += np.array([0.08, 0.0, 0.0])
    kfs[5].T_world_cam, kfs[5].T_world_cam_filter = T_off.copy(), T_off.copy()
    problem, point_ids, gauge = mapper._problem(landmarks)
    sol = adjust_window(problem, K, 1.0, 2.0, 10)
    future = Future()
    future.set_result(sol)
    mapper._pending = _Pending(future, 0, list(kfs), point_ids, gauge)
    mapper.harvest(0, landmarks)
    corr = mapper.take_correction()
    assert corr.frame_index == 5
    assert np.linalg.norm(corr.T_world_cam_adjusted[:3, 3] - T_true[:3, 3]) < 0.005
    np.testing.assert_array_equal(corr.T_world_cam_filter, T_off)
    assert np.all(np.linalg.eigvalsh(corr.cov_relative) > 0)
    assert mapper.take_correction() is None

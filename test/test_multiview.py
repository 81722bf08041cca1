"""Multi-view bootstrap (multiview.py) and the two estimator extensions in the pipeline."""
import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.multiview import MultiViewBootstrap, bundle_adjust
from ekf_vo.core.pipeline import VisualOdometry
from ekf_vo.tools.evaluate import evaluate
from ekf_vo.tools.synth import SynthConfig, render_sequence
from ekf_vo.tools.synth_points import project, smooth_orbit

K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])


def _scene(seed=0, n_frames=60, sigma=0.5):
    rng = np.random.default_rng(seed)
    T, stamps = smooth_orbit(n_frames, 30.0, radius=6.0, seed=seed)
    X = rng.uniform(-2.5, 2.5, (250, 3))
    obs = []
    for Tk in T:
        px, d = project(K, Tk, X)
        vis = (d > 0.1) & np.all((px > 0) & (px < [640, 480]), axis=1)
        obs.append((np.flatnonzero(vis), px[vis] + rng.normal(0, sigma, (int(vis.sum()), 2))))
    return T, stamps, X, obs


def _sim3(A, B):
    """Umeyama (1991): s, R, t minimising |B - (s R A + t)|^2 over rows."""
    ma, mb = A.mean(0), B.mean(0)
    U, d, Vt = np.linalg.svd((B - mb).T @ (A - ma) / len(A))
    S = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    s = np.trace(np.diag(d) @ S) / np.mean(np.sum((A - ma) ** 2, axis=1))
    return s, R, mb - s * R @ ma


def _aligned_errors(T_est, X_est, T_gt, X_gt):
    """Rotation (deg) and position errors of cameras after the Sim(3) alignment of the
    reconstructed points onto the true ones (the scene recovered up to similarity)."""
    s, R, t = _sim3(X_est, X_gt)
    rot = [_rot_deg(R @ Te[:3, :3], Tg[:3, :3]) for Te, Tg in zip(T_est, T_gt)]
    pos = [np.linalg.norm(s * R @ Te[:3, 3] + t - Tg[:3, 3]) for Te, Tg in zip(T_est, T_gt)]
    return np.array(rot), np.array(pos)


def _rot_deg(Ra, Rb):
    return geo.rotation_angle_deg(Ra, Rb)


def test_bundle_adjustment_reduces_the_error_and_recovers_the_scene():
    T, _, X, obs = _scene()
    cams = [0, 12, 24, 36, 48]
    rng = np.random.default_rng(1)
    T_init, cam_idx, pt_idx, px = [], [], [], []
    for j, k in enumerate(cams):
        Tk = T[k].copy()
        if j >= 1:   # perturb all but the gauge camera: ~1 deg, 5 cm
            Tk[:3, :3] = geo.quat_to_matrix(geo.rotvec_to_quat(rng.normal(0, 0.015, 3))) @ Tk[:3, :3]
            if j >= 2:
                Tk[:3, 3] += rng.normal(0, 0.05, 3)
        T_init.append(Tk)
        ids, p = obs[k]
        cam_idx += [j] * len(ids)
        pt_idx += list(ids)
        px.append(p)
    X_init = X + rng.normal(0, 0.05, X.shape)
    ba = bundle_adjust(np.array(T_init), X_init, np.array(cam_idx), np.array(pt_idx),
                       np.concatenate(px), K, huber_px=1.0, max_evaluations=400)
    # rms of the 2-D error norm: sigma sqrt(2) = 0.71 px at the optimum
    assert ba.rms_after_px < 0.75 < ba.rms_before_px
    baseline = np.linalg.norm(T[cams[1]][:3, 3] - T[cams[0]][:3, 3])
    rot, pos = _aligned_errors(ba.T_world_cam, ba.X_world, T[cams], X)
    rot0, pos0 = _aligned_errors(np.array(T_init), X_init, T[cams], X)
    # the cameras end near the truth: errors of up to 1.5 deg and 5.7 % of the baseline
    # at the start, a fifth of that or less after. (The position error where the solver stops is
    # 1.0-1.1 % of the baseline, and it moves along a weak direction as the solver goes
    # on: 1.02 / 1.05 / 1.14 % after 1,000 / 2,000 / 5,000 evaluations on an AMD EPYC, so
    # a bound at 1 % held on one CPU and not on another.)
    assert rot.max() < 0.2 < rot0.max() / 5
    assert pos.max() < 0.02 * baseline < pos0.max() / 2.5
    assert np.linalg.norm(ba.T_world_cam[1][:3, 3] - ba.T_world_cam[0][:3, 3]) == \
        pytest.approx(baseline, rel=1e-9)


def test_multi_view_bootstrap_from_tracks_recovers_the_scene():
    T, stamps, X, obs = _scene(seed=2)
    cfg = dataclasses.replace(VoConfig(), multiview_keyframes=5, pixel_sigma_px=0.5,
                              multiview_ba_huber_px=0.5,
                              multiview_keyframe_parallax_deg=4.0,
                              multiview_ba_max_evaluations=1000)
    mv = MultiViewBootstrap(cfg, K)
    step = None
    for k, (ids, px) in enumerate(obs):
        step = mv.step(k, int(stamps[k] * 1e9), ids.astype(np.int64), px)
        if step.status == 'done':
            break
    assert step.status == 'done' and len(step.keyframes) == 5
    assert step.ba.rms_after_px < step.ba.rms_before_px
    # world = keyframe 0's camera frame, |C1 - C0| = bootstrap_baseline_m: map the truth
    f0, f1 = step.keyframes[0].frame_index, step.keyframes[1].frame_index
    T_gt = T[[kf.frame_index for kf in step.keyframes]]
    T_est = np.array([kf.T_world_cam for kf in step.keyframes])
    rot, pos = _aligned_errors(T_est, step.X_world, T_gt, X[step.point_ids])
    baseline = np.linalg.norm(T[f1][:3, 3] - T[f0][:3, 3])
    # from tracks the first baseline is short (2 deg parallax): positions to 5% of it
    assert rot.max() < 0.2 and pos.max() < 0.05 * baseline


@pytest.fixture(scope='module')
def rendered():
    cfg = SynthConfig(frames=120, seed=3, trajectory='walk')
    frames = list(render_sequence(cfg))
    return PinholeCamera(cfg.width, cfg.height, cfg.K()), frames


@pytest.mark.parametrize('overrides', [{'map_refinement': 'filter'},
                                       {'bootstrap': 'multi_view'}])
def test_pipeline_with_an_extension_tracks_a_rendered_sequence(rendered, overrides):
    camera, frames = rendered
    vo = VisualOdometry(dataclasses.replace(VoConfig(), **overrides), camera)
    results = [vo.process(img, stamp) for stamp, img, _ in frames]
    ok = [(r.stamp_ns * 1e-9, r.T_world_cam) for r in results if r.ok]
    ev = evaluate(np.array([s * 1e-9 for s, _, _ in frames]),
                  np.array([T for _, _, T in frames]), np.array([s for s, _ in ok]),
                  np.array([T for _, T in ok]), n_frames_total=len(frames))
    assert ev.pct_tracked >= 90.0
    assert ev.ate_sim3_pct_of_path < 3.0
    assert vo.n_resets == 0
    if 'map_refinement' in overrides:
        assert vo.points.n_frozen > 0
        assert vo.points.state_dim <= 13 + vo.cfg.filter_max_points
    for r in results:
        if r.ok:
            assert np.all(np.isfinite(r.pose_cov)) and np.linalg.eigvalsh(r.pose_cov).min() > 0

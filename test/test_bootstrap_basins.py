"""The bootstrap's polish finds the right basin of the epipolar cost (docs/method.md §2.1.1).

A camera moving forward has a second minimum of the Sampson cost: the translation turned
sideways, a yaw or pitch compensating it. A polish from one start stays in the basin it
starts in; `other_basin` starts again from turned translations and keeps the
model of least robust cost. A scene close to a plane has two relative poses that fit it;
the one with points behind a camera loses, and a pair that cannot tell them apart
otherwise is refused or holds the other in its covariance (§2.1.2).
"""
from __future__ import annotations


import cv2
import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.bootstrap import (TwoViewBootstrap, common_tracks, other_basin,
                                   refine_relative_pose, robust_sampson_cost, sampson_px)
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import VisualOdometry
from ekf_vo.tools.synth import SynthConfig, render_sequence

from .support.benchmarks import run_benchmark
from .support.rendered import standing_first

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))


def _forward_pair(seed: int):
    """Points 2-15 m ahead, seen before and after a 0.4 m step forward with a small turn;
    0.3 px noise. Returns (p_ref, p_cur, R_cur_ref, t_cur_ref unit)."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 640, 250), rng.uniform(0, 480, 250)
    z = rng.uniform(2.0, 15.0, 250)
    X = np.c_[(u - 320) / 500 * z, (v - 240) / 500 * z, z]
    R = cv2.Rodrigues(np.radians([0.3, -0.5, 0.1]).reshape(3, 1))[0]
    t = np.array([0.03, 0.05, 1.0]) / np.linalg.norm([0.03, 0.05, 1.0])
    Xc = X @ R.T + 0.4 * t
    p_ref = X[:, :2] / X[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.3, (250, 2))
    p_cur = Xc[:, :2] / Xc[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.3, (250, 2))
    return p_ref, p_cur, R, t


def _wall_pair(seed: int, relief_m: float):
    """A wall 5 m ahead turned 30 deg about the vertical, its points `relief_m` in front
    of or behind it, seen before and after a 0.8 m step sideways with a 2 deg turn;
    0.3 px noise. Returns (ids, p_ref, p_cur, R_cur_ref) of the points seen by both."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 640, 250), rng.uniform(0, 480, 250)
    ray = np.c_[(u - 320) / 500, (v - 240) / 500, np.ones(250)]
    normal = np.array([np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))])
    X = ray * (5.0 / (ray @ normal) + rng.uniform(-relief_m, relief_m, 250))[:, None]
    R = cv2.Rodrigues(np.radians([0.5, 2.0, 0.2]).reshape(3, 1))[0]
    t = np.array([-1.0, 0.05, 0.1]) / np.linalg.norm([-1.0, 0.05, 0.1])
    Xc = X @ R.T + 0.8 * t
    p_ref = X[:, :2] / X[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.3, (250, 2))
    p_cur = Xc[:, :2] / Xc[:, 2:] * 500 + [320, 240] + rng.normal(0, 0.3, (250, 2))
    seen = np.all((p_cur > 0) & (p_cur < [640, 480]), axis=1)
    return np.flatnonzero(seen), p_ref[seen], p_cur[seen], R


def test_the_flat_walls_pose_with_points_behind_the_cameras_loses() -> None:
    """On a flat wall (and with 5 cm of relief at 5 m) the five-point RANSAC model can be
    the homography's other decomposition, 8.5 deg off, which puts 40 % of the points
    behind a camera. The decomposition that puts them all in front replaces it, and the
    pair is taken near the truth (docs/method.md §2.1.2)."""
    bootstrap = TwoViewBootstrap(VoConfig(), K)
    wrong_at_first = 0
    for relief_m in (0.0, 0.05):
        for seed in range(4):
            ids, p_ref, p_cur, R_true = _wall_pair(seed, relief_m)
            R_ransac = bootstrap._relative_pose(p_ref, p_cur, 1.0)[0]
            wrong_at_first += _angle_deg(R_ransac @ R_true.T) > 5.0
            res = bootstrap.try_pair(ids, p_ref, ids, p_cur)
            assert res.ok, (relief_m, seed, res.reason)
            assert _angle_deg(res.R_cur_ref @ R_true.T) < 0.2, (relief_m, seed)
            assert len(res.rival_rotvecs) == 0
    assert wrong_at_first >= 3          # the premise: RANSAC's model was the other one


def polish(R, t, p_ref, p_cur):
    """The polish of try_pair: refine_relative_pose, then other_basin's model if any."""
    R0, t0 = refine_relative_pose(R, t, p_ref, p_cur, K, 3.0, 2.0)
    found = other_basin(R0, t0, p_ref, p_cur, K, 3.0, 2.0)
    return (R0, t0) if found is None else found


def test_a_start_in_the_wrong_basin_is_left_for_the_model_of_least_cost() -> None:
    p_ref, p_cur, R_true, t_true = _forward_pair(0)
    turned = cv2.Rodrigues(np.array([0.0, np.radians(40.0), 0.0]).reshape(3, 1))[0] @ t_true
    R1, t1 = refine_relative_pose(R_true, turned, p_ref, p_cur, K, 3.0, 2.0)
    # the premise: a single polish from this start does not reach the truth
    assert _angle_deg(R1 @ R_true.T) > 0.5
    R2, t2 = polish(R_true, turned, p_ref, p_cur)
    assert _angle_deg(R2 @ R_true.T) < 0.1
    assert float(t2 @ t_true) > 0.99          # the cheirality vote kept t's sign
    assert robust_sampson_cost(R2, t2, p_ref, p_cur, K, 3.0, 2.0) < \
        robust_sampson_cost(R1, t1, p_ref, p_cur, K, 3.0, 2.0)


def test_a_start_in_the_right_basin_is_kept() -> None:
    p_ref, p_cur, R_true, t_true = _forward_pair(1)
    R, t = polish(R_true, t_true, p_ref, p_cur)
    R0, t0 = refine_relative_pose(R_true, t_true, p_ref, p_cur, K, 3.0, 2.0)
    assert _angle_deg(R @ R0.T) < 1e-6
    assert float(t @ t0) > 1 - 1e-9


def _first_bootstrap_after_standing(trajectory: str, seed: int, standing: int = 30,
                                    **camera):
    """The rendered `trajectory` (SynthConfig `camera` fields) whose first view is held
    for `standing` frames (sensor noise 2 grey levels, as bench.rotation_nees's
    ``_still``), through the pipeline until its first bootstrap: (that frame's result,
    the frames (stamp, image, T_world_cam), the inputs of every try_pair, the camera,
    the config)."""
    cfg = SynthConfig(frames=60, seed=seed, trajectory=trajectory, **camera)
    frames = standing_first(list(render_sequence(cfg)), standing,
                            np.random.default_rng([seed, 30]))
    camera = PinholeCamera.from_camera_info({'width': cfg.width, 'height': cfg.height,
                                             'K': cfg.K(), 'D': cfg.D(),
                                             'distortion_model': 'plumb_bob'})
    vo_cfg = VoConfig()
    vo = VisualOdometry(vo_cfg, camera, seed=seed)
    pairs = []                       # the real try_pair, its inputs kept
    try_pair = vo.bootstrapper.try_pair

    def keeping_the_pair(ids_ref, px_ref, ids_cur, px_cur, *args, **kwargs):
        pairs.append((ids_ref.copy(), px_ref.copy(), ids_cur.copy(), px_cur.copy()))
        return try_pair(ids_ref, px_ref, ids_cur, px_cur, *args, **kwargs)

    vo.bootstrapper.try_pair = keeping_the_pair
    try:
        for stamp, img, _ in frames:
            res = vo.process(img, stamp)
            if res.ok and res.bootstrapped:
                return res, frames, pairs, camera, vo_cfg
    finally:
        if vo.local_map is not None:
            vo.local_map.close()
    raise AssertionError(f'no bootstrap in {len(frames)} frames')


def _pose_at(frames, stamp_ns: int) -> np.ndarray:
    return next(T for stamp, _, T in frames if stamp == stamp_ns)


def test_the_rendered_walk_after_standing_bootstraps_in_the_truths_basin() -> None:
    """The rendered walk, seed 6, its first view held for 1 s (sensor noise 2 grey
    levels): the bootstrap pair's rotation was 3.1 deg off, in the other basin of the
    epipolar cost. Now the model is the minimum of the basin that holds the truth (the
    pair's own points, polished from the true relative pose, give the same rotation),
    and that minimum is near the truth.

    On an AMD EPYC without AVX-512 it once was 1.38 deg off (pair 0-57, a NEES of 48
    against its anchor): the lens fall-off had been learnt from the standing frames'
    tracks, which measure none, and the correction put in force bent the tracks
    (docs/method.md §2.1.1, §6.11). Without it the pair is 0.15 deg off there."""
    res, frames, pairs, camera, vo_cfg = _first_bootstrap_after_standing('walk', 6)
    ref = res.reference_frame_index
    # the world frame is the standing camera's: the estimate's rotation is relative to it
    assert np.allclose(frames[ref][2][:3, :3], frames[0][2][:3, :3])
    R_est_cur_ref = res.T_world_cam[:3, :3].T
    T_cur_ref_true = np.linalg.inv(_pose_at(frames, res.stamp_ns)) @ frames[ref][2]
    t_true = T_cur_ref_true[:3, 3] / np.linalg.norm(T_cur_ref_true[:3, 3])
    _, p_ref, p_cur = common_tracks(*pairs[-1])
    thr = vo_cfg.bootstrap_ransac_px
    gate, huber = 3.0 * thr, 2.0 * thr          # the bootstrap's polish (bootstrap.py)
    R_basin, t_basin = refine_relative_pose(T_cur_ref_true[:3, :3], t_true, p_ref, p_cur,
                                            camera.K, gate_px=gate, huber_px=huber)
    # the same basin: the valley's floor is flat to a few tenths of a degree (§2.1.1:
    # the same basin polished further moved the rotation by up to 0.24 deg), the other
    # basin is 2-3 deg away
    assert _angle_deg(R_est_cur_ref @ R_basin.T) < 0.5
    assert _angle_deg(R_est_cur_ref @ T_cur_ref_true[:3, :3].T) < 0.5
    # and no better fit than the estimate by more than chance (other_basin's test)
    t_est = res.T_world_cam[:3, :3].T @ -res.T_world_cam[:3, 3]
    t_est /= np.linalg.norm(t_est)
    r = np.abs(sampson_px(R_est_cur_ref, t_est, p_ref, p_cur, camera.K))
    var = float(np.mean(r[r < gate] ** 2))
    gain = robust_sampson_cost(R_est_cur_ref, t_est, p_ref, p_cur, camera.K, gate, huber) \
        - robust_sampson_cost(R_basin, t_basin, p_ref, p_cur, camera.K, gate, huber)
    assert 2.0 * gain / var < 20.52


def test_the_rendered_orbit_after_standing_waits_out_the_planar_ambiguity() -> None:
    """The rendered orbit, seed 77, its first view held for 1 s: the pair 0-49 has two
    relative poses 8.3 deg apart that fit its tracks within chance (the homography's two
    decompositions, both with every point in front), and RANSAC took the wrong one; the
    map was then published up to 18 deg off with a covariance of 0.4 deg. Such a pair is
    refused now, and the one taken is near the truth (docs/method.md §2.1.2)."""
    res, frames, _, _, _ = _first_bootstrap_after_standing('orbit', 77)
    T_cur_ref_true = np.linalg.inv(_pose_at(frames, res.stamp_ns)) @ \
        frames[res.reference_frame_index][2]
    assert _angle_deg(res.T_world_cam[:3, :3].T @ T_cur_ref_true[:3, :3].T) < 0.5


def test_a_flat_scenes_other_pose_that_fits_better_is_held_by_the_covariance() -> None:
    """The rendered orbit through the narrow lens (39 deg across), seed 1: the pair 0-9
    is right (0.2 deg), but the homography's other pose, 2.3 deg away, fits its tracks
    better by chi 35, and waiting does not tell them apart (the tracks favour the wrong
    pose until frame 23). The pair is taken, and its published covariance holds the
    other pose: a sigma of more than 2 deg, where it was 0.5 deg before the rival was
    counted (docs/method.md §2.1.2)."""
    res, frames, _, _, _ = _first_bootstrap_after_standing('orbit', 1, standing=0,
                                                           fx=900.0)
    R_world_cam = res.T_world_cam[:3, :3]
    T_cur_ref_true = np.linalg.inv(_pose_at(frames, res.stamp_ns)) @ \
        frames[res.reference_frame_index][2]
    assert _angle_deg(R_world_cam.T @ T_cur_ref_true[:3, :3].T) < 0.5
    sigma_deg = np.degrees(np.sqrt(np.linalg.eigvalsh(res.pose_cov[3:, 3:])))
    assert sigma_deg.max() > 2.0


def test_the_winning_model_keeps_the_translation_in_front_with_outliers() -> None:
    """The sign of t is voted by the winning model's inliers only: 45 % of the
    correspondences are random and must not turn the camera round. (With that many
    outliers the truncated cost is bumpy: from this start the model ends 0.01-0.55 deg
    off, against 0.01-0.04 from the truth; the other basin is 1-3 deg away.)"""
    for seed in range(20):
        p_ref, p_cur, R_true, t_true = _forward_pair(seed)
        rng = np.random.default_rng(100 + seed)
        bad = rng.random(len(p_cur)) < 0.45
        p_cur = p_cur.copy()
        p_cur[bad] = rng.uniform([0, 0], [640, 480], (int(bad.sum()), 2))
        turned = cv2.Rodrigues(np.array([0.0, np.radians(40.0), 0.0]).reshape(3, 1))[0] \
            @ t_true
        R, t = polish(R_true, turned, p_ref, p_cur)
        assert float(t @ t_true) > 0.9, seed
        assert _angle_deg(R @ R_true.T) < 1.0, seed


def test_bench_bootstrap_pairs_reports_the_first_pair() -> None:
    """`python -m bench.bootstrap_pairs`: one row per run, with the pair and a small
    error on the rendered walk; a real sequence's name is refused in one line."""
    proc = run_benchmark('bootstrap_pairs', '--sequences', 'walk', '--seeds', '0',
                         timeout=600)
    assert proc.returncode == 0, proc.stderr
    rows = [r for r in proc.stdout.splitlines() if r.startswith('| walk |')]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip('|').split('|')]
    assert cells[2].startswith('0-') and float(cells[3]) < 0.5
    refused = run_benchmark('bootstrap_pairs', '--sequences', 'kitti_raw', timeout=120)
    assert refused.returncode == 2
    assert len(refused.stderr.strip().splitlines()) == 1 and 'kitti_raw' in refused.stderr

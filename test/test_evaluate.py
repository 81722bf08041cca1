"""Tests for ekf_vo.io.trajectory and ekf_vo.tools.evaluate (evo-based evaluation).

The key cross-check: ``evaluate()`` uses evo's association, Umeyama alignment and APE/RPE;
here the same numbers are recomputed with an independent numpy Umeyama implementation.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ekf_vo.tools.evaluate import EvalResult, EvaluationError, evaluate
from ekf_vo.io.trajectory import read_gt_from_bag, read_trajectory, read_tum, write_tum

T0 = 1_700_000_000.0  # realistic epoch stamps exercise float precision
SCALE_EST = 0.37      # estimate is 0.37 x the true size -> evo's Sim(3) scale is 1/0.37


# ----------------------------------------------------------------------------- helpers
def make_gt(n: int = 100, rate_hz: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth non-planar GT: (stamps (n,), T_world_cam (n, 4, 4))."""
    t = np.arange(n) / rate_hz
    u = 2.0 * np.pi * t / (n / rate_hz)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = 3.0 * np.cos(u)
    T[:, 1, 3] = 2.0 * np.sin(u)
    T[:, 2, 3] = 0.5 * np.sin(2.0 * u) + 0.2 * t
    T[:, :3, :3] = Rotation.from_euler('zyx', np.c_[u, 0.2 * np.sin(u), 0.1 * np.cos(3 * u)]
                                       ).as_matrix()
    return T0 + t, T


def apply_sim3(T: np.ndarray, s: float, R0: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """Left-apply a Sim(3) to poses: R' = R0 R, t' = s R0 t + t0 (result stays SE(3))."""
    out = T.copy()
    out[:, :3, :3] = R0 @ T[:, :3, :3]
    out[:, :3, 3] = s * T[:, :3, 3] @ R0.T + t0
    return out


def umeyama_np(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Independent Umeyama (1991) Sim(3): dst ~= s R src + t for (N, 3) point sets."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    var_s = np.mean(np.sum(xs ** 2, axis=1))
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def known_sim3() -> tuple[float, np.ndarray, np.ndarray]:
    R0 = Rotation.from_euler('xyz', [25.0, -40.0, 110.0], degrees=True).as_matrix()
    return SCALE_EST, R0, np.array([4.0, -2.5, 1.2])


def cli_cmd() -> list[str]:
    script = Path(sys.executable).parent / 'ekf-vo-eval'
    if script.exists():
        return [str(script)]
    return [sys.executable, '-m', 'ekf_vo.tools.evaluate']


# ----------------------------------------------------------------------------- (a) cross-check
def test_sim3_noisy_matches_independent_umeyama() -> None:
    rng = np.random.default_rng(7)
    stamps, gt = make_gt(100)
    sigma = 0.003  # position noise per axis, in GT metres
    noisy = gt.copy()
    noisy[:, :3, 3] += rng.normal(0.0, sigma, size=(100, 3))
    s0, R0, t0 = known_sim3()
    est = apply_sim3(noisy, s0, R0, t0)

    r = evaluate(stamps, gt, stamps, est)
    assert isinstance(r, EvalResult)
    assert r.n_matched == 100 and r.pct_tracked == pytest.approx(100.0)
    # Estimate is 0.37 x true size, so the scale evo applies to it is ~1/0.37.
    assert r.sim3_scale == pytest.approx(1.0 / s0, rel=5e-3)
    assert r.scale_error_pct == pytest.approx(100.0 * (s0 - 1.0), rel=5e-3)  # ~ -63 %
    # ATE at the noise level: E|n| ~ sigma*sqrt(3) minus the 7 fitted DOF.
    assert 0.5 * sigma * np.sqrt(3) < r.ate_sim3_rmse < 1.5 * sigma * np.sqrt(3)
    assert r.ate_se3_rmse > 10 * r.ate_sim3_rmse  # no scale correction -> large error
    assert r.rot_err_max_deg < 0.5  # noise only in positions

    # Independent numpy computation on the same associated points.
    s, R, t = umeyama_np(est[:, :3, 3], gt[:, :3, 3])
    aligned = s * est[:, :3, 3] @ R.T + t
    err = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    assert r.sim3_scale == pytest.approx(s, rel=1e-9)
    assert r.ate_sim3_rmse == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-6)
    assert r.ate_sim3_max == pytest.approx(err.max(), rel=1e-6)
    np.testing.assert_allclose(r.trans_err_m, err, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(r.T_gt_est_sim3[:3, :3], s * R, atol=1e-9)

    # RPE (delta 1 frame) on the Sim(3)-aligned estimate, recomputed by hand.
    P = est.copy()
    P[:, :3, :3] = R @ est[:, :3, :3]
    P[:, :3, 3] = aligned
    inv = np.linalg.inv
    e_t, e_r = [], []
    for i in range(99):
        E = inv(inv(gt[i]) @ gt[i + 1]) @ (inv(P[i]) @ P[i + 1])
        e_t.append(np.linalg.norm(E[:3, 3]))
        e_r.append(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))
    assert r.rpe_trans_rmse == pytest.approx(np.sqrt(np.mean(np.square(e_t))), rel=1e-6)
    assert r.rpe_rot_rmse_deg == pytest.approx(np.sqrt(np.mean(np.square(e_r))),
                                               rel=1e-6, abs=1e-9)

    # Path length and percentage.
    gt_len = np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))
    assert r.path_length_gt_m == pytest.approx(gt_len, rel=1e-12)
    assert r.ate_sim3_pct_of_path == pytest.approx(100 * r.ate_sim3_rmse / gt_len, rel=1e-12)


# ----------------------------------------------------------------------------- (b) exact copy
def test_exact_sim3_copy_gives_zero_error() -> None:
    stamps, gt = make_gt(100)
    s0, R0, t0 = known_sim3()
    est = apply_sim3(gt, s0, R0, t0)
    r = evaluate(stamps, gt, stamps, est)
    assert r.ate_sim3_rmse < 1e-9
    assert r.ate_sim3_max < 1e-9
    assert r.rot_err_max_deg < 1e-5
    assert r.rpe_trans_rmse < 1e-9
    assert r.rpe_rot_rmse_deg < 1e-5
    assert r.sim3_scale == pytest.approx(1.0 / s0, rel=1e-9)
    # The alignment is the inverse of the applied transform.
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = s0 * R0, t0
    np.testing.assert_allclose(r.T_gt_est_sim3 @ S, np.eye(4), atol=1e-9)


def test_input_not_modified() -> None:
    stamps, gt = make_gt(50)
    s0, R0, t0 = known_sim3()
    est = apply_sim3(gt, s0, R0, t0)
    est_before, gt_before = est.copy(), gt.copy()
    evaluate(stamps, gt, stamps, est)
    np.testing.assert_array_equal(est, est_before)
    np.testing.assert_array_equal(gt, gt_before)


# ----------------------------------------------------------------------------- (c) TUM I/O
def test_tum_round_trip(tmp_path: Path) -> None:
    stamps, gt = make_gt(100)
    stamps = stamps + 1e-7 * np.arange(100)  # sub-microsecond digits must survive
    path = tmp_path / 'sub' / 'traj.tum'
    write_tum(path, stamps, gt)
    s2, T2 = read_tum(path)
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(T2, gt, atol=5e-9)
    assert path.read_text().startswith('#')
    s3, T3 = read_trajectory(path)  # auto-detect: TUM
    np.testing.assert_array_equal(s3, s2)


def test_tum_read_comments_and_errors(tmp_path: Path) -> None:
    p = tmp_path / 'c.txt'
    p.write_text('# header\n\n1.5 1 2 3 0 0 0 1\n  # indented comment\n'
                 '2.5 1 2 3 0 0 0 2  # unnormalised quaternion\n')
    s, T = read_tum(p)
    np.testing.assert_array_equal(s, [1.5, 2.5])
    np.testing.assert_allclose(T[1], np.array([[1, 0, 0, 1], [0, 1, 0, 2],
                                               [0, 0, 1, 3], [0, 0, 0, 1.0]]))
    bad = tmp_path / 'bad.txt'
    bad.write_text('1.0 1 2 3 0 0 1\n')
    with pytest.raises(ValueError, match='8 columns'):
        read_tum(bad)


# ----------------------------------------------------------------------------- (d) CLI
def test_cli_json_and_plot(tmp_path: Path) -> None:
    stamps, gt = make_gt(100)
    s0, R0, t0 = known_sim3()
    gt_path, est_path, png = tmp_path / 'gt.tum', tmp_path / 'est.tum', tmp_path / 'o' / 'e.png'
    write_tum(gt_path, stamps, gt)
    write_tum(est_path, stamps[::2] + 0.002, apply_sim3(gt[::2], s0, R0, t0))
    proc = subprocess.run(cli_cmd() + [str(gt_path), str(est_path), '--json', '--plot', str(png),
                                       '--max-diff', '0.01', '--frames', '50'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    for key in ('ate_sim3_rmse', 'ate_sim3_mean', 'ate_sim3_median', 'ate_sim3_max',
                'ate_se3_rmse', 'sim3_scale', 'rpe_trans_rmse', 'rpe_rot_rmse_deg',
                'rot_err_mean_deg', 'rot_err_max_deg', 'path_length_gt_m',
                'ate_sim3_pct_of_path', 'ate_se3_pct_of_path', 'scale_error_pct',
                'n_gt', 'n_est', 'n_matched', 'pct_tracked'):
        assert key in d
    assert d['n_matched'] == 50 and d['pct_tracked'] == pytest.approx(100.0)
    assert d['ate_sim3_rmse'] < 1e-6
    assert d['sim3_scale'] == pytest.approx(1 / s0, rel=1e-6)
    assert png.exists() and png.stat().st_size > 0

    proc = subprocess.run(cli_cmd() + [str(gt_path), str(est_path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert 'ATE Sim(3) RMSE' in proc.stdout and 'Tracked' in proc.stdout


# ----------------------------------------------------------------------------- (e) degenerate
def test_degenerate_inputs_raise() -> None:
    stamps, gt = make_gt(100)
    with pytest.raises(EvaluationError, match='associated'):  # only 2 matches
        evaluate(stamps, gt, stamps[:2], gt[:2])
    with pytest.raises(EvaluationError, match='associated'):  # no time overlap
        evaluate(stamps, gt, stamps + 100.0, gt)
    frozen = np.tile(np.eye(4), (100, 1, 1))
    frozen[:, :3, 3] = [1.0, 2.0, 3.0]
    with pytest.raises(EvaluationError, match='identical'):  # estimate never moves
        evaluate(stamps, gt, stamps, frozen)
    with pytest.raises(EvaluationError, match='identical'):  # ground truth never moves
        evaluate(stamps, frozen, stamps, gt)
    with pytest.raises(EvaluationError, match='empty'):
        evaluate(stamps, gt, np.zeros(0), np.zeros((0, 4, 4)))
    with pytest.raises(EvaluationError, match='shape'):
        evaluate(stamps, gt, stamps, gt[:, :3, :])


# ----------------------------------------------------------------------------- (f) % tracked
def test_pct_tracked_with_missing_poses() -> None:
    rng = np.random.default_rng(3)
    stamps, gt = make_gt(100)
    keep = np.r_[0:30, 70:100]  # tracking lost for 40 frames
    jitter = rng.uniform(-0.003, 0.003, keep.size)
    r = evaluate(stamps, gt, stamps[keep] + jitter, gt[keep])
    assert (r.n_gt, r.n_est, r.n_matched) == (100, 60, 60)
    assert r.pct_tracked == pytest.approx(60.0)
    r2 = evaluate(stamps, gt, stamps[keep], gt[keep], n_frames_total=120)
    assert r2.pct_tracked == pytest.approx(50.0)
    # Stamps too far off (> max diff) are not associated.
    r3 = evaluate(stamps, gt, stamps[keep] + np.where(keep < 30, 0.0, 0.02), gt[keep])
    assert r3.n_matched == 30 and r3.pct_tracked == pytest.approx(30.0)
    assert r3.path_length_gt_m < r3.path_length_gt_total_m


# ----------------------------------------------------------------------------- (g) GT from bag
def write_gt_bag(path: Path, stamps: np.ndarray, T: np.ndarray, topic: str) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    PoseStamped = ts.types['geometry_msgs/msg/PoseStamped']
    Header = ts.types['std_msgs/msg/Header']
    Time = ts.types['builtin_interfaces/msg/Time']
    Pose = ts.types['geometry_msgs/msg/Pose']
    Point = ts.types['geometry_msgs/msg/Point']
    Quaternion = ts.types['geometry_msgs/msg/Quaternion']
    quats = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # xyzw
    with Writer(path, version=9) as writer:
        conn = writer.add_connection(topic, PoseStamped.__msgtype__, typestore=ts)
        for s, Ti, q in zip(stamps, T, quats):
            ns = int(round(s * 1e9))
            msg = PoseStamped(
                header=Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id='world'),
                pose=Pose(position=Point(x=Ti[0, 3], y=Ti[1, 3], z=Ti[2, 3]),
                          orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
            writer.write(conn, ns, ts.serialize_cdr(msg, PoseStamped.__msgtype__))


def test_gt_from_bag_and_cli(tmp_path: Path) -> None:
    stamps, gt = make_gt(100)
    bag = tmp_path / 'gt_bag'
    write_gt_bag(bag, stamps, gt, '/ground_truth/pose')

    s_bag, T_bag = read_gt_from_bag(bag)
    np.testing.assert_allclose(s_bag, stamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(T_bag, gt, atol=1e-12)
    with pytest.raises(ValueError, match='not in bag'):
        read_gt_from_bag(bag, topic='/nope')

    s0, R0, t0 = known_sim3()
    est_path = tmp_path / 'est.tum'
    write_tum(est_path, stamps[10:], apply_sim3(gt[10:], s0, R0, t0))
    proc = subprocess.run(cli_cmd() + [str(bag), str(est_path), '--json'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    assert d['n_gt'] == 100 and d['n_matched'] == 90
    assert d['pct_tracked'] == pytest.approx(90.0)
    assert d['ate_sim3_rmse'] < 1e-6

    proc = subprocess.run(cli_cmd() + [str(bag), str(est_path), '--gt-topic', '/nope'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and 'not in bag' in proc.stderr

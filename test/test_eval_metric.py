"""Metric (SE(3), no scale fitted) evaluation and the 6-DoF pose NEES (ekf-vo-eval --se3).

Synthetic trajectories with known answers: a copy of the ground truth scaled by 1.1, an
exact rigid copy, and a metric estimate whose pose errors are drawn from its own published
covariances (the NEES of an honest covariance has mean 6)."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.io.trajectory import write_covariances, write_tum
from ekf_vo.tools.consistency import CHI2_6DOF_999, pose_nees, rotation_nees
from ekf_vo.tools.evaluate import evaluate, format_table

from .test_evaluate import apply_sim3, cli_cmd, make_gt

R_W = geo.rotvecs_to_matrices(np.array([[0.4, -0.9, 1.3]]))[0]   # estimate world vs GT world
T_W = np.array([2.0, -1.0, 0.5])


def honest_estimate(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                   np.ndarray]:
    """(stamps, gt_T, est_T, cov): a metric estimate in its own (rigidly moved) world whose
    6-DoF errors are drawn from its covariances (expressed in the estimate's world, position
    then world rotation vector); the first pose is exact, as the alignment assumes."""
    rng = np.random.default_rng(seed)
    stamps, gt = make_gt(n)
    D = np.diag([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    B = rng.normal(size=(n, 6, 6))
    scale = rng.uniform(0.5, 2.0, n)[:, None, None]
    cov = scale * (D @ (B @ np.transpose(B, (0, 2, 1)) / 6 + 0.5 * np.eye(6)) @ D)
    err = np.einsum('kij,kj->ki', np.linalg.cholesky(cov), rng.normal(size=(n, 6)))
    err[0] = 0.0
    true_in_est = apply_sim3(gt, 1.0, R_W, T_W)           # the truth in the estimate's world
    est = true_in_est.copy()
    est[:, :3, 3] -= err[:, :3]                           # p_true - p_est = e_p
    est[:, :3, :3] = np.transpose(geo.rotvecs_to_matrices(err[:, 3:]), (0, 2, 1)) \
        @ true_in_est[:, :3, :3]                          # R_true R_est^T = Exp(e_r)
    return stamps, gt, est, cov


# ----------------------------------------------------------------------------- evaluate()
def test_estimate_ten_percent_too_large() -> None:
    stamps, gt = make_gt(100)
    est = apply_sim3(gt, 1.1, R_W, T_W)
    r = evaluate(stamps, gt, stamps, est)
    assert r.scale_error_pct == pytest.approx(10.0, abs=1e-6)
    assert r.ate_sim3_rmse < 1e-9
    assert r.ate_se3_rmse > 0.05                         # the metric error shows the scale
    assert r.ate_se3_pct_of_path == pytest.approx(100 * r.ate_se3_rmse / r.path_length_gt_m)
    err = np.linalg.norm(r.est_xyz_aligned_se3 - r.gt_xyz, axis=1)
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(r.ate_se3_rmse, rel=1e-9)
    table = format_table(r)
    assert 'ATE SE(3) RMSE' in table and '+10.00 %' in table
    d = r.to_dict()
    assert d['scale_error_pct'] == pytest.approx(10.0, abs=1e-6) and 'ate_se3_pct_of_path' in d


def test_estimate_too_small_has_negative_scale_error() -> None:
    stamps, gt = make_gt(100)
    r = evaluate(stamps, gt, stamps, apply_sim3(gt, 0.8, R_W, T_W))
    assert r.scale_error_pct == pytest.approx(-20.0, abs=1e-6)


def test_exact_metric_estimate_has_zero_se3_error() -> None:
    stamps, gt = make_gt(100)
    r = evaluate(stamps, gt, stamps, apply_sim3(gt, 1.0, R_W, T_W))
    assert r.ate_se3_rmse < 1e-9 and r.ate_se3_pct_of_path < 1e-9
    assert abs(r.scale_error_pct) < 1e-9
    np.testing.assert_allclose(r.est_xyz_aligned_se3, r.gt_xyz, atol=1e-9)


# ----------------------------------------------------------------------------- pose NEES
def test_errors_drawn_from_the_covariance_give_a_pose_nees_of_six() -> None:
    stamps, gt, est, cov = honest_estimate(600, seed=5)
    r = pose_nees(stamps, gt, stamps, est, stamps, cov)
    assert (r.n_frames, r.n_skipped) == (600, 0)
    assert 4.5 < r.mean < 7.5
    assert 4.0 < r.median < 6.5                           # chi2(6) median 5.35
    assert r.pct_above_999 < 1.0
    assert CHI2_6DOF_999 == pytest.approx(22.458, abs=1e-3)
    # the rotation block alone, through the shared association / alignment: mean ~3
    assert 2.2 < rotation_nees(stamps, gt, stamps, est, stamps, cov).mean < 3.8
    # a covariance 4x too small (2x too confident in sigma) reads 4x larger
    over = pose_nees(stamps, gt, stamps, est, stamps, cov / 4)
    assert over.mean == pytest.approx(4 * r.mean, rel=1e-6)


def test_bad_covariances_are_skipped_and_counted() -> None:
    stamps, gt, est, cov = honest_estimate(50, seed=2)
    cov[5] = 0.0                                          # all zero
    cov[7, 0, 0] = np.nan                                 # non-finite
    v = np.arange(1.0, 7.0)
    cov[9] = np.outer(v, v)                               # rank 1
    cov[11, 3:, 3:] = 0.0                                 # rotation block missing
    r = pose_nees(stamps, gt, stamps, est, stamps, cov)
    assert (r.n_frames, r.n_skipped) == (46, 4)
    assert np.all(np.isfinite(r.nees)) and len(r.times_s) == 46
    assert not np.isin(stamps[[5, 7, 9, 11]], r.times_s).any()
    with pytest.raises(ValueError, match='positive definite'):
        pose_nees(stamps, gt, stamps, est, stamps, np.zeros_like(cov))
    with pytest.raises(ValueError, match='matches the ground truth'):
        pose_nees(stamps, gt, stamps + 100.0, est, stamps + 100.0, cov)


# ----------------------------------------------------------------------------- CLI --se3
def test_cli_se3_metric_line_pose_nees_json_and_plot(tmp_path: Path) -> None:
    stamps, gt, est, cov = honest_estimate(300, seed=9)
    gt_p, est_p, cov_p = tmp_path / 'gt.tum', tmp_path / 'est.tum', tmp_path / 'est.cov'
    big_p, png = tmp_path / 'big.tum', tmp_path / 'p' / 'se3.png'
    write_tum(gt_p, stamps, gt)
    write_tum(est_p, stamps, est)
    write_covariances(cov_p, stamps, cov)
    write_tum(big_p, stamps, apply_sim3(gt, 1.1, R_W, T_W))

    proc = subprocess.run(cli_cmd() + [str(gt_p), str(big_p), '--se3', '--plot', str(png)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    first = proc.stdout.splitlines()[0]
    assert first.startswith('metric (SE(3), no scale fitted): ATE ')
    assert '% of path; scale error +10.00 %' in first
    assert 'ATE Sim(3) RMSE' in proc.stdout and png.stat().st_size > 10_000

    proc = subprocess.run(cli_cmd() + [str(gt_p), str(est_p), '--se3', '--cov', str(cov_p)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith('metric (SE(3), no scale fitted)')
    assert 'rotation NEES' in proc.stdout and 'pose NEES (6 dof' in proc.stdout

    proc = subprocess.run(cli_cmd() + [str(gt_p), str(est_p), '--se3', '--cov', str(cov_p),
                                       '--json'], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    assert 4.5 < d['pose_nees_mean'] < 7.5
    assert d['pose_nees_frames'] == 300 and d['pose_nees_skipped'] == 0
    assert abs(d['scale_error_pct']) < 5.0 and d['ate_se3_pct_of_path'] > 0
    assert 'rot_nees_mean' in d

    # without --se3: no metric headline, no pose NEES (the scale is arbitrary)
    proc = subprocess.run(cli_cmd() + [str(gt_p), str(est_p), '--cov', str(cov_p)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'metric (SE(3)' not in proc.stdout and 'pose NEES' not in proc.stdout


def test_twist_errors_drawn_from_the_covariance_give_a_twist_nees_of_three() -> None:
    """A circle at 1 m/s and 0.5 rad/s, sampled at 100 Hz; the estimated twist is the
    true one plus noise drawn from its stated covariance: both NEES means are ~3."""
    from ekf_vo.tools.consistency import gt_twist, twist_nees
    rng = np.random.default_rng(4)
    t = np.arange(0, 20, 0.01)
    yaw = 0.5 * t
    gt = np.tile(np.eye(4), (len(t), 1, 1))
    gt[:, :3, :3] = geo.rotvecs_to_matrices(np.column_stack((0 * t, 0 * t, yaw)))
    gt[:, 0, 3], gt[:, 1, 3] = 2 * np.sin(yaw), 2 * (1 - np.cos(yaw))
    truth = np.array([gt_twist(t, gt, k) for k in range(1, len(t) - 1)])
    assert np.allclose(truth[:, :3], [1.0, 0.0, 0.0], atol=1e-3)    # forward in the body
    assert np.allclose(truth[:, 3:], [0.0, 0.0, 0.5], atol=1e-3)
    cov = np.tile(np.diag([0.01, 0.02, 0.005, 1e-4, 2e-4, 5e-5]), (len(truth), 1, 1))
    est = truth + rng.normal(size=truth.shape) * np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    r = twist_nees(t, gt, t[1:-1], est, cov, max_time_diff_s=1e-4)
    assert r.n_frames == len(truth)
    assert 2.7 < r.linear_mean < 3.3 and 2.7 < r.angular_mean < 3.3
    too_small = twist_nees(t, gt, t[1:-1], est, cov / 4, max_time_diff_s=1e-4)
    assert too_small.linear_mean > 10

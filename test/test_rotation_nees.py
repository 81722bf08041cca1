"""Rotation NEES of published poses (tools/consistency.py) and the covariance file."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ekf_vo.core import geometry as geo
from ekf_vo.io.trajectory import read_covariances, write_covariances
from ekf_vo.tools.consistency import CHI2_3DOF_999, rotation_nees
from .support.data import need_shared_data

DEMO_BAG = str(Path(__file__).resolve().parents[1] / 'bags' / 'demo')


def test_covariances_round_trip_and_bad_lines_are_one_line_errors(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 6, 6))
    cov = A @ np.transpose(A, (0, 2, 1))
    stamps = 1700000000.0 + np.arange(5) / 30
    write_covariances(tmp_path / 'c.cov', stamps, cov)
    s, c = read_covariances(tmp_path / 'c.cov')
    np.testing.assert_array_equal(s, stamps)
    np.testing.assert_allclose(c, cov, rtol=1e-8)
    (tmp_path / 'bad.cov').write_text('1.0 2.0 3.0\n')
    with pytest.raises(ValueError, match='bad.cov:1'):
        read_covariances(tmp_path / 'bad.cov')


def test_errors_drawn_from_the_covariance_give_a_nees_of_three():
    """An estimate whose rotation errors are drawn from its own covariance (in a world
    frame rotated against the ground truth's) is honest: mean ~3, ~0.1 % above 16.27."""
    rng = np.random.default_rng(1)
    n = 4000
    R_world = geo.rotvecs_to_matrices(np.array([[0.3, -1.0, 0.5]]))[0]   # frame offset
    gt_T = np.tile(np.eye(4), (n, 1, 1))
    gt_T[:, :3, :3] = geo.rotvecs_to_matrices(rng.normal(0, 1, (n, 3)))
    L = np.diag([0.01, 0.02, 0.005])
    cov_rot = L @ L.T
    est_T = gt_T.copy()
    errs = rng.normal(size=(n, 3)) @ L.T
    errs[0] = 0                                              # the aligned first pose
    for k in range(n):
        # error in the ground truth's world frame, expressed in the estimate's world
        R_true_err = geo.rotvecs_to_matrices(errs[k:k + 1])[0]
        est_T[k, :3, :3] = R_world @ R_true_err.T @ gt_T[k, :3, :3]
    cov = np.zeros((n, 6, 6))
    cov[:, :3, :3] = np.eye(3)
    cov[:, 3:, 3:] = R_world @ cov_rot @ R_world.T          # in the estimate's frame
    t = np.arange(n) / 30.0
    r = rotation_nees(t, gt_T, t, est_T, t, cov)
    assert r.n_frames == n
    assert 2.8 < r.mean < 3.2
    assert r.pct_above_999 < 0.5
    assert CHI2_3DOF_999 > 16


def test_run_writes_covariances_that_eval_reads(tmp_path):
    """ekf-vo-run --cov, then ekf-vo-eval --cov --nees-plot, on the demo bag."""
    est, cov, png = tmp_path / 'e.tum', tmp_path / 'e.cov', tmp_path / 'n.png'
    run = subprocess.run([sys.executable, '-m', 'ekf_vo.tools.run', DEMO_BAG, '-o',
                          str(est), '--cov', str(cov), '--limit', '120', '-q'],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    stamps, covs = read_covariances(cov)
    assert len(stamps) == len(est.read_text().splitlines()) - 1       # the TUM header
    assert np.all(np.linalg.eigvalsh(covs) > 0)
    ev = subprocess.run([sys.executable, '-m', 'ekf_vo.tools.evaluate', DEMO_BAG,
                         str(est), '--cov', str(cov), '--nees-plot', str(png),
                         '--frames', '120'], capture_output=True, text=True, timeout=300)
    assert ev.returncode == 0, ev.stderr
    assert 'rotation NEES' in ev.stdout and png.stat().st_size > 10_000
    bad = subprocess.run([sys.executable, '-m', 'ekf_vo.tools.evaluate', DEMO_BAG,
                          str(est), '--nees-plot', str(png)], capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_kitti_ground_truth_turns_at_a_constant_rate_the_images_contradict():
    """docs/method.md §14.4, the reason bench.rotation_nees also aligns KITTI 06 at frame
    12: over frames 0-11 the ground truth's relative rotations are constant (a driven
    car's are not), and the images' five-point rotations disagree with them several
    times more per pair than over frames 12-50 (bench.kitti_gt_check, no ekf_vo
    estimator involved)."""
    need_shared_data('kitti06_f0-50', 'the ground-truth check')
    from bench.kitti_gt_check import check
    first, rest = check(12)['stretches']
    assert np.all(first['gt_relative_rotation_std_deg'] * 20 <
                  rest['gt_relative_rotation_std_deg'])
    # disagreement per pair about the two axes the filter and the images share (y, z)
    per_pair_first = np.abs(first['summed_disagreement_deg'][1:]) / first['n_pairs']
    per_pair_rest = np.abs(rest['summed_disagreement_deg'][1:]) / rest['n_pairs']
    assert np.all(per_pair_first > 3 * per_pair_rest)
    assert np.all(np.abs(first['summed_disagreement_deg'][1:]) > 0.3)


def test_the_bench_names_a_rendered_sequence_through_another_camera():
    from bench import rotation_nees as bench
    assert bench._synthetic_name('handheld_rotation_hd') == \
        ('handheld_rotation', 1, 0, '', 'hd')
    assert bench._synthetic_name('ground_robot_x3_still_fisheye_jitter') == \
        ('ground_robot', 3, bench.STILL_FRAMES, 'jitter', 'fisheye')
    assert bench._synthetic_name('orbit') == ('orbit', 1, 0, '', '')
    assert bench._synthetic_name('kitti_raw') is None
    assert bench._synthetic_name('orbit_fisheye_x2') is None   # suffixes in their order


def test_kitti_backwards_plays_the_recorded_frames_in_reverse_at_ten_hertz():
    """bench.rotation_nees' ``kitti_reverse``: frame k played is frame n-1-k recorded, with
    its ground truth, stamped 0.1 s apart; its ``_from12`` window is the frames recorded
    from frame 12 on, which it plays first."""
    need_shared_data('kitti06_f0-50', 'the reversed KITTI sequence')
    from bench import rotation_nees as bench
    from ekf_vo.io.dataset import load_folder
    from bench.common import shared_data
    data = load_folder(shared_data('kitti06_f0-50'))
    n = len(data.stamps_ns)
    rev = bench._Resequenced(data, np.arange(n - 1, -1, -1))
    np.testing.assert_allclose(np.diff(rev.stamps_ns), data.stamps_ns[1] - data.stamps_ns[0])
    np.testing.assert_array_equal(rev.gt_T_world_cam[0], np.asarray(data.gt_T_world_cam)[-1])
    recorded = [g for _, g in data.frames()]
    played = [g for _, g in rev.frames()]
    np.testing.assert_array_equal(played[0], recorded[-1])
    np.testing.assert_array_equal(played[-1], recorded[0])
    start, end = bench._gt_reliable_window_s(rev)
    n_reliable = n - bench.KITTI_GT_RELIABLE_FROM
    assert start == pytest.approx(rev.stamps_ns[0] * 1e-9)
    assert end == pytest.approx(rev.stamps_ns[n_reliable - 1] * 1e-9)
    # as recorded, the window is the frames from 12 to the end
    assert bench._gt_reliable_window_s(data) == pytest.approx(
        (data.stamps_ns[bench.KITTI_GT_RELIABLE_FROM] * 1e-9, data.stamps_ns[-1] * 1e-9))


def test_kitti_started_later_plays_the_recorded_frames_from_there():
    """bench.rotation_nees' ``kitti_raw_startN``: the recorded frames from N on, with
    their ground truth; its ``_from12`` window still starts at recorded frame 12."""
    from bench import rotation_nees as bench
    assert bench._kitti_start('kitti_jpeg_start8') == ('kitti_jpeg', 8)
    assert bench._kitti_start('kitti_raw') == ('kitti_raw', 0)
    assert bench._kitti_start('kitti_2x_start8') == ('kitti_2x_start8', 0)   # not a variant
    need_shared_data('kitti06_f0-50', 'KITTI started later')
    from ekf_vo.io.dataset import load_folder
    from bench.common import shared_data
    data = load_folder(shared_data('kitti06_f0-50'))
    later, frames, _ = bench._folder_frames('kitti_raw_start5')
    played = [g for _, g, _ in frames]
    recorded = [g for _, g in data.frames()]
    assert len(played) == len(recorded) - 5
    # with the stamps they were recorded with (a node started later sees those)
    assert later.stamps_ns == [int(t) for t in data.stamps_ns[5:]]
    np.testing.assert_allclose(later.gt_stamps_s, np.asarray(data.stamps_ns[5:]) * 1e-9)
    np.testing.assert_array_equal(played[0], recorded[5])
    np.testing.assert_array_equal(later.gt_T_world_cam[0], np.asarray(data.gt_T_world_cam)[5])
    start, _ = bench._gt_reliable_window_s(later)
    assert start == pytest.approx(data.stamps_ns[bench.KITTI_GT_RELIABLE_FROM] * 1e-9)
    with pytest.raises(ValueError, match='has 51 frames'):
        bench._folder_frames('kitti_raw_start60')


def test_a_jpeg_variant_names_its_quality():
    """``kitti_jpeg30`` and the ``_jpeg30`` suffix encode at quality 30 (``kitti_jpeg``,
    ``_jpeg``: 75); a quality outside 1..100 is a one-line error with exit 2."""
    from bench import rotation_nees as bench
    assert bench._jpeg_quality('jpeg') == bench.JPEG_QUALITY == 75
    assert bench._jpeg_quality('jpeg30') == 30
    assert bench._jpeg_quality('raw') is None and bench._jpeg_quality('2x') is None
    assert bench._real_sequence('kitti_jpeg30_start6_from12') == 'kitti_jpeg'
    assert bench._real_sequence('kitti_raw_from12') == 'kitti_raw'
    assert bench._synthetic_name('walk_jpeg30') == ('walk', 1, 0, '', 'jpeg30')
    assert bench._synthetic_name('orbit_x2_jpeg50_flicker') == ('orbit', 2, 0, 'flicker',
                                                                'jpeg50')
    rng = np.random.default_rng(0)
    gray = np.clip(rng.normal(128, 40, (48, 64)), 0, 255).astype(np.uint8)
    # a lower quality loses more of the image
    errs = [np.abs(bench._jpeg(gray, q).astype(int) - gray).mean() for q in (90, 75, 30)]
    assert errs[0] < errs[1] < errs[2]
    np.testing.assert_array_equal(bench._jpeg(gray), bench._jpeg(gray, 75))
    out = subprocess.run([sys.executable, '-m', 'bench.rotation_nees', '--sequences',
                          'walk_jpeg0'], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        'bench.rotation_nees: JPEG quality 0 is not in 1..100']

"""The benchmark in quick mode (what `make bench-quick` runs), end to end, ~2-3 minutes.

Checks that the report, the JSON and the plots are written, that the key figures are
finite, and the qualitative claims that are robust at quick-mode sizes: the EKF beats
per-frame EPnP on the bunny at 3 px, its covariance is consistent, the camera-only update
grows about linearly with the number of points while EKF-SLAM grows faster, and memory
stays flat. Sections on ../shared/data skip their parts when it is absent.
"""
import json
import math

import pytest

from .support.benchmarks import run_benchmark
from .support.data import need_shared_data, shared_data

pytestmark = pytest.mark.data


@pytest.fixture(scope='module')
def quick_run(tmp_path_factory):
    need_shared_data('bunny', 'benchmark')
    out = tmp_path_factory.mktemp('bench')
    status = run_benchmark('run_all', '--quick', '--out', str(out)).returncode
    return status, out, json.loads((out / 'results.json').read_text())


def _finite(*xs):
    return all(isinstance(x, (int, float)) and math.isfinite(x) for x in xs)


def test_outputs_written(quick_run):
    status, out, res = quick_run
    assert status == 0, res['meta']['failed']
    report = (out / 'report.md').read_text()
    for title in ('## Summary', '## 1.', '## 2.', '## 3.', '## 4.', '## 5.', '## 6.', '## 7.'):
        assert title in report
    for png in ('bunny_per_pose.png', 'bunny_noise_sweep.png', 'fading_memory_focal.png',
                'precise_points.png', 'speed.png', 'scaling.png', 'memory.png'):
        assert (out / png).stat().st_size > 10_000, png
        assert f'({png})' in report
    if shared_data('kitti06_f0-50') is not None:
        assert (out / 'real_data.png').is_file()


def test_bunny_ekf_beats_epnp_at_3px_and_is_consistent(quick_run):
    _, _, res = quick_run
    b = res['bunny']
    m = b['mean']
    assert _finite(m['ekf_trans_pct'], m['epnp_trans_pct'], m['ekf_rot_deg'], m['epnp_rot_deg'])
    assert b['setup']['all_visible'] and b['setup']['all_dof_change_every_step']
    assert b['setup']['points'] == 453 and b['setup']['poses'] == 55
    assert m['ekf_trans_pct'] < m['epnp_trans_pct']
    assert m['ekf_rot_deg'] < m['epnp_rot_deg']
    assert b['checks']['epnp_zero_at_zero_noise']
    # NEES of a 6-dof pose: mean 6 for an honest covariance
    assert 3.0 < b['nees']['ekf_mean'] < 10.0
    assert 3.0 < res['consistency']['nees_mean'] < 10.0


def test_fading_memory_figures_finite(quick_run):
    _, _, res = quick_run
    s = res['fading_memory']['focal']['summary']
    assert 1.0 <= s['S_tuned_on_a'] <= 1.02
    for name in ('a_yaw10', 'b_yaw20_pitch20', 'c_yaw70'):
        r = s[name]
        assert _finite(r['plain_heading_mean_abs'], r['tuned_heading_mean_abs'],
                       r['plain_pitch_mean_abs'])
        assert r['plain_heading_mean_abs'] < 5.0    # no divergence with a fixed map


def test_precise_points_fraction(quick_run):
    _, _, res = quick_run
    r = res['precise_points']['synthetic_room']
    assert r['frames_scored'] >= 0.8 * r['frames']
    assert 0.0 < r['fraction_mean'] <= 1.0


def test_update_cost_linear_for_camera_only_superlinear_for_slam(quick_run):
    _, _, res = quick_run
    sc = res['scaling']
    assert sc['equivalence_max_abs_diff'] < 1e-8
    assert sc['camera_only_slope'] < 1.5
    assert sc['slam_slope'] > sc['camera_only_slope'] + 0.5
    # at the largest size both ran, SLAM is far slower
    n = sc['slam_n_points'][-1]
    cam = sc['camera_only_ms'][sc['n_points'].index(n)]
    assert sc['slam_ms'][-1] > 20 * cam


def test_speed_and_memory(quick_run):
    _, _, res = quick_run
    assert res['throughput']['demo_640x480']['fps'] > 5.0
    for key in ('latency', 'latency_kitti'):
        lat = res['throughput'][key]
        if 'skipped' in lat:
            continue
        # with a map_node beside, every frame after the first pose is answered or was
        # dropped by vo_node's live queue because the estimator was behind, and counted so
        # (docs/ros.md); behind rarely: at most a tenth of the frames (0-1 of 100 at 30 Hz
        # on this 2-core machine, which also runs the player and map_node). The speed
        # target itself (no drop, p95) is bench.latency's and the report's.
        dropped = lat['dropped_behind']
        assert lat['no_odometry_after_first'] <= dropped, lat
        assert dropped <= 0.1 * lat['frames_sent'], lat
        assert lat['map_clouds_nonempty'] > 0, lat
    m = res['memory']
    assert m['rss_flat'], m['rss_growth_second_half_mb_per_1000_frames']
    assert m['map_size_max'] <= m['map_bound']
    assert m['pct_frames_ok'] > 90.0


def test_real_data_tabulated(quick_run):
    _, _, res = quick_run
    for s in ('kitti06_f0-50', 'middlebury_dino'):
        if shared_data(s) is None:
            continue
        r = res['real_compare'][s]
        for e in ('ekf', 'iekf', 'epnp'):
            assert _finite(r[e]['ate_pct_path']['mean'], r[e]['pct_tracked']['mean'])


def test_local_map_section_tabulated(quick_run):
    """bench.local_map in the report: both configurations, all four bags, every seed
    bootstrapped and evaluated."""
    _, out, res = quick_run
    if shared_data('kitti06_f0-50') is None:
        assert 'skipped' in res['local_map']
        return
    assert '## Local map: KITTI 06' in (out / 'report.md').read_text()
    for config in res['local_map'].values():
        assert set(config['variants']) == {'raw-before', 'raw-after', 'jpeg-before',
                                           'jpeg-after'}
        for v in config['variants'].values():
            s = v['summary']
            assert s['no_pose'] == 0 and s['no_eval'] == 0
            assert _finite(s['ate_pct_mean'], s['ate_pct_max'])


def test_without_the_data_folder_the_data_sections_skip_and_the_run_succeeds(tmp_path,
                                                                             monkeypatch):
    """A user's fresh clone has no data folder: `make bench-quick` must still succeed."""
    monkeypatch.setenv('EKF_VO_SHARED_DATA', str(tmp_path / 'no_data_here'))
    out = tmp_path / 'bench'
    proc = run_benchmark('run_all', '--quick', '--only', 'bunny', 'consistency',
                         '--out', str(out), timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = (out / 'report.md').read_text()
    assert '## bunny: skipped (' in report and 'Failed sections' not in report

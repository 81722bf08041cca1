"""bench.start_offsets: every estimator on the same demo frames from several start frames
(docs/method.md §9.4). Guards that the comparison runs and means what it says; the
figures themselves are the benchmark's."""
import math

from bench.start_offsets import paired_lower_ate

from .support.benchmarks import benchmark_json, run_benchmark


def test_each_estimator_runs_from_each_start_frame(tmp_path):
    res = benchmark_json('start_offsets', tmp_path / 'offsets.json', '--offsets', '2',
                         '--estimators', 'ekf', 'epnp')
    assert set(res['runs']) == {'ekf', 'epnp'}
    for est, runs in res['runs'].items():
        assert [r['start'] for r in runs] == [0, 1]
        for r in runs:
            # the demo's 300 frames less the start and the bootstrap's few
            assert r['published'] > 250, (est, r)
            assert all(math.isfinite(r[k]) and r[k] > 0 for k in
                       ('ate_sim3_rmse', 'rpe_trans_rmse', 'rot_err_max_deg')), (est, r)
            assert r['ate_sim3_rmse'] < 0.1, (est, r)   # metres; the demo's path is 5.6 m
    # the paired view: at how many starts each one's ATE is the lower, as its ATEs say
    ekf, epnp = res['runs']['ekf'], res['runs']['epnp']
    assert res['paired_lower_ate'] == {'ekf vs epnp': [
        sum(a['ate_sim3_rmse'] < b['ate_sim3_rmse'] for a, b in zip(ekf, epnp)),
        sum(b['ate_sim3_rmse'] < a['ate_sim3_rmse'] for a, b in zip(ekf, epnp))]}


def test_a_bad_override_is_one_line_and_exit_2():
    for bad in ('no_such_parameter=1', 'estimator=iekf'):   # the latter: --estimators'
        proc = run_benchmark('start_offsets', '--set', bad)
        assert proc.returncode == 2, bad
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert 'Traceback' not in proc.stderr


def test_paired_counts_leave_ties_to_neither():
    def runs(*ates):
        return [{'ate_sim3_rmse': a} for a in ates]
    pairs = paired_lower_ate({'ekf': runs(1.0, 2.0, 3.0, 4.0),
                              'epnp': runs(2.0, 1.0, 3.0, 5.0),
                              'iekf': runs(0.5, 0.5, 0.5, 9.0)})
    assert pairs == {'ekf vs epnp': [2, 1],      # start 2 is a tie
                     'ekf vs iekf': [1, 3], 'epnp vs iekf': [1, 3]}

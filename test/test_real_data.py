"""The core offline on the real sequences of ../shared/data (skipped when it is absent).

Accuracy targets with numbers live in the benchmark (python -m bench.real_data);
these tests guard the behaviour the issue asks for, with the issue's own bounds.
"""
import numpy as np
import pytest

from bench.common import shared_data
from bench.real_data import run_sequence

pytestmark = pytest.mark.data


def _need(name):
    if shared_data(name) is None:
        pytest.skip(f'../shared/data/{name} is absent (a fresh clone): real-data test skipped')


def test_kitti06_tracks_95_percent_with_ate_under_2_percent_of_path():
    _need('kitti06_f0-50')
    r = run_sequence('kitti06_f0-50', seed=0)
    print(f"KITTI 06: tracked {r['pct_tracked']:.1f} %, ATE {r['ate_sim3_rmse']:.3f} m = "
          f"{r['ate_pct_path']:.2f} % of {r['path_length']:.1f} m, {r['fps']:.1f} fps")
    assert r['pct_tracked'] >= 95.0
    assert r['ate_pct_path'] <= 2.0
    assert r['n_resets'] == 0


def test_middlebury_dino_tracks_every_view_after_ground_truth_bootstrap():
    _need('middlebury_dino')
    r = run_sequence('middlebury_dino', seed=0)
    # view 0 is the bootstrap reference (its pose is given, not estimated); every later
    # view must produce a pose
    assert r['frames_tracked'] == r['frames'] - 1
    assert r['n_resets'] == 0
    # the trajectory is the ring of views, not a collapse (generous bound; numbers in bench)
    assert r['ate_pct_path'] < 3.0
    stamps = np.array(r['est_stamps'])
    assert np.all(np.diff(stamps) > 0)

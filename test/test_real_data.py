"""The core offline on the real sequences of ../shared/data (skipped when it is absent).

Accuracy targets with numbers live in the benchmark (python -m bench.real_data);
these tests guard the behaviour the issue asks for, with the issue's own bounds, on one
seeded run of the benchmark (`--single`, the sequence's preset).
"""
from pathlib import Path

import numpy as np
import pytest

from .support.benchmarks import benchmark_json
from .support.data import need_shared_data

pytestmark = pytest.mark.data


def run_sequence(name: str, tmp_path: Path, seed: int = 0) -> dict:
    need_shared_data(name, 'real-data test')
    return benchmark_json('real_data', tmp_path / f'{name}.json', name, '--single',
                          '--seed', str(seed))


def test_kitti06_tracks_95_percent_with_ate_under_2_percent_of_path(tmp_path):
    r = run_sequence('kitti06_f0-50', tmp_path, seed=0)
    print(f"KITTI 06: tracked {r['pct_tracked']:.1f} %, ATE {r['ate_sim3_rmse']:.3f} m = "
          f"{r['ate_pct_path']:.2f} % of {r['path_length']:.1f} m, {r['fps']:.1f} fps")
    assert r['pct_tracked'] >= 95.0
    assert r['ate_pct_path'] <= 2.0
    assert r['n_resets'] == 0


def test_middlebury_dino_tracks_every_view_after_ground_truth_bootstrap(tmp_path):
    r = run_sequence('middlebury_dino', tmp_path, seed=0)
    # view 0 is the bootstrap reference (its pose is given, not estimated); every later
    # view must produce a pose
    assert r['frames_tracked'] == r['frames'] - 1
    assert r['n_resets'] == 0
    # the trajectory is the ring of views, not a collapse (generous bound; numbers in bench)
    assert r['ate_pct_path'] < 3.0
    stamps = np.array(r['est_stamps'])
    assert np.all(np.diff(stamps) > 0)

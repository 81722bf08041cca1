"""bench.keyframe_pairs: the truth a keyframe-pair check is set beside, and a recorder that
leaves the pipeline as it is (docs/method.md §15.4). The figures are the benchmark's."""
import numpy as np
import pytest

from bench.keyframe_pairs import pair_truth, recording
from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core import pipeline, rotation_check
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.demo import load_demo_frames


def _R(rotvec_deg):
    return geo.quat_to_matrix(geo.rotvec_to_quat(np.radians(np.asarray(rotvec_deg, float))))


def test_the_true_discrepancy_is_the_filters_error_over_the_pair_in_any_gauge():
    R_gt_a, R_gt_b = _R([0, 10, 0]), _R([3, 25, -2])
    drift = _R([0.5, 0, 0])                  # the filter's b is off by 0.5 deg (world)
    R_a, R_b = R_gt_a, drift @ R_gt_b
    d = pair_truth(R_a, R_b, R_gt_a, R_gt_b)
    assert np.degrees(np.linalg.norm(d)) == pytest.approx(0.5, abs=1e-9)
    # the ground truth in another world frame: the same discrepancy
    G = _R([40, -70, 15])
    assert np.allclose(pair_truth(R_a, R_b, G @ R_gt_a, G @ R_gt_b), d, atol=1e-12)
    assert np.allclose(pair_truth(R_gt_a, R_gt_b, R_gt_a, R_gt_b), 0.0, atol=1e-12)


def _demo_poses(n_frames):
    info, frames = load_demo_frames()
    stream = VoStream(VoConfig(), seed=0)
    stream.set_camera(info)
    poses = []
    for stamp, gray in frames[:n_frames]:
        res = stream.process(gray, stamp)
        if res.ok:
            poses.append((res.T_world_cam.copy(), res.pose_cov.copy()))
    stream.vo.close()
    return poses


def test_recording_the_checks_changes_nothing_and_puts_the_pipeline_back():
    plain = _demo_poses(120)
    with recording() as records:
        recorded = _demo_poses(120)
    assert rotation_check.check_rotation.__name__ == 'check_rotation'
    assert rotation_check._closest.__name__ == '_closest'
    assert pipeline.VisualOdometry._check_rotation.__name__ == '_check_rotation'
    assert records, 'the demo makes keyframe-pair checks in its first 120 frames'
    assert all(a < b for a, b, *_ in records)
    assert len(plain) == len(recorded)
    for (T0, C0), (T1, C1) in zip(plain, recorded):
        assert np.array_equal(T0, T1) and np.array_equal(C0, C1)

"""bench.keyframe_pairs: the truth a keyframe-pair check is set beside, and the record of
each check a frame's result carries (FrameResult.keyframe_pair_check, docs/method.md
§15.4). The figures are the benchmark's."""
import numpy as np
import pytest

from bench.keyframe_pairs import pair_truth, records_of
from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
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


def _demo_results(n_frames):
    info, frames = load_demo_frames()
    stream = VoStream(VoConfig(), seed=0)
    stream.set_camera(info)
    results = [stream.process(gray, stamp) for stamp, gray in frames[:n_frames]]
    stream.vo.close()
    return results


def test_each_keyframe_pair_check_is_on_the_result_of_the_frame_that_took_it():
    results = _demo_results(120)
    records = records_of(results)
    assert records, 'the demo makes keyframe-pair checks in its first 120 frames'
    taken_at = [k for k, r in enumerate(results) if r.keyframe_pair_check is not None]
    for k, record in zip(taken_at, records):
        a, b, check = record.frame_a, record.frame_b, record.check
        R_a, R_b = record.R_world_a, record.R_world_b
        # a pair of earlier keyframes, taken on the frame after the newest of them (the
        # check runs in a worker and is taken before the next frame's verdict)
        assert a < b and k == b + 1
        assert np.allclose(R_a @ R_a.T, np.eye(3)) and np.allclose(R_b @ R_b.T, np.eye(3))
        if check is not None:
            # the verdict was weighed against its candidates: the reported one among them
            candidates = check.candidates
            assert candidates
            d = [np.degrees(np.linalg.norm(geo.quat_to_rotvec(geo.matrix_to_quat(
                R_a.T @ R_b @ R_c)))) for R_c, _ in candidates]
            assert min(abs(x - check.angle_deg) for x in d) < 1e-6
    assert any(record.check is not None for record in records)

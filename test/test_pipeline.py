"""The per-frame pipeline on rendered images: tracking, EPnP baseline, loss and recovery,
bad input. Accuracy numbers live in the benchmarks; these guard behaviour with margins."""
import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import TrackingState, VisualOdometry
from ekf_vo.core.stream import VoStream
from ekf_vo.io.dataset import load_folder
from ekf_vo.tools.evaluate import evaluate
from ekf_vo.tools.synth import SynthConfig, render_sequence

from .support.data import need_shared_data


@pytest.fixture(scope='module')
def sequence():
    cfg = SynthConfig(frames=150, seed=3, trajectory='walk')
    frames = list(render_sequence(cfg))
    camera = PinholeCamera(cfg.width, cfg.height, cfg.K())
    return camera, frames


def run(camera, frames, **overrides):
    vo = VisualOdometry(dataclasses.replace(VoConfig(), **overrides), camera)
    results = [vo.process(img, stamp) for stamp, img, _ in frames]
    return vo, results


def ate_pct(frames, results):
    ok = [(r.stamp_ns * 1e-9, r.T_world_cam) for r in results if r.ok]
    gt_s = np.array([s * 1e-9 for s, _, _ in frames])
    gt_T = np.array([T for _, _, T in frames])
    ev = evaluate(gt_s, gt_T, np.array([s for s, _ in ok]), np.array([T for _, T in ok]),
                  n_frames_total=len(frames))
    return ev


@pytest.mark.parametrize('estimator', ['ekf', 'iekf', 'epnp'])
def test_tracks_a_rendered_hand_held_sequence(sequence, estimator):
    camera, frames = sequence
    vo, results = run(camera, frames, estimator=estimator)
    ev = ate_pct(frames, results)
    assert ev.pct_tracked >= 90.0
    assert ev.ate_sim3_pct_of_path < 3.0
    assert vo.n_resets == 0
    # the bootstrap names the frame whose camera is the world frame: it is at the origin
    # and one baseline (one map unit) from the first pose
    boot = next(k for k, r in enumerate(results) if r.bootstrapped)
    ref = results[boot].reference_frame_index
    assert 0 <= ref < boot
    assert np.linalg.norm(results[boot].T_world_cam[:3, 3]) == pytest.approx(1.0, rel=1e-6)
    for r in results:
        if r.ok:
            assert np.all(np.isfinite(r.pose_cov)) and np.linalg.eigvalsh(r.pose_cov).min() > 0
            assert np.all(np.isfinite(r.twist_cov))
            assert set(r.timings_ms) >= {'track', 'total'}


def test_lost_on_black_frames_relocalises_in_the_kept_map(sequence):
    """Loss is declared within max_failed_frames of the blackout, nothing is published
    while lost, the map is kept and the first good frame is found in it again."""
    camera, frames = sequence
    black = np.zeros_like(frames[0][1])
    vo = VisualOdometry(VoConfig(), camera)
    results = [vo.process(black if 60 <= k < 66 else img, stamp)
               for k, (stamp, img, _) in enumerate(frames)]
    states = [r.state for r in results]
    assert any(s == TrackingState.LOST for s in states[60:64])
    assert not any(r.ok for r in results[61:66])
    assert vo.n_resets == 0
    assert results[66].ok and results[66].message.startswith('relocalised')


def test_lost_on_black_frames_then_rebootstraps_in_the_same_odom_frame(sequence):
    """relocalise: false, the behaviour before §15.7: the map is dropped and a new one is
    attached to the last good pose."""
    camera, frames = sequence
    black = np.zeros_like(frames[0][1])
    vo = VisualOdometry(VoConfig(relocalise=False), camera)
    results = []
    for k, (stamp, img, _) in enumerate(frames):
        results.append(vo.process(black if 60 <= k < 66 else img, stamp))
    states = [r.state for r in results]
    assert TrackingState.TRACKING in states[:60]
    # loss is detected within max_failed_frames of the blackout and nothing is published
    assert any(s == TrackingState.INITIALISING for s in states[60:64])
    assert not any(r.ok for r in results[61:66])
    assert vo.n_resets == 1
    # tracking is back within a bounded number of good frames
    back = next(k for k in range(66, len(results)) if results[k].ok)
    assert back - 66 <= 20, f'recovered only {back - 66} frames after the blackout'
    # the new map is attached to the last good pose: no jump of the odom frame
    last_good = max(k for k in range(60) if results[k].ok)
    jump = np.linalg.norm(results[back].T_world_cam[:3, 3] -
                          results[last_good].T_world_cam[:3, 3])
    step = np.median([np.linalg.norm(results[k + 1].T_world_cam[:3, 3] -
                                     results[k].T_world_cam[:3, 3])
                      for k in range(10, 50) if results[k].ok and results[k + 1].ok])
    assert jump < 40 * step, f'odom jumped {jump:.3f} (median step {step:.4f})'


def test_ground_truth_is_read_for_the_first_map_only(sequence):
    """The papers' ground-truth bootstrap fixes the first map; after a loss the pipeline
    bootstraps again from its images, as it would live (docs/method.md §9.4): ground
    truth handed again would favour the estimator that loses track more often."""
    camera, frames = sequence
    black = np.zeros_like(frames[0][1])
    far = np.eye(4)
    far[:3, 3] = [100.0, 0.0, 0.0]      # a "known" pose no image supports
    vo = VisualOdometry(VoConfig(relocalise=False), camera)
    results = []
    for k, (stamp, img, T) in enumerate(frames):
        known = T if k < 60 else far @ T
        results.append(vo.process(black if 60 <= k < 66 else img, stamp, known))
    first = next(r for r in results if r.ok)
    k_first = results.index(first)
    # the first map is the ground truth's: its pose is the true one
    assert np.allclose(first.T_world_cam[:3, 3], frames[k_first][2][:3, 3], atol=0.05)
    assert vo.n_resets == 1 and vo.n_maps == 2
    back = next(k for k in range(66, len(results)) if results[k].ok)
    # the second map is attached where the camera was, not at the pose handed in
    assert np.linalg.norm(results[back].T_world_cam[:3, 3] - frames[back][2][:3, 3]) < 5.0


def test_bad_frames_are_skipped_without_losing_the_track(sequence):
    """The stream (the core's front door) rejects a repeated stamp, a slightly older one
    and a wrong-size image, counts them, and the track goes on."""
    camera, frames = sequence
    stream = VoStream(VoConfig())
    assert stream.set_camera(camera) and not stream.set_camera(camera)
    for stamp, img, _ in frames[:40]:
        assert stream.admit(stamp) is None
        stream.process(img, stamp)
    assert stream.state == TrackingState.TRACKING
    stamp = frames[39][0]
    assert stream.admit(stamp).key == 'duplicate_stamp'
    assert stream.admit(stamp - 1000).key == 'out_of_order'
    assert stream.admit(frames[40][0]) is None
    assert stream.process(frames[40][1][:100], frames[40][0]).key == 'size_mismatch'
    r = stream.process(frames[40][1], frames[40][0])
    assert r.ok and stream.state == TrackingState.TRACKING
    assert stream.counters == {'duplicate_stamp': 1, 'out_of_order': 1, 'size_mismatch': 1}


def _tracking_stream(camera, frames) -> VoStream:
    """A stream fed `frames` through its front door, tracking at the end."""
    stream = VoStream(VoConfig())
    stream.set_camera(camera)
    for stamp, img, _ in frames:
        stream.admit(stamp)
        stream.process(img, stamp)
    assert stream.state == TrackingState.TRACKING
    return stream


def test_time_going_backwards_resets_and_a_new_calibration_restarts(sequence):
    camera, frames = sequence
    stream = _tracking_stream(camera, frames[:30])
    stamp0, img0 = frames[29][0] - 2_000_000_000, frames[0][1]
    assert stream.admit(stamp0) is None                 # looped: 2 s behind
    r = stream.process(img0, stamp0)
    assert stream.n_resets == 1 and not r.ok and stream.state != TrackingState.TRACKING
    other = PinholeCamera.from_camera_info(
        {'width': camera.width, 'height': camera.height,
         'K': (camera.K * [[1.1], [1.1], [1]]).reshape(-1).tolist(),
         'D': [0.0] * 5, 'distortion_model': 'plumb_bob'})
    assert stream.set_camera(other) and stream.n_camera_changes == 1
    assert stream.n_resets == 1 and stream.state == TrackingState.INITIALISING


@pytest.mark.parametrize('relocalise', [True, False])
def test_a_long_gap_is_not_extrapolated(sequence, relocalise):
    """After a gap longer than max_dt_s the motion model is not trusted: the camera is
    found again in the map (relocalise) or the map is dropped (re-bootstrap)."""
    camera, frames = sequence
    vo = VisualOdometry(VoConfig(max_dt_s=0.5, relocalise=relocalise), camera)
    for stamp, img, _ in frames[:30]:
        vo.process(img, stamp)
    assert vo.state == TrackingState.TRACKING
    r = vo.process(frames[30][1], frames[30][0] + 2_000_000_000)
    if relocalise:
        assert vo.n_resets == 0 and r.ok and r.message.startswith('relocalised')
    else:
        assert vo.n_resets == 1 and not r.ok


def test_a_time_reset_is_not_lost_when_its_frame_is_dropped(sequence):
    """A caller's queue may drop the very frame where time went back: the estimator still
    resets on the first older frame it processes."""
    camera, frames = sequence
    stream = _tracking_stream(camera, frames[:30])
    back = frames[29][0] - 3_000_000_000
    assert stream.admit(back) is None                       # accepted, never processed
    assert stream.admit(back + 33_000_000) is None
    r = stream.process(frames[0][1], back + 33_000_000)
    assert stream.n_resets == 1 and stream.n_requested_resets == 1 and not r.ok


def test_the_local_map_adjusts_windows_deterministically(sequence):
    """local_map on (docs/method.md §12): keyframes are made, adjustments run in the
    worker and are applied, the map points get covariances, and two runs agree exactly
    (an adjustment is applied at a fixed frame, whatever the worker's timing)."""
    camera, frames = sequence
    runs = [run(camera, frames, local_map=True, map_point_uncertainty=True)
            for _ in range(2)]
    (vo, results), (_, again) = runs
    stats = vo.local_map.stats
    assert stats.n_keyframes >= 5 and stats.n_runs >= 3
    assert 0 < stats.last_rms_px < 2.0
    ev = ate_pct(frames, results)
    assert ev.pct_tracked >= 90.0 and ev.ate_sim3_pct_of_path < 3.0
    assert vo.n_resets == 0
    cov = vo.map.covariances(vo.map.ids)
    assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov)[:, -1] > 0)
    for a, b in zip(results, again):
        assert a.ok == b.ok
        if a.ok:
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    vo.local_map.close()


def test_pose_feedback_moves_the_filter_and_keeps_tracking(sequence):
    """ba_pose_feedback on with no gate (docs/method.md §12.2): each applied adjustment
    hands the filter its newest keyframe's pose as a measurement, the filter takes it,
    ~/status counts it, and the run still tracks with a finite, positive covariance."""
    camera, frames = sequence
    vo, results = run(camera, frames, local_map=True, ba_pose_feedback=True,
                      ba_pose_feedback_min_nis=0.0)
    stats = vo.local_map.stats
    assert stats.n_runs >= 3 and stats.n_feedback >= 1
    assert stats.feedback_last_m >= 0.0 and np.isfinite(stats.feedback_last_deg)
    status = stats.as_status()
    assert status['ba_feedbacks'] == stats.n_feedback
    ev = ate_pct(frames, results)
    assert ev.pct_tracked >= 90.0 and ev.ate_sim3_pct_of_path < 3.0
    assert vo.n_resets == 0
    for r in results:
        if r.ok:
            assert np.all(np.isfinite(r.pose_cov))
            assert np.all(np.linalg.eigvalsh(r.pose_cov) > 0)
    vo.local_map.close()


def test_map_points_are_found_again_as_tracks(sequence):
    """refind_map_points on (docs/method.md §12.5): map points whose track ended are
    found again by descriptor and come back as tracks under their own ids, and the
    run still tracks."""
    camera, frames = sequence
    vo, results = run(camera, frames, local_map=True, refind_map_points=True)
    found = sum(r.n_found_again for r in results)
    assert found > 0            # the walk's tracks are long: few points are lost in view
    ev = ate_pct(frames, results)
    assert ev.pct_tracked >= 90.0 and vo.n_resets == 0
    vo.local_map.close()


@pytest.mark.data
def test_the_large_window_retry_waits_for_the_pose_on_kitti():
    """With someone waiting for the pose and time to spare, the large window's retry of
    lost tracks without a map point comes after on_pose (docs/method.md §17.3): it does
    on KITTI 06, where dozens a frame wait, and every pose, covariance, count and map is
    the same as a run whose retry does not wait. Without time to spare (frames stamped
    1 ms apart), nothing waits."""
    data = load_folder(need_shared_data('kitti06_f0-50', 'KITTI retry-after-pose test'))
    frames = list(data.frames())[:20]
    t0 = frames[0][0]

    def run(pose_first: bool, stretch: float) -> tuple[list, int]:
        stream = VoStream(VoConfig(), seed=0)
        stream.set_camera(data.camera)
        out, waited = [], 0
        for stamp, gray in frames:
            # 0.3 s apart: time to spare whatever the machine's load
            stamp = t0 + int((stamp - t0) * stretch)
            seen = []
            out.append(stream.process(gray, stamp, on_pose=seen.append) if pose_first
                       else stream.process(gray, stamp))
            waited += stream.vo.tracker.stats.n_wide_waited
            assert not seen or seen[0] is out[-1]
        return out, waited

    (plain, waited_plain), (first, waited_first) = run(False, 3.0), run(True, 3.0)
    assert waited_plain == 0 and waited_first > 0
    assert sum(r.ok for r in first) >= 15
    for a, b in zip(plain, first):
        assert (a.ok, a.n_tracks, a.n_inliers, a.map_size, a.n_new_points) == \
            (b.ok, b.n_tracks, b.n_inliers, b.map_size, b.n_new_points)
        if a.ok:
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
            np.testing.assert_array_equal(a.pose_cov, b.pose_cov)
    assert run(True, 0.01)[1] == 0        # 1 ms apart: no time to spare


def test_the_pose_goes_out_before_the_new_corners(sequence):
    """on_pose sees a tracked frame's final pose before the tracker's new corners are
    detected (FeatureTracker.finish after it, docs/method.md §17.3): the frames that top
    the tracks up do it after the callback, and every pose, covariance and track count is
    the same as without a callback."""
    camera, frames = sequence
    _, plain = run(camera, frames)
    vo = VisualOdometry(VoConfig(), camera)
    seen, topped_after = [], 0
    for stamp, img, _ in frames:
        at_pose = []
        res = vo.process(img, stamp, on_pose=lambda r: at_pose.append(
            (vo.tracker.next_id, r.T_world_cam.copy(), r.pose_cov.copy())))
        if at_pose:
            next_id, T, cov = at_pose[0]
            topped_after += vo.tracker.next_id > next_id
            np.testing.assert_array_equal(T, res.T_world_cam)
            np.testing.assert_array_equal(cov, res.pose_cov)
            assert {'track', 'top_up', 'detect', 'to_pose'} <= set(res.timings_ms)
            assert 0.0 < res.timings_ms['to_pose'] < res.timings_ms['total']
        seen.append(res)
    assert topped_after >= 5
    for a, b in zip(plain, seen):
        assert (a.ok, a.n_tracks, a.n_inliers, a.map_size) == \
            (b.ok, b.n_tracks, b.n_inliers, b.map_size)
        if a.ok:
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
            np.testing.assert_array_equal(a.pose_cov, b.pose_cov)

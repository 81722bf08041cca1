"""Relocalisation after a loss (core/relocalise.py): the demo's real images with the lens
covered for 20 frames, or a 2 s gap in the stream; the map is kept and the camera found in
it again, in the same world frame and scale."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.stream import VoStream
from ekf_vo.io.bag import read_ground_truth
from ekf_vo.tools.demo import demo_bag, load_demo_frames
from ekf_vo.tools.evaluate import evaluate

BLACK = range(150, 170)


@pytest.fixture(scope='module')
def demo():
    info, frames = load_demo_frames()
    gt_ns, gt_T = read_ground_truth(demo_bag())
    return info, frames, np.asarray(gt_ns) * 1e-9, gt_T


def _run(demo, black=(), gap_after=None, **overrides):
    info, frames, gt_s, gt_T = demo
    stream = VoStream(dataclasses.replace(VoConfig(), **overrides))
    stream.set_camera(PinholeCamera.from_camera_info(info))
    oks, stamps, poses = [], [], []
    for k, (t, g) in enumerate(frames):
        if gap_after is not None and gap_after < k <= gap_after + 60:
            continue                                   # 60 frames = 2 s not received
        if k in black:
            g = np.zeros_like(g)
        r = stream.process(g, t)
        # black frames are identical: the first repeats are skipped (a Rejection, not ok)
        oks.append((k, r.ok))
        if r.ok:
            stamps.append(t * 1e-9)
            poses.append(r.T_world_cam)
    stream.vo.local_map.close()
    ev = evaluate(gt_s, gt_T, np.array(stamps), np.array(poses), max_time_diff_s=1e-3)
    return dict(oks), ev, stream.n_resets, np.array(stamps), np.array(poses)


def _first_ok_after(oks, k0):
    return next(k for k in sorted(oks) if k >= k0 and oks[k]) - k0


def test_covered_lens_relocalises_at_once_in_the_same_map(demo):
    oks, ev, resets, _, _ = _run(demo, black=BLACK)
    _, ev_clean, _, _, _ = _run(demo)
    assert resets == 0
    assert _first_ok_after(oks, BLACK.stop) <= 5
    # the same world frame and scale: the whole run aligns as one trajectory (the
    # issue's target is 1.2x; this guards against a re-bootstrap's new frame)
    assert ev.ate_sim3_rmse < 2.5 * ev_clean.ate_sim3_rmse
    assert ev.sim3_scale == pytest.approx(ev_clean.sim3_scale, rel=0.05)


def test_without_relocalisation_the_map_is_dropped(demo):
    oks, _, resets, _, _ = _run(demo, black=BLACK, relocalise=False)
    assert resets >= 1
    assert _first_ok_after(oks, BLACK.stop) > 5


def test_a_two_second_gap_relocalises_within_five_frames(demo):
    oks, _, resets, _, _ = _run(demo, gap_after=120)
    assert resets == 0
    assert _first_ok_after(oks, 181) <= 5


def test_a_jolt_the_motion_model_cannot_follow_is_a_loss_not_a_drift():
    """KITTI 06 with frames 20-22 missing and the stamps evenly spaced: the camera seems
    to jump 4.8 m in 0.1 s. The prediction fails for most tracks and the map in view is
    not found: the frame is LOST (it went on DEGRADED with 16-69 inliers and drifted to
    18 deg, 22 % of the poses above the 99.9 % bound; docs/method.md §15.10)."""
    from ekf_vo.io.dataset import load_folder
    from ekf_vo.tools.consistency import rotation_nees
    from .support.data import need_shared_data
    data = load_folder(need_shared_data('kitti06_f0-50', 'a jolted car'))
    frames = list(data.frames())
    keep = [k for k in range(len(frames)) if not 20 <= k <= 22]
    t0, dt = frames[0][0], frames[1][0] - frames[0][0]
    stream = VoStream(VoConfig(), seed=0)
    stream.set_camera(data.camera)
    stamps, poses, covs, results = [], [], [], []
    for j, k in enumerate(keep):
        r = stream.process(frames[k][1], t0 + j * dt)
        results.append((k, r))
        if r.ok:
            stamps.append((t0 + j * dt) * 1e-9)
            poses.append(r.T_world_cam)
            covs.append(r.pose_cov)
    stream.vo.close()
    jolt = dict(results)[23]
    assert jolt.state.value == 'lost' and 'motion model' in jolt.message
    gt_s = np.array([(t0 + j * dt) * 1e-9 for j in range(len(keep))])
    gt_T = np.asarray(data.gt_T_world_cam)[keep]
    st = np.array(stamps)
    late = st >= gt_s[12] - 1e-6          # KITTI 06's first second: docs/method.md §14.4
    rn = rotation_nees(gt_s, gt_T, st[late], np.array(poses)[late], st[late],
                       np.array(covs)[late], 1e-3)
    assert rn.to_dict()['rot_nees_pct_above_99_9'] <= 5.0
    assert np.max(rn.err_deg) < 3.0

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

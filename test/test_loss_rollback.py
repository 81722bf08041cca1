"""A loss after failed frames goes back to the last published state (docs/method.md §7.4).

The failed frames' updates rest on a handful of inliers and may turn the velocities
anywhere; the time spent relocalising, and the anchor of a re-bootstrapped map, are
predicted from the last state that was published instead.
"""
from __future__ import annotations

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.ekf import ANG, VEL
from ekf_vo.core.frame_result import TrackingState
from ekf_vo.core.pipeline import VisualOdometry
from ekf_vo.tools.synth import SynthConfig, render_sequence


@pytest.fixture(scope='module')
def walk():
    cfg = SynthConfig(frames=240, seed=1, trajectory='walk')
    camera = PinholeCamera.from_camera_info({'width': cfg.width, 'height': cfg.height,
                                             'K': cfg.K(), 'D': cfg.D(),
                                             'distortion_model': 'plumb_bob'})
    return camera, list(render_sequence(cfg))


def _boxed(img: np.ndarray, shift_px: int, half_px: int = 20) -> np.ndarray:
    """The image shifted sideways, all but a small box at its centre black: a handful
    of tracks that land somewhere else than the filter predicts."""
    img = np.roll(img, shift_px, axis=1)
    h, w = img.shape[0] // 2, img.shape[1] // 2
    out = np.zeros_like(img)
    out[h - half_px:h + half_px, w - half_px:w + half_px] = \
        img[h - half_px:h + half_px, w - half_px:w + half_px]
    return out


def test_a_loss_predicts_from_the_last_published_state(walk) -> None:
    camera, frames = walk
    vo = VisualOdometry(VoConfig(), camera, seed=0)
    try:
        for stamp, img, _ in frames[:60]:
            res = vo.process(img, stamp)
        assert res.ok and vo.state == TrackingState.TRACKING
        x_published = vo.ekf.x.copy()
        # two frames with a handful of misplaced tracks: failed (too few inliers), and
        # the second's update applied all the same; then a frame the tracks leave
        res = [vo.process(_boxed(frames[k][1], 3 * (k - 59)), frames[k][0])
               for k in (60, 61)]
        assert not any(r.ok for r in res) and res[1].n_inliers > 0
        moved = vo.ekf.x.copy()
        strip = frames[62][1].copy()
        strip[:, 60:] = 0
        vo.process(strip, frames[62][0])
        assert vo.state == TrackingState.LOST
        # the failed update moved the velocities ...
        assert not np.allclose(moved[ANG], x_published[ANG], atol=1e-9)
        # ... the loss predicts from the last published state instead: the constant-
        # velocity model keeps its velocities exactly
        assert np.allclose(vo.ekf.x[ANG], x_published[ANG], atol=1e-12)
        assert np.allclose(vo.ekf.x[VEL], x_published[VEL], atol=1e-12)
    finally:
        vo.close()

"""A frame sent twice under a new stamp (a driver or relay repeating it) is skipped by the
stream, so the filter never hears that the camera stopped; a camera that really stands
still in a noise-free simulator is still processed (core/stream.py, docs/ros.md)."""
import dataclasses

import numpy as np
import pytest

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import TrackingState
from ekf_vo.core.stream import Rejection, VoStream
from ekf_vo.tools.synth import SynthConfig, render_sequence


@pytest.fixture(scope='module')
def sequence():
    cfg = SynthConfig(frames=90, seed=3, trajectory='orbit')
    return PinholeCamera(cfg.width, cfg.height, cfg.K()), list(render_sequence(cfg))


def _feed(camera, stamped_images, **overrides):
    """Every (stamp, image) through a fresh stream's front door: the results in order."""
    stream = VoStream(dataclasses.replace(VoConfig(), **overrides))
    stream.set_camera(camera)
    results = []
    for stamp, img in stamped_images:
        rejected = stream.admit(stamp)
        results.append(rejected if rejected is not None else stream.process(img, stamp))
    return stream, results


def _with_repeats(frames, every):
    """The frames, each `every`-th followed by itself again half a frame later."""
    dt = frames[1][0] - frames[0][0]
    out = []
    for k, (stamp, img, _) in enumerate(frames):
        out.append((stamp, img))
        if k % every == every - 1:
            out.append((stamp + dt // 2, img.copy()))
    return out


def test_a_repeated_frame_changes_no_pose(sequence):
    """Before the rule the repeats reached the filter as frames showing no motion: on the
    rendered orbit with a fifth of them repeated the track was lost and re-bootstrapped
    50 deg off (docs/ros.md). Skipped, they leave every pose as it was without them."""
    camera, frames = sequence
    _, plain = _feed(camera, [(s, img) for s, img, _ in frames])
    stream, repeated = _feed(camera, _with_repeats(frames, 5))
    skipped = [r for r in repeated if isinstance(r, Rejection)]
    assert len(skipped) == len(frames) // 5
    assert {r.key for r in skipped} == {'repeated_image'}
    assert stream.counters['repeated_image'] == len(skipped)
    kept = [r for r in repeated if not isinstance(r, Rejection)]
    assert len(kept) == len(plain)
    assert sum(r.ok for r in plain) > len(plain) // 2
    for a, b in zip(plain, kept):
        assert a.ok == b.ok
        if a.ok:
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
            np.testing.assert_array_equal(a.pose_cov, b.pose_cov)


def test_a_camera_standing_still_without_noise_is_processed_after_the_skips(sequence):
    """A noise-free simulated camera that stops sends one image again and again: after
    repeated_image_max_skip of them the rest are frames, and the track holds."""
    camera, frames = sequence
    dt = frames[1][0] - frames[0][0]
    last_stamp, last_img, _ = frames[59]
    standing = [(last_stamp + (k + 1) * dt, last_img) for k in range(10)]
    stream, results = _feed(camera, [(s, img) for s, img, _ in frames[:60]] + standing)
    skips = VoConfig().repeated_image_max_skip
    assert skips > 0
    tail = results[60:]
    assert all(isinstance(r, Rejection) for r in tail[:skips])
    assert not any(isinstance(r, Rejection) for r in tail[skips:])
    assert stream.state == TrackingState.TRACKING and tail[-1].ok


def test_never_skipped_when_the_rule_is_off(sequence):
    camera, frames = sequence
    stream, results = _feed(camera, _with_repeats(frames[:40], 5), repeated_image_max_skip=0)
    assert not any(isinstance(r, Rejection) for r in results)
    assert stream.counters['repeated_image'] == 0

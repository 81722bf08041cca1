"""A noisy sensor's frames are smoothed before tracking, a clean one's are not
(core/sensor_noise.py, docs/method.md §6.12)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.features import FeatureTracker
from ekf_vo.core.pipeline import VisualOdometry
from ekf_vo.core.sensor_noise import SensorNoise, noise_sigma
from ekf_vo.tools.synth import SynthConfig, render_sequence


def rendered(noise_px: float, frames: int = 12) -> list:
    """The rendered room's walk with `noise_px` grey levels of sensor noise."""
    return list(render_sequence(SynthConfig(frames=frames, seed=1, trajectory='walk',
                                            noise_px=noise_px)))


def test_the_estimate_reads_the_noise_of_a_rendered_sensor() -> None:
    """Immerkær's estimate finds the noise added to textured images within 10 %, and
    the texture alone reads as far less than the threshold."""
    for noise in (2.0, 5.0, 15.0):
        est = np.median([noise_sigma(img) for _, img, _ in rendered(noise, 4)])
        assert abs(est - noise) < 0.1 * noise + 0.5, (noise, est)
    assert noise_sigma(np.zeros((2, 50), np.uint8)) == 0.0          # too small: nothing


def test_a_noisy_sensor_is_smoothed_a_clean_one_is_not() -> None:
    """The decision follows the median of the recent estimates: on from the first
    frames of a noisy sensor, off again (slowly) once it is clean; a new image size
    starts over; 0 disables the estimate."""
    clean = [img for _, img, _ in rendered(2.0)]
    noisy = [img for _, img, _ in rendered(15.0)]
    s = SensorNoise(12.0, 1.0)
    assert [s.observe(img) for img in clean] == [False] * len(clean)
    assert not s.smoothing and s.smooth(clean[0]) is clean[0]
    s = SensorNoise(12.0, 1.0)
    started = [s.observe(img) for img in noisy]
    assert s.smoothing and started.count(True) == 1 and started.index(True) <= 2
    smoothed = s.smooth(noisy[0])
    assert smoothed.shape == noisy[0].shape and noise_sigma(smoothed) < 0.5 * 15.0
    for k, img in enumerate(clean * 10):                # the light comes back
        s.observe(img)
        if not s.smoothing:
            break
    assert not s.smoothing and k > len(clean)           # not on one frame's word
    s.observe(noisy[0][:200, :300].copy())              # another size: starts over
    assert s.smoothing and s.estimate_grey > 12.0       # from that frame alone
    off = SensorNoise(0.0, 1.0)
    assert not any(off.observe(img) for img in noisy) and np.isnan(off.estimate_grey)


def test_the_tracker_and_the_pipeline_smooth_a_noisy_stream() -> None:
    """A stream at 15 grey levels is tracked on smoothed frames and its results say so;
    one at 2 grey levels gives the same tracks as with the smoothing disabled."""
    noisy = rendered(15.0)
    on = dataclasses.replace(VoConfig(), denoise_min_noise_grey=12.0)
    vo = VisualOdometry(on, _camera())
    results = [vo.process(img, stamp) for stamp, img, _ in noisy]
    assert results[-1].denoised and results[-1].sensor_noise_grey > 12.0
    assert not results[0].denoised or results[0].sensor_noise_grey >= 12.0
    clean = rendered(2.0)
    a = FeatureTracker(on)
    b = FeatureTracker(VoConfig())
    for _, img, _ in clean:
        ta, tb = a.track(img), b.track(img)
        np.testing.assert_array_equal(ta.ids, tb.ids)
        np.testing.assert_array_equal(ta.px, tb.px)
    assert not a.noise.smoothing and 1.5 < a.noise.estimate_grey < 3.0


def _camera() -> PinholeCamera:
    cfg = SynthConfig()
    return PinholeCamera(cfg.width, cfg.height, cfg.K())

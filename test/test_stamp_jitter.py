"""Image stamps that jitter by a few milliseconds (a driver that stamps on arrival): with
stamp_sigma_s set, the prediction is uncertain by the motion over the stamp's error
(docs/method.md §3.5), so the filter follows the images instead of its own timing."""
import dataclasses

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.consistency import rotation_nees
from ekf_vo.tools.evaluate import evaluate
from ekf_vo.tools.synth import SynthConfig, render_sequence

JITTER_S = 0.005


def test_the_orbit_with_stamps_jittered_by_5_ms_keeps_its_accuracy():
    """Seed 3, stamps + N(0, 5 ms). Without the allowance (stamp_sigma_s: 0, the default):
    ATE 2.27 % of the path, rotation error up to 12.9 deg; the clean stream's are 0.17 %
    and 1.2 deg. With 2 ms: 0.17 % and 1.4 deg; the margins here are wide."""
    cfg = SynthConfig(frames=300, seed=3, trajectory='orbit')
    rng = np.random.default_rng([3, 77])
    frames = [(t + int(rng.normal(0.0, JITTER_S) * 1e9), img, T)
              for t, img, T in render_sequence(cfg)]
    frames.sort(key=lambda f: f[0])
    stream = VoStream(dataclasses.replace(VoConfig(), stamp_sigma_s=0.002), seed=3)
    stream.set_camera(PinholeCamera.from_camera_info({
        'width': cfg.width, 'height': cfg.height, 'K': cfg.K(), 'D': cfg.D(),
        'distortion_model': 'plumb_bob'}))
    stamps, poses, covs = [], [], []
    for t, img, _ in frames:
        res = stream.process(img, t)
        if res.ok:
            stamps.append(t * 1e-9)
            poses.append(res.T_world_cam)
            covs.append(res.pose_cov)
    gt_s = np.array([t * 1e-9 for t, _, _ in frames])
    gt_T = np.array([T for _, _, T in frames])
    stamps, poses = np.array(stamps), np.array(poses)
    assert stream.n_resets == 0
    ev = evaluate(gt_s, gt_T, stamps, poses, max_time_diff_s=1e-4, n_frames_total=len(frames))
    assert ev.ate_sim3_pct_of_path < 1.0
    rn = rotation_nees(gt_s, gt_T, stamps, poses, stamps, np.array(covs), max_time_diff_s=1e-4)
    assert rn.err_deg.max() < 3.0
    assert rn.pct_above_999 < 5.0

"""The core, offline, on the real sequences of ../shared/data (no ROS, no bag).

KITTI 06 frames 0-50: monocular bootstrap from the images (scale arbitrary), ATE after
Sim(3) alignment. Middlebury dino: the paper's protocol, two-view bootstrap from the
ground truth of the first two views (fixes the scale), then EKF vs EPnP.

    python -m ekf_vo.bench.real_data kitti06_f0-50 [--estimator ekf|iekf|epnp]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from ..config import VoConfig
from ..core.camera import PinholeCamera
from ..core.pipeline import VisualOdometry
from ..tools.dataset import load_folder
from ..tools.evaluate import evaluate
from .common import shared_data

#: settings per sequence (documented deviations from the defaults, and why)
PRESETS = {
    # 10 Hz car: larger inter-frame motion -> bigger process noise in map units
    'kitti06_f0-50': {},
    # untextured object on black, 7.7 deg per view, no real time (1 s per view)
    'middlebury_dino': {'max_features': 600, 'corner_quality': 0.001,
                        'min_feature_distance_px': 5.0, 'bootstrap_min_inliers': 30,
                        'min_tracking_inliers': 8},
}
GT_BOOTSTRAP = {'middlebury_dino': True}


def run_sequence(name: str, overrides: dict | None = None, gt_bootstrap: bool | None = None,
                 limit: int | None = None, seed: int = 0) -> dict:
    folder = shared_data(name)
    if folder is None:
        raise FileNotFoundError(f'../shared/data/{name} is absent')
    data = load_folder(folder)
    values = dict(PRESETS.get(name, {}))
    values.update(overrides or {})
    cfg = dataclasses.replace(VoConfig(), **values).validate()
    camera = PinholeCamera.from_camera_info(data.camera)
    vo = VisualOdometry(cfg, camera, seed=seed)
    use_gt = GT_BOOTSTRAP.get(name, False) if gt_bootstrap is None else gt_bootstrap
    stamps, poses, results = [], [], []
    t0 = time.perf_counter()
    for k, (stamp_ns, gray) in enumerate(data.frames(limit)):
        known = data.gt_at(k) if (use_gt and vo.state.value == 'initialising') else None
        res = vo.process(gray, stamp_ns, known_T_world_cam=known)
        results.append(res)
        if res.ok:
            stamps.append(stamp_ns * 1e-9)
            poses.append(res.T_world_cam)
    wall = time.perf_counter() - t0
    n = len(results)
    ev = evaluate(data.gt_stamps_s, data.gt_T_world_cam, np.array(stamps), np.array(poses),
                  max_time_diff_s=1e-3, n_frames_total=n)
    stages = {}
    for r in results:
        for key, ms in r.timings_ms.items():
            stages.setdefault(key, []).append(ms)
    return {'sequence': name, 'estimator': cfg.estimator, 'frames': n,
            'frames_tracked': len(stamps), 'pct_tracked': 100.0 * len(stamps) / n,
            'fps': n / wall, 'stage_ms': {k: float(np.mean(v)) for k, v in stages.items()},
            'ate_sim3_rmse': ev.ate_sim3_rmse, 'ate_pct_path': ev.ate_sim3_pct_of_path,
            'ate_se3_rmse': ev.ate_se3_rmse, 'path_length': ev.path_length_gt_m,
            'rpe_trans_rmse': ev.rpe_trans_rmse, 'rpe_rot_rmse_deg': ev.rpe_rot_rmse_deg,
            'rot_err_mean_deg': ev.rot_err_mean_deg, 'rot_err_max_deg': ev.rot_err_max_deg,
            'rot_drift_mean_deg': ev.rot_err_origin_mean_deg,
            'rot_drift_max_deg': ev.rot_err_origin_max_deg,
            'scale': ev.sim3_scale, 'n_resets': vo.n_resets,
            'messages': [r.message for r in results if r.message][:20], 'eval': ev,
            'est_stamps': stamps, 'est_T': poses}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('sequence', choices=sorted(PRESETS))
    parser.add_argument('--estimator', default=None, choices=('ekf', 'iekf', 'epnp'))
    parser.add_argument('--set', nargs='*', default=[], metavar='NAME=VALUE',
                        help='override VoConfig fields')
    args = parser.parse_args(argv)
    overrides = {}
    for item in args.set:
        key, value = item.split('=', 1)
        overrides[key] = type(getattr(VoConfig(), key))(eval(value))  # noqa: S307 (dev CLI)
    if args.estimator:
        overrides['estimator'] = args.estimator
    r = run_sequence(args.sequence, overrides)
    for key in ('sequence', 'estimator', 'frames', 'frames_tracked', 'pct_tracked', 'fps',
                'ate_sim3_rmse', 'ate_pct_path', 'path_length', 'rpe_trans_rmse',
                'rpe_rot_rmse_deg', 'rot_err_mean_deg', 'rot_err_max_deg',
                'rot_drift_mean_deg', 'rot_drift_max_deg', 'scale',
                'n_resets', 'stage_ms', 'messages'):
        print(f'{key:>18}: {r[key]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

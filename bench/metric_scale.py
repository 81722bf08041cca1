"""Metric scale (docs/method.md §16): odometry in metres, and how right it is.

    python -m bench.metric_scale [--seeds 0 1 2] [--json out.json] [--only kitti|robot]

- KITTI 06 f0-50 (from ../shared/data), the four bags of bench.local_map (raw / JPEG 75,
  CameraInfo before / after its image), `scale_source: camera_height`,
  `camera_height_m: 1.65`.
- The rendered ground robot with a synthetic wheel odometry (/scale_odom; 2 % distance
  noise, 1 % heading noise, slip episodes reading +30 %): its first edge (170 frames, a
  straight drive) and the whole loop with four 90 deg turns in place (760 frames), each
  with 5 % and 20 % of the time slipping; `scale_source: odometry`, the robot's extrinsic.

Per run: frames published, scale error (the Sim(3) fit's scale, est/true - 1), ATE after
SE(3) alignment (no scale fitted) and after Sim(3), both in % of the path, and the 6-DoF
pose NEES (rigid alignment at the first published pose; 6 ideal, 22.46 the 99.9 % bound).
Nothing here uses ground truth in the estimator.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench.local_map import VARIANTS, build_bags

SEQUENCE = 'kitti06_f0-50'
KITTI_SCALE = {'scale_source': 'camera_height', 'camera_height_m': 1.65}
ROBOT_CASES = {'edge': 170, 'loop': 760}
SLIP_SHARES = (0.05, 0.2)


def run_one(bag: Path, params: Any, overrides: dict, seed: int) -> dict[str, Any]:
    from ekf_vo.tools.consistency import pose_nees
    from ekf_vo.tools.run import run_bag
    s = run_bag(bag, params, overrides, seed=seed)
    ev = s.eval
    out = {'seed': seed, 'frames': s.frames, 'pct_published': s.pct_tracked,
           'resets': s.n_resets, 'scale': dict(s.scale),
           'scale_error_pct': None if ev is None else float(ev.scale_error_pct),
           'ate_se3_pct': None if ev is None else float(ev.ate_se3_pct_of_path),
           'ate_sim3_pct': None if ev is None else float(ev.ate_sim3_pct_of_path),
           'pose_nees_mean': None, 'pose_nees_median': None, 'pose_nees_pct_above': None}
    if ev is not None and s.est_pose_cov:
        from ekf_vo.io.bag import read_ground_truth
        gt_ns, gt_T = read_ground_truth(bag)
        stamps = np.array(s.est_stamps_s)
        try:
            n = pose_nees(gt_ns * 1e-9, gt_T, stamps, np.array(s.est_T_world_cam), stamps,
                          np.array(s.est_pose_cov))
            out.update(pose_nees_mean=n.mean, pose_nees_median=n.median,
                       pose_nees_pct_above=n.pct_above_999)
        except ValueError as exc:
            out['nees_error'] = str(exc)
    return out


def kitti(seeds: list[int], work: Path) -> dict[str, list]:
    from bench.common import shared_data
    folder = shared_data(SEQUENCE)
    if folder is None:
        print(f'bench.metric_scale: {SEQUENCE} absent: KITTI skipped', file=sys.stderr)
        return {}
    bags = build_bags(folder, work, list(VARIANTS))
    return {name: [run_one(bag, None, KITTI_SCALE, seed) for seed in seeds]
            for name, bag in bags.items()}


def robot(seeds: list[int], work: Path) -> dict[str, list]:
    from ekf_vo.tools.synth import SynthConfig, write_bag
    from ekf_vo.tools.synth_scene import GROUND_ROBOT_T_BASE_CAM_XYZ
    from ekf_vo.tools.wheel_odometry import WheelNoise
    params = {'T_base_cam_xyz': list(GROUND_ROBOT_T_BASE_CAM_XYZ)}
    out: dict[str, list] = {}
    for case, frames in ROBOT_CASES.items():
        for share in SLIP_SHARES:
            runs = []
            for seed in seeds:
                bag = work / f'robot_{case}_{share}_{seed}'
                write_bag(SynthConfig(trajectory='ground_robot', frames=frames, seed=seed),
                          bag, wheel_odom=WheelNoise(slip_share=share), overwrite=True)
                runs.append(run_one(bag, params, {'scale_source': 'odometry'}, seed))
            out[f'robot {case}, slip {share:.0%}'] = runs
    return out


def _fmt(v: Any, spec: str = '.2f') -> str:
    return '-' if v is None else format(v, spec)


def table(results: dict[str, list]) -> str:
    rows = ['| case | seed | published % | resets | scale error % | ATE SE(3) % | '
            'ATE Sim(3) % | pose NEES mean / median / % > bound | scale sigma % |',
            '|---|---|---|---|---|---|---|---|---|']
    for name, runs in results.items():
        for r in runs:
            rows.append(
                f"| {name} | {r['seed']} | {r['pct_published']:.1f} | {r['resets']} | "
                f"{_fmt(r['scale_error_pct'], '+.2f')} | {_fmt(r['ate_se3_pct'])} | "
                f"{_fmt(r['ate_sim3_pct'], '.3f')} | {_fmt(r['pose_nees_mean'], '.1f')} / "
                f"{_fmt(r['pose_nees_median'], '.1f')} / "
                f"{_fmt(r['pose_nees_pct_above'], '.0f')} | "
                f"{_fmt(r['scale'].get('scale_sigma_pct'), '.1f')} |")
    return '\n'.join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='python -m bench.metric_scale', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    p.add_argument('--only', choices=('kitti', 'robot'), default=None)
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    results: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, 'kitti'):
            results.update(kitti(args.seeds, Path(tmp)))
        if args.only in (None, 'robot'):
            results.update(robot(args.seeds, Path(tmp)))
    print(table(results))
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1) + '\n', encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())

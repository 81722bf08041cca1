"""Metric scale (docs/method.md §16): odometry in metres, and how right it is.

    python -m bench.metric_scale [--seeds 0 1 2] [--json out.json] [--only kitti|robot]

- KITTI 06 f0-50 (from ../shared/data), the four bags of bench.local_map (raw / JPEG 75,
  CameraInfo before / after its image), `scale_source: camera_height`,
  `camera_height_m: 1.65`.
- The rendered ground robot with a synthetic wheel odometry (/scale_odom; 2 % distance
  noise, 1 % heading noise, slip episodes of 1 s reading +30 %): its first edge (170
  frames, a straight drive), the whole loop with four 90 deg turns in place (760 frames),
  and the rectangle with rounded corners driven without stopping (ground_robot_arcs, 550
  frames, one loop), each with 5 % and 20 % of the time slipping; `scale_source:
  odometry`, the robot's extrinsic.

With --dds, the raw KITTI bag (camera_height) and the robot's rounded loop (odometry, 5 %
slip) are also played in real time into a vo_node over DDS (queue_policy all), and the
recorded nav_msgs/Odometry, brought back to the camera's optical frame with the node's
extrinsic, is evaluated the same way (ATE and scale error; no NEES).

Per run: frames published, scale error (the Sim(3) fit's scale, est/true - 1), ATE after
SE(3) alignment (no scale fitted) and after Sim(3), both in % of the path, and the 6-DoF
pose NEES (rigid alignment at the first published pose; 6 ideal, 22.46 the 99.9 % bound),
for KITTI also aligned at frame 12 (its ground truth's frames 0-11 turn at a constant
rate the images contradict), and the twist NEES, linear and angular (3 ideal each; the
ground truth's central differences, tools/consistency.twist_nees).
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
#: KITTI 06's ground truth turns at an exactly constant rate over frames 0-11, which the
#: images contradict (docs/method.md §14.4): its pose NEES is also given aligned at 12
KITTI_GT_RELIABLE_FROM = 12
KITTI_SCALE = {'scale_source': 'camera_height', 'camera_height_m': 1.65}
#: case -> (trajectory, frames)
ROBOT_CASES = {'edge': ('ground_robot', 170), 'loop': ('ground_robot', 760),
               'arcs': ('ground_robot_arcs', 550)}
SLIP_SHARES = (0.05, 0.2)


def _pose_nees_from(gt_ns, gt_T, stamps, est_T, covs, start_s: float) -> float | None:
    """The pose NEES mean of the frames from `start_s` on, aligned at the first of them."""
    from ekf_vo.tools.consistency import pose_nees
    keep = stamps >= start_s - 1e-6
    if keep.sum() < 3:
        return None
    return pose_nees(gt_ns * 1e-9, gt_T, stamps[keep], est_T[keep], stamps[keep],
                     covs[keep]).mean


def run_one(bag: Path, params: Any, overrides: dict, seed: int,
            nees_from_frame: int | None = None) -> dict[str, Any]:
    """One offline run's figures; `nees_from_frame`: also the pose NEES aligned at that
    image frame (KITTI: KITTI_GT_RELIABLE_FROM)."""
    from ekf_vo.tools.consistency import pose_nees, twist_nees
    from ekf_vo.tools.run import run_bag
    s = run_bag(bag, params, overrides, seed=seed)
    ev = s.eval
    out = {'seed': seed, 'frames': s.frames, 'pct_published': s.pct_tracked,
           'resets': s.n_resets, 'scale': dict(s.scale),
           'scale_error_pct': None if ev is None else float(ev.scale_error_pct),
           'ate_se3_pct': None if ev is None else float(ev.ate_se3_pct_of_path),
           'ate_sim3_pct': None if ev is None else float(ev.ate_sim3_pct_of_path),
           'pose_nees_mean': None, 'pose_nees_median': None, 'pose_nees_pct_above': None,
           'twist_nees_linear_mean': None, 'twist_nees_angular_mean': None,
           'pose_nees_from_mean': None}
    if ev is not None and s.est_pose_cov:
        from ekf_vo.io.bag import read_ground_truth
        gt_ns, gt_T = read_ground_truth(bag)
        stamps = np.array(s.est_stamps_s)
        try:
            n = pose_nees(gt_ns * 1e-9, gt_T, stamps, np.array(s.est_T_world_cam), stamps,
                          np.array(s.est_pose_cov))
            out.update(pose_nees_mean=n.mean, pose_nees_median=n.median,
                       pose_nees_pct_above=n.pct_above_999)
            t = twist_nees(gt_ns * 1e-9, gt_T, stamps, np.array(s.est_twist),
                           np.array(s.est_twist_cov))
            out.update(twist_nees_linear_mean=t.linear_mean,
                       twist_nees_angular_mean=t.angular_mean)
            if nees_from_frame is not None:
                out['pose_nees_from_mean'] = _pose_nees_from(
                    gt_ns, gt_T, stamps, np.array(s.est_T_world_cam),
                    np.array(s.est_pose_cov), gt_ns[nees_from_frame] * 1e-9)
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
    return {name: [run_one(bag, None, KITTI_SCALE, seed, KITTI_GT_RELIABLE_FROM)
                   for seed in seeds] for name, bag in bags.items()}


def robot(seeds: list[int], work: Path) -> dict[str, list]:
    from ekf_vo.tools.synth import SynthConfig, write_bag
    from ekf_vo.tools.synth_scene import GROUND_ROBOT_T_BASE_CAM_XYZ
    from ekf_vo.tools.wheel_odometry import WheelNoise
    params = {'T_base_cam_xyz': list(GROUND_ROBOT_T_BASE_CAM_XYZ)}
    out: dict[str, list] = {}
    for case, (trajectory, frames) in ROBOT_CASES.items():
        for share in SLIP_SHARES:
            runs = []
            for seed in seeds:
                bag = work / f'robot_{case}_{share}_{seed}'
                write_bag(SynthConfig(trajectory=trajectory, frames=frames, seed=seed),
                          bag, wheel_odom=WheelNoise(slip_share=share), overwrite=True)
                runs.append(run_one(bag, params, {'scale_source': 'odometry'}, seed))
            out[f'robot {case}, slip {share:.0%}'] = runs
    return out


def dds_run(bag: Path, params: list[str], work: Path, T_base_cam_xyz=(0.0, 0.0, 0.0)
            ) -> dict[str, Any]:
    """Play `bag` into a fresh vo_node (extra `-p` parameters `params`) and evaluate the
    odometry it publishes."""
    from bench.dds_nees import camera_poses, record_odometry
    from ekf_vo.config import NodeConfig
    from ekf_vo.core.frames import optical_to_body_extrinsic
    from ekf_vo.io.bag import read_ground_truth, topic_counts
    from ekf_vo.ros.harness import domain_id_for
    from ekf_vo.tools.evaluate import evaluate
    topics = [t for t in topic_counts(bag) if t != '/ground_truth/pose']
    args = ['-r', 'image:=/camera/image_raw', '-r', 'camera_info:=/camera/camera_info',
            '-r', 'odom:=/odom', '-r', 'scale_odom:=/scale_odom', '-p',
            'queue_policy:=all', '-p', 'T_base_cam_xyz:=[%s]' % ','.join(
                str(float(v)) for v in T_base_cam_xyz)]
    for item in params:
        args += ['-p', item]
    odom = record_odometry(bag, args, topics, work, domain_id_for(__name__))
    T_bc = optical_to_body_extrinsic(T_base_cam_xyz, NodeConfig().T_base_cam_xyzw)
    stamps, poses, _ = camera_poses(list(odom), T_bc)
    gt_ns, gt_T = read_ground_truth(bag)
    ev = evaluate(gt_ns * 1e-9, gt_T, stamps, poses, n_frames_total=len(gt_ns))
    return {'seed': 'dds', 'frames': len(gt_ns), 'pct_published': ev.pct_tracked,
            'resets': 0, 'scale': {}, 'scale_error_pct': ev.scale_error_pct,
            'ate_se3_pct': ev.ate_se3_pct_of_path, 'ate_sim3_pct': ev.ate_sim3_pct_of_path,
            'pose_nees_mean': None, 'pose_nees_median': None, 'pose_nees_pct_above': None,
            'twist_nees_linear_mean': None, 'twist_nees_angular_mean': None,
            'pose_nees_from_mean': None}


def dds(work: Path) -> dict[str, list]:
    from bench.common import shared_data
    from ekf_vo.tools.synth import SynthConfig, write_bag
    from ekf_vo.tools.synth_scene import GROUND_ROBOT_T_BASE_CAM_XYZ
    from ekf_vo.tools.wheel_odometry import WheelNoise
    out: dict[str, list] = {}
    folder = shared_data(SEQUENCE)
    if folder is not None:
        bag = build_bags(folder, work, ['raw-before'])['raw-before']
        out['raw-before over DDS'] = [dds_run(bag, [
            'scale_source:=camera_height', 'camera_height_m:=1.65'], work)]
    trajectory, frames = ROBOT_CASES['arcs']
    bag = work / 'robot_arcs_dds'
    write_bag(SynthConfig(trajectory=trajectory, frames=frames), bag,
              wheel_odom=WheelNoise(), overwrite=True)
    out['robot arcs, slip 5% over DDS'] = [dds_run(bag, ['scale_source:=odometry'], work,
                                                   GROUND_ROBOT_T_BASE_CAM_XYZ)]
    return out


def _fmt(v: Any, spec: str = '.2f') -> str:
    return '-' if v is None else format(v, spec)


def table(results: dict[str, list]) -> str:
    rows = ['| case | seed | published % | resets | scale error % | ATE SE(3) % | '
            'ATE Sim(3) % | pose NEES mean / median / % > bound | pose NEES from frame 12 | '
            'twist NEES lin / ang | scale sigma % |',
            '|---|---|---|---|---|---|---|---|---|---|---|']
    for name, runs in results.items():
        for r in runs:
            rows.append(
                f"| {name} | {r['seed']} | {r['pct_published']:.1f} | {r['resets']} | "
                f"{_fmt(r['scale_error_pct'], '+.2f')} | {_fmt(r['ate_se3_pct'])} | "
                f"{_fmt(r['ate_sim3_pct'], '.3f')} | {_fmt(r['pose_nees_mean'], '.1f')} / "
                f"{_fmt(r['pose_nees_median'], '.1f')} / "
                f"{_fmt(r['pose_nees_pct_above'], '.0f')} | "
                f"{_fmt(r.get('pose_nees_from_mean'), '.1f')} | "
                f"{_fmt(r['twist_nees_linear_mean'], '.1f')} / "
                f"{_fmt(r['twist_nees_angular_mean'], '.1f')} | "
                f"{_fmt(r['scale'].get('scale_sigma_pct'), '.1f')} |")
    return '\n'.join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='python -m bench.metric_scale', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    p.add_argument('--only', choices=('kitti', 'robot'), default=None)
    p.add_argument('--dds', action='store_true', help='also through vo_node over DDS')
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    results: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, 'kitti'):
            results.update(kitti(args.seeds, Path(tmp)))
        if args.only in (None, 'robot'):
            results.update(robot(args.seeds, Path(tmp)))
        if args.dds:
            results.update(dds(Path(tmp)))
    print(table(results))
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1) + '\n', encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())

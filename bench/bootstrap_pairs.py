"""How far off is the bootstrap pair's rotation, against its covariance? (docs/method.md §2.1.1)

Each rendered sequence (bench.rotation_nees's names: ``walk``, ``orbit_still``, ...) runs
until its first bootstrap; the pair's relative rotation is compared with the ground truth
and with the covariance the map is anchored with (map_uncertainty.relative_pose_covariance,
at pixel_sigma_px): the angle, and the NEES (3 dof; 16.27 is the 99.9 % bound). The error
of this pair is shared by the whole first map, and a first published pose hides it when
the orientation is aligned there, so it is measured here on its own.

    python -m bench.bootstrap_pairs [--sequences walk walk_still ...] [--seeds 0 1 2]
                                    [--set NAME=VALUE ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.map_uncertainty import relative_pose_covariance
from ekf_vo.core.stream import VoStream

from . import rotation_nees
from .common import overrides_or_report


def _first_pair(camera: dict, frames, overrides: dict, seed: int):
    """(stamp of the reference frame [ns], stamp of the current frame, T_world_ref,
    T_world_cur, map points, K) of the first bootstrap, or None. Stamps, not indices:
    the stream may skip frames before the pipeline counts them (repeats)."""
    cfg = dataclasses.replace(VoConfig(), **overrides).validate()
    stream = VoStream(cfg, seed=seed)                     # as bench.rotation_nees
    stream.set_camera(PinholeCamera.from_camera_info(camera))
    counted = {}                                          # pipeline frame index -> stamp
    try:
        for stamp, img, _ in frames:
            res = stream.process(img, stamp)
            vo = stream.vo
            if vo is None:
                continue
            counted.setdefault(vo.frame_index, stamp)
            if res.ok and getattr(res, 'bootstrapped', False) and vo.local_map is not None:
                kf = vo.local_map.keyframes
                return (counted[res.reference_frame_index], stamp, kf[0].T_world_cam_filter,
                        kf[-1].T_world_cam_filter, vo.map.X_world.copy(), vo.camera.K)
    finally:
        if stream.vo is not None:
            stream.vo.close()
    return None


def measure(name: str, seed: int, overrides: dict | None = None) -> dict:
    """The first bootstrap pair of one rendered sequence against its ground truth."""
    trajectory, speedup, still, fault, camera = rotation_nees._synthetic_name(name)
    overrides = overrides or {}
    gt_s, gt_T, pair = rotation_nees._synthetic(trajectory, seed, overrides, speedup, still,
                                                fault, run=_first_pair, camera=camera)
    if pair is None:
        return {'sequence': name, 'seed': seed, 'pair': None}
    s_ref, s_cur, T_ref, T_cur, X, K = pair
    ref, cur = (int(np.argmin(np.abs(gt_s - s * 1e-9))) for s in (s_ref, s_cur))
    R_est = T_ref[:3, :3].T @ T_cur[:3, :3]
    R_true = gt_T[ref][:3, :3].T @ gt_T[cur][:3, :3]
    d_world = T_ref[:3, :3] @ geo.quat_to_rotvec(geo.matrix_to_quat(R_est @ R_true.T))
    sigma_px = dataclasses.replace(VoConfig(), **overrides).pixel_sigma_px
    S = relative_pose_covariance(K, T_ref, T_cur, X, sigma_px)[3:, 3:]
    return {'sequence': name, 'seed': seed, 'pair': (ref, cur),
            'err_deg': float(np.degrees(np.linalg.norm(d_world))),
            'nees': float(d_world @ np.linalg.solve(S, d_world)),
            'sigma_deg': np.degrees(np.sqrt(np.diag(S))).round(3).tolist()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sequences', nargs='+', default=['walk', 'walk_still', 'orbit'])
    p.add_argument('--seeds', nargs='+', type=int, default=list(range(8)))
    p.add_argument('--set', nargs='+', default=[], metavar='NAME=VALUE')
    args = p.parse_args(argv)
    overrides = overrides_or_report(args.set, 'bootstrap_pairs')
    if overrides is None:
        return 2
    for name in args.sequences:
        if rotation_nees._synthetic_name(name) is None:
            print(f'bootstrap_pairs: {name} is not a rendered sequence', file=sys.stderr)
            return 2
    print('| sequence | seed | pair | rotation error deg | NEES | sigma deg (world x, y, z) |')
    print('|---|---|---|---|---|---|')
    for name in args.sequences:
        for seed in args.seeds:
            r = measure(name, seed, overrides)
            if r['pair'] is None:
                print(f'| {name} | {seed} | none | | | |', flush=True)
                continue
            print(f"| {name} | {seed} | {r['pair'][0]}-{r['pair'][1]} | {r['err_deg']:.3f} | "
                  f"{r['nees']:.1f} | {r['sigma_deg']} |", flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

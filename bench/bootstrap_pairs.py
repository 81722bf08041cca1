"""How far off is the bootstrap pair's rotation, against its covariance? (docs/method.md §2.1.1)

Each rendered sequence (bench.rotation_nees's names: ``walk``, ``orbit_still``, ...) runs
until its first bootstrap; the pair's relative rotation is compared with the ground truth
and with the covariance the map is anchored with (map_uncertainty.relative_pose_covariance,
at pixel_sigma_px): the angle, and the NEES (3 dof; 16.27 is the 99.9 % bound). The error
of this pair is shared by the whole first map, and a first published pose hides it when
the orientation is aligned there, so it is measured here on its own.

    python -m bench.bootstrap_pairs [--sequences walk walk_still ...] [--seeds 0 1 2]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.map_uncertainty import relative_pose_covariance
from ekf_vo.core.stream import VoStream
from . import rotation_nees


def _first_pair(camera: dict, frames, overrides: dict, seed: int):
    """(reference frame, current frame, T_world_ref, T_world_cur, map points) of the
    first bootstrap, or None."""
    stream = VoStream(VoConfig().validate(), seed=seed)      # as bench.rotation_nees
    stream.set_camera(PinholeCamera.from_camera_info(camera))
    try:
        for k, (stamp, img, _) in enumerate(frames):
            res = stream.process(img, stamp)
            if res.ok and res.bootstrapped:
                vo = stream.vo
                kf = vo.local_map.keyframes
                return (res.reference_frame_index, k, kf[0].T_world_cam_filter,
                        kf[-1].T_world_cam_filter, vo.map.X_world.copy(), vo.camera.K)
    finally:
        if stream.vo is not None:
            stream.vo.close()
    return None


def measure(name: str, seed: int) -> dict:
    trajectory, speedup, still, fault = rotation_nees._synthetic_name(name)
    gt_s, gt_T, pair = rotation_nees._synthetic(trajectory, seed, {}, speedup, still, fault,
                                                run=_first_pair)
    if pair is None:
        return {'sequence': name, 'seed': seed, 'pair': None}
    ref, cur, T_ref, T_cur, X, K = pair
    R_est = T_ref[:3, :3].T @ T_cur[:3, :3]
    R_true = gt_T[ref][:3, :3].T @ gt_T[cur][:3, :3]
    d_world = T_ref[:3, :3] @ geo.quat_to_rotvec(geo.matrix_to_quat(R_est @ R_true.T))
    S = relative_pose_covariance(K, T_ref, T_cur, X, VoConfig().pixel_sigma_px)[3:, 3:]
    return {'sequence': name, 'seed': seed, 'pair': (ref, cur),
            'err_deg': float(np.degrees(np.linalg.norm(d_world))),
            'nees': float(d_world @ np.linalg.solve(S, d_world)),
            'sigma_deg': np.degrees(np.sqrt(np.diag(S))).round(3).tolist()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--sequences', nargs='+', default=['walk', 'walk_still', 'orbit'])
    p.add_argument('--seeds', nargs='+', type=int, default=list(range(8)))
    args = p.parse_args(argv)
    for name in args.sequences:
        if rotation_nees._synthetic_name(name) is None:
            print(f'bootstrap_pairs: {name} is not a rendered sequence', file=sys.stderr)
            return 2
    print('| sequence | seed | pair | rotation error deg | NEES | sigma deg (world x, y, z) |')
    print('|---|---|---|---|---|---|')
    for name in args.sequences:
        for seed in args.seeds:
            r = measure(name, seed)
            if r['pair'] is None:
                print(f'| {name} | {seed} | none | | | |', flush=True)
                continue
            print(f"| {name} | {seed} | {r['pair'][0]}-{r['pair'][1]} | {r['err_deg']:.3f} | "
                  f"{r['nees']:.1f} | {r['sigma_deg']} |", flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

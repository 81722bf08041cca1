"""Does KITTI 06's ground truth agree with its own images over the first second?

docs/method.md §14.4. Every rotation NEES on KITTI 06 is judged against the ground truth's
orientation, so the ground truth itself is checked here, with nothing of ekf_vo's
estimator: for each pair of consecutive frames, OpenCV's five-point essential matrix
(Shi-Tomasi corners, KLT with a forward-backward check, RANSAC at 0.5 px, then
`recoverPose`) gives the relative rotation the images show, and it is compared with the
ground truth's relative rotation (both as rotation vectors in the earlier camera's frame,
degrees). Printed per stretch of frames: how much the ground truth's own relative
rotations vary (a driven car's do), and the summed disagreement with the images per axis
(what an orientation aligned at the stretch's first frame inherits).

    python -m bench.kitti_gt_check [--split 12] [--json OUT]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.geometry import matrix_to_quat, quat_to_rotvec
from ekf_vo.io.dataset import load_folder
from .common import machine, shared_data, write_json
from .rotation_nees import KITTI_GT_RELIABLE_FROM

#: RANSAC threshold of the essential matrix [px], forward-backward KLT gate [px]
_RANSAC_PX, _FB_PX = 0.5, 0.5


def _deg(R: np.ndarray) -> np.ndarray:
    """Rotation vector [deg] of a rotation matrix."""
    return np.degrees(quat_to_rotvec(matrix_to_quat(R)))


def image_rotation(K: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, int]:
    """Rotation R_a_b (camera b's axes in camera a) between two images, from the
    essential matrix of KLT tracks alone, and the number of RANSAC inliers."""
    p0 = cv2.goodFeaturesToTrack(a, 3000, 0.01, 7)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=4)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=(21, 21), maxLevel=4)
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(back - p0, axis=2)[:, 0] < _FB_PX)
    E, mask = cv2.findEssentialMat(p0[ok], p1[ok], K, cv2.RANSAC, 0.999, _RANSAC_PX)
    _, R_b_a, _, mask = cv2.recoverPose(E, p0[ok], p1[ok], K, mask=mask)
    return R_b_a.T, int(np.count_nonzero(mask))


def check(split: int) -> dict:
    data = load_folder(shared_data('kitti06_f0-50'))
    K = PinholeCamera.from_camera_info(data.camera).K
    T = np.asarray(data.gt_T_world_cam)
    frames = [g for _, g in data.frames()]
    rows = []
    for k in range(len(frames) - 1):
        R_gt = T[k, :3, :3].T @ T[k + 1, :3, :3]
        R_img, n = image_rotation(K, frames[k], frames[k + 1])
        rows.append({'frame': k, 'gt_deg': _deg(R_gt),
                     'images_minus_gt_deg': _deg(R_gt.T @ R_img),
                     'inliers': n})
    out = {'machine': machine(), 'split': split, 'pairs': rows, 'stretches': []}
    for lo, hi in ((0, split - 1), (split, len(rows))):
        part = rows[lo:hi]
        gt = np.array([r['gt_deg'] for r in part])
        diff = np.array([r['images_minus_gt_deg'] for r in part])
        out['stretches'].append({
            'frames': f'{lo}-{hi}', 'n_pairs': len(part),
            'gt_relative_rotation_std_deg': gt.std(axis=0),
            'summed_disagreement_deg': diff.sum(axis=0),
            'mean_abs_disagreement_deg': np.abs(diff).mean(axis=0)})
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--split', type=int, default=KITTI_GT_RELIABLE_FROM,
                   help='first frame after the stretch under suspicion')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    if shared_data('kitti06_f0-50') is None:
        print('bench.kitti_gt_check: skipped: the developers\' data folder (kitti06_f0-50) '
              'is absent', file=sys.stderr)
        return 2
    out = check(args.split)
    print(f"# KITTI 06: ground truth against the images' five-point rotations ({out['machine']})")
    print('| frames | GT relative rotation, std over the pairs (x, y, z) deg | '
          'images - GT, summed (x, y, z) deg | mean |images - GT| deg |')
    print('|---|---|---|---|')
    for s in out['stretches']:
        fmt = ', '.join
        print(f"| {s['frames']} | {fmt(f'{v:.4f}' for v in s['gt_relative_rotation_std_deg'])} | "
              f"{fmt(f'{v:+.3f}' for v in s['summed_disagreement_deg'])} | "
              f"{fmt(f'{v:.3f}' for v in s['mean_abs_disagreement_deg'])} |")
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == '__main__':
    sys.exit(main())

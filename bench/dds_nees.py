"""Rotation NEES of what vo_node publishes over DDS: a bag played into a fresh node.

`ekf-vo-play` (the player's Python API) plays a bag's images and CameraInfo in real time
into vo_node (`queue_policy: all`: nothing dropped), every
nav_msgs/Odometry is recorded, brought back from odom/base_link to the camera's optical
frame with the node's extrinsic (docs/ros.md: T_world_cam = T_base_cam^-1 T_odom_base
T_base_cam, rotation covariance R_bc^T Sigma R_bc), and compared with the bag's ground
truth as bench.rotation_nees does.

Sequences: ``demo`` = the bundled demo bag (JPEG CompressedImage, 640x480, 30 Hz);
``kitti`` = KITTI 06 frames 0-50 from ../shared/data through ekf-vo-convert (raw mono8,
1226x370, 10 Hz), its rotation NEES from frame 12 on, where its ground truth is
reliable (docs/method.md §14.4), as bench.rotation_nees's ``kitti_raw_from12``.

    python -m bench.dds_nees [--sequence demo|kitti] [--json OUT]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from .common import machine, write_json

INFO = '/camera/camera_info'
#: sequence -> (image topic played, image_transport of the node)
SEQUENCES = {'demo': ('/camera/image_raw/compressed', 'compressed'),
             'kitti': ('/camera/image_raw', 'raw')}


def record_odometry(bag: Path, node_args: list[str], topics: list[str], work: Path,
                    domain: int) -> list:
    """Start a vo_node (`node_args`), play `topics` of `bag` into it in real time, and
    return every nav_msgs/Odometry it published on /odom (its log in `work`)."""
    from nav_msgs.msg import Odometry
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from ekf_vo.ros.harness import Harness, NodeProcess
    from ekf_vo.ros.player import play_bag
    node = NodeProcess('ekf_vo.ros.vo_node', node_args, domain, work / 'vo_node.log')
    node.wait_for_output('vo_node ready')
    h = Harness(domain)
    try:
        odom = h.record(Odometry, '/odom', QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                                                      history=HistoryPolicy.KEEP_ALL))
        play_bag(h.node, bag, rate=1.0, topics=topics, clock=False, wait_for=['*'],
                 wait_timeout_s=20.0)
        h.spin_until_quiet(odom)            # until the answers stop coming
    finally:
        h.close()
        node.stop()
    return list(odom)


def _record(bag: Path, sequence: str, work: Path) -> list:
    from ekf_vo.ros.harness import domain_id_for
    image, transport = SEQUENCES[sequence]
    return record_odometry(bag, [
        '-p', f'image_transport:={transport}', '-r', 'image:=/camera/image_raw',
        '-r', 'camera_info:=' + INFO, '-r', 'odom:=/odom', '-p', 'queue_policy:=all'],
        [image, INFO], work, domain_id_for(__name__))


def _bag(sequence: str, work: Path) -> tuple[Path, float] | str:
    """(the bag to play, the stamp [s] from which the NEES is counted), or why the
    sequence is unavailable."""
    if sequence == 'demo':
        from ekf_vo.tools.demo import demo_bag
        return demo_bag(), -np.inf
    from ekf_vo.io.dataset import load_folder
    from ekf_vo.tools.convert import convert
    from .common import shared_data
    from .rotation_nees import KITTI_GT_RELIABLE_FROM
    folder = shared_data('kitti06_f0-50')
    if folder is None:
        return 'kitti skipped: ../shared/data/kitti06_f0-50 is absent'
    bag = work / 'kitti06_raw'
    convert('kitti', folder, bag, jpeg_quality=None, info_after_image=False)
    return bag, load_folder(folder).stamps_ns[KITTI_GT_RELIABLE_FROM] * 1e-9 - 1e-6


def camera_poses(msgs: list, T_bc: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps s, T_world_cam (n,4,4), 6x6 covariances whose rotation block is in the
    camera's world frame) from odometry messages of a node with the extrinsic `T_bc`
    (T_base_cam; None: the default one)."""
    from ekf_vo import bridge as conv
    from ekf_vo.config import NodeConfig
    from ekf_vo.core import geometry as geo
    from ekf_vo.core.frames import optical_to_body_extrinsic
    if T_bc is None:
        cfg = NodeConfig()
        T_bc = optical_to_body_extrinsic(cfg.T_base_cam_xyz, cfg.T_base_cam_xyzw)
    R_bc = T_bc[:3, :3]
    stamps, poses, covs = [], [], []
    for m in msgs:
        p, q = m.pose.pose.position, m.pose.pose.orientation
        T_ob = geo.make_T(geo.quat_to_matrix(np.array([q.w, q.x, q.y, q.z])),
                          np.array([p.x, p.y, p.z]))
        stamps.append(conv.stamp_to_ns(m.header.stamp) * 1e-9)
        poses.append(np.linalg.inv(T_bc) @ T_ob @ T_bc)
        C = np.array(m.pose.covariance, float).reshape(6, 6)
        cov = np.eye(6)
        cov[3:, 3:] = R_bc.T @ C[3:, 3:] @ R_bc
        covs.append(cov)
    return np.array(stamps), np.array(poses), np.array(covs)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--sequence', choices=sorted(SEQUENCES), default='demo')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    from ekf_vo.io.bag import read_ground_truth
    from ekf_vo.tools.consistency import rotation_nees
    with tempfile.TemporaryDirectory() as tmp:
        found = _bag(args.sequence, Path(tmp))
        if isinstance(found, str):
            print(f'bench.dds_nees: {found}')
            return 0
        bag, from_s = found
        msgs = _record(bag, args.sequence, Path(tmp))
        gt_ns, gt_T = read_ground_truth(bag)
    if len(msgs) < 3:
        print(f'bench.dds_nees: only {len(msgs)} odometry messages', file=sys.stderr)
        return 1
    stamps, poses, covs = camera_poses(msgs)
    keep = stamps >= from_s
    rn = rotation_nees(np.asarray(gt_ns) * 1e-9, gt_T, stamps[keep], poses[keep],
                       stamps[keep], covs[keep], 1e-3)
    from .rotation_nees import KITTI_GT_RELIABLE_FROM
    counted = '' if args.sequence == 'demo' else \
        f', NEES from frame {KITTI_GT_RELIABLE_FROM}'
    print(f'# rotation NEES of vo_node over DDS, {args.sequence}{counted} ({machine()})')
    print(f'odometry messages {len(msgs)}; rotation NEES mean {rn.mean:.2f}, median '
          f'{rn.median:.2f}, {rn.pct_above_999:.1f} % above 16.27; max rotation error '
          f'{np.max(rn.err_deg):.2f} deg')
    if args.json:
        write_json(args.json, {'machine': machine(), 'sequence': args.sequence,
                               'n_odometry': len(msgs), **rn.to_dict(),
                               'rot_err_max_deg': float(np.max(rn.err_deg))})
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""The main job (`make demo`): the bundled bag through vo_node + map_node over DDS.

1. start vo_node and map_node in their own process (`ekf_vo_nodes`, the shipped params file,
   use_sim_time, compressed transport) on a private localhost-only DDS domain;
2. play bags/demo from this process with /clock (ekf-vo-play's library function);
3. record the odometry the node PUBLISHED (the online trajectory) and the late-joiner map;
4. convert odometry (base frame in odom) back to the camera optical frame, evaluate it
   against the bag's /ground_truth/pose with evo (Sim(3) ATE, RPE, rotation), print the
   summary table, write the TUM trajectory, the JSON summary and the plot.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEMO_BAG = REPO / 'bags' / 'demo'
PARAMS = REPO / 'config' / 'ekf_vo.yaml'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--bag', type=Path, default=DEMO_BAG)
    parser.add_argument('--params', type=Path, default=PARAMS)
    parser.add_argument('--out', type=Path, default=Path('out/demo'))
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--domain-id', type=int, default=int(os.environ.get(
        'EKF_VO_DEMO_DOMAIN', '77')), help='private DDS domain for the demo')
    args = parser.parse_args(argv)
    # private, localhost-only DDS traffic: the demo must not talk to a robot on the LAN
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    t_start = time.perf_counter()

    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from ekf_vo.ros.harness import Harness, NodeProcess
    from ..config import load_yaml_params, split_params
    from ..core import geometry as geo
    from ..core.frames import optical_to_body_extrinsic
    from ..ros import conversions as conv
    from . import bagio
    from .evaluate import evaluate, format_table, plot_result
    from .play import play_bag
    from .trajectory_io import write_tum

    args.out.mkdir(parents=True, exist_ok=True)
    topics = bagio.bag_topics(args.bag)
    image_topic = next(t for t, ty in topics.items() if ty.endswith('CompressedImage')
                       or ty.endswith('/Image'))
    compressed = topics[image_topic].endswith('CompressedImage')
    info_topic = next(t for t, ty in topics.items() if ty.endswith('CameraInfo'))
    ros_args = ['--params-file', str(args.params), '-p', 'use_sim_time:=true',
                '-r', f'camera_info:={info_topic}', '-r', 'odom:=/odom']
    if compressed:
        ros_args += ['-p', 'image_transport:=compressed',
                     '-r', f'image/compressed:={image_topic}']
    else:
        ros_args += ['-r', f'image:={image_topic}']
    _, node_cfg = split_params(load_yaml_params(args.params))
    T_base_cam = optical_to_body_extrinsic(node_cfg.T_base_cam_xyz, node_cfg.T_base_cam_xyzw)

    print(f'[demo] starting vo_node + map_node (domain {args.domain_id}), bag {args.bag}')
    nodes = NodeProcess('ekf_vo.ros.run_all', ros_args, args.domain_id,
                        args.out / 'nodes.log')
    h = None
    try:
        nodes.wait_for_output('vo_node ready', timeout=60.0)
        h = Harness(args.domain_id, 'ekf_vo_demo')
        odom: list = []
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        h.node.create_subscription(Odometry, '/odom', odom.append, reliable)
        done = threading.Event()
        stats: dict = {}

        def play() -> None:
            stats.update(play_bag(h.node, args.bag, rate=args.rate, clock=True,
                                  wait_for=[image_topic, info_topic], start_paused_s=0.5))
            done.set()
        print(f'[demo] playing {args.bag.name} at x{args.rate} with /clock ...')
        player = threading.Thread(target=play, daemon=True)
        player.start()
        while not done.is_set():
            h.executor.spin_once(timeout_sec=0.05)
        h.spin_for(2.0)          # the last frames' odometry
        clouds: list = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        h.node.create_subscription(PointCloud2, '/map_points', clouds.append, latched)
        h.spin_until(lambda: clouds, 5.0)
    finally:
        if h is not None:
            h.close()
        nodes.stop()

    n_frames = stats.get('per_topic', {}).get(image_topic, 0)
    stamps, poses = [], []
    T_cam_base = geo.invert_T(T_base_cam)
    for msg in odom:
        T_odom_base, _, _, _ = conv.odometry_to_pose(msg)
        # invert T_odom_base = T_base_cam T_world_cam T_base_cam^-1 (vo_node's output map)
        poses.append(T_cam_base @ T_odom_base @ T_base_cam)
        stamps.append(conv.stamp_to_ns(msg.header.stamp) * 1e-9)
    est_tum = args.out / 'estimate_tum.txt'
    write_tum(est_tum, np.array(stamps), np.array(poses) if poses else np.zeros((0, 4, 4)))
    gt_ns, gt_T = bagio.read_ground_truth(args.bag)
    write_tum(args.out / 'groundtruth_tum.txt', gt_ns * 1e-9, gt_T)
    wall = time.perf_counter() - t_start
    if len(stamps) < 3:
        print(f'[demo] FAILED: only {len(stamps)} odometry messages; see '
              f'{args.out / "nodes.log"}')
        return 1
    result = evaluate(gt_ns * 1e-9, gt_T, np.array(stamps), np.array(poses),
                      n_frames_total=n_frames)
    plot_result(result, args.out / 'trajectory.png', title='ekf_vo demo: online odometry')
    n_map = len(conv.pointcloud2_to_xyz(clouds[-1])) if clouds else 0
    summary = result.to_dict()
    summary.update({'frames_played': n_frames, 'odometry_messages': len(stamps),
                    'map_points_late_subscriber': n_map, 'wall_time_s': wall})
    (args.out / 'summary.json').write_text(json.dumps(summary, indent=1, default=float))
    print()
    print(format_table(result))
    print(f'{"Odometry messages":<38}{len(stamps)} for {n_frames} frames played')
    print(f'{"Map points (late subscriber)":<38}{n_map}')
    print(f'{"Wall time":<38}{wall:.1f} s')
    print(f'[demo] wrote {est_tum}, {args.out / "trajectory.png"}, '
          f'{args.out / "summary.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

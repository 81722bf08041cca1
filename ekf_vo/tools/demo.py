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

from ..cli import HelpFormatter, UsageError, check_writable, entry_point

#: the source tree (a checkout or an editable install); bags/ and config/ are here
SOURCE_ROOT = Path(__file__).resolve().parents[2]


def package_file(relative: str) -> Path:
    """`relative` (e.g. 'bags/demo') in the installed share directory (ament index,
    share/ekf_vo) when it is there, else in the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory
        installed = Path(get_package_share_directory('ekf_vo')) / relative
    except (ImportError, LookupError, OSError, ValueError):
        installed = None        # no ament index (plain venv) or the package is not in it
    if installed is not None and installed.exists():
        return installed
    return SOURCE_ROOT / relative


def demo_bag() -> Path:
    """The bundled demo bag (bags/demo)."""
    return package_file('bags/demo')


def load_demo_frames(bag: Path | None = None) -> tuple[dict, list]:
    """The bag's first CameraInfo (as a dict) and every image, decoded to grey, with its
    stamp: (info, [(stamp_ns, gray), ...]). Needs no rclpy (message fields only)."""
    from ..bridge import camera_info_to_dict, decode_image, select_camera_topics, stamp_to_ns
    from ..io.bag import bag_topics, iter_bag
    bag = bag or demo_bag()
    camera = select_camera_topics(bag_topics(bag))
    info, frames = None, []
    for topic, msgtype, _, msg in iter_bag(bag, [camera.image, camera.info]):
        if topic == camera.info:
            info = camera_info_to_dict(msg) if info is None else info
        else:
            frames.append((stamp_to_ns(msg.header.stamp), decode_image(msgtype, msg, gray=True)))
    return info, frames


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='ekf-vo-demo', description=__doc__.split('\n')[0],
                                     formatter_class=HelpFormatter)
    parser.add_argument('--bag', type=Path, default=demo_bag(),
                        help='bag to play (rosbag2 directory or ROS 1 .bag file)')
    parser.add_argument('--params', type=Path, default=package_file('config/ekf_vo.yaml'),
                        help='params file of the nodes')
    parser.add_argument('--out', type=Path, default=Path('out/demo'),
                        help='output folder (trajectories, summary.json, plot, node log)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--domain-id', type=int, default=int(os.environ.get(
        'EKF_VO_DEMO_DOMAIN', '77')), help='private DDS domain for the demo')
    return parser


def node_ros_args(bag: Path, params: Path) -> tuple[list[str], str, str]:
    """The nodes' --ros-args for the bag's image and CameraInfo topics:
    (ros_args, image_topic, info_topic)."""
    from ..bridge.topics import select_camera_topics, transport_topic
    from ..io.bag import bag_topics
    camera = select_camera_topics(bag_topics(bag))
    # the demo is a replay: every frame processed in order, the same figures on every run
    # and equal to `ekf-vo-run` on the bag (docs/ros.md §8)
    ros_args = ['--params-file', str(params), '-p', 'use_sim_time:=true',
                '-p', 'queue_policy:=all',
                '-r', f'camera_info:={camera.info}', '-r', 'odom:=/odom',
                '-p', f'image_transport:={camera.transport}',
                '-r', f"{transport_topic('image', camera.transport)}:={camera.image}"]
    return ros_args, camera.image, camera.info


def play_and_record(h, args: argparse.Namespace, topics: tuple[str, str]
                    ) -> tuple[list, list, dict]:
    """Play the bag from the harness's node (with /clock) while recording /odom; then get
    the map as a late subscriber. Returns (odometry, map clouds, play statistics)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    from ..ros.player import play_bag
    odom = h.record(Odometry, '/odom', QoSProfile(depth=100,
                                                  reliability=ReliabilityPolicy.RELIABLE))
    done = threading.Event()
    stats: dict = {}

    def play() -> None:
        stats.update(play_bag(h.node, args.bag, rate=args.rate, clock=True,
                              wait_for=list(topics), start_paused_s=0.5))
        done.set()
    print(f'[demo] playing {args.bag.name} at x{args.rate} with /clock ...')
    threading.Thread(target=play, daemon=True).start()
    while not done.is_set():
        h.executor.spin_once(timeout_sec=0.05)
    h.spin_for(2.0)          # the last frames' odometry
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    clouds = h.record(PointCloud2, '/map_points', latched)
    h.spin_until(lambda: clouds, 5.0)
    return odom, clouds, stats


def run_nodes(args: argparse.Namespace) -> tuple[list, list, dict, str]:
    """vo_node + map_node in their own process, fed the bag over DDS:
    (odometry, map clouds, play statistics, image topic)."""
    from ..ros.harness import Harness, NodeProcess
    ros_args, image_topic, info_topic = node_ros_args(args.bag, args.params)
    print(f'[demo] starting vo_node + map_node (domain {args.domain_id}), bag {args.bag}')
    nodes = NodeProcess('ekf_vo.ros.run_all', ros_args, args.domain_id,
                        args.out / 'nodes.log')
    h = None
    try:
        nodes.wait_for_output('vo_node ready', timeout=60.0)
        h = Harness(args.domain_id, 'ekf_vo_demo')
        return (*play_and_record(h, args, (image_topic, info_topic)), image_topic)
    finally:
        if h is not None:
            h.close()
        nodes.stop()


def base_cam_extrinsic(params: Path) -> np.ndarray:
    """T_base_cam (optical camera frame in the base frame) of the nodes' params file."""
    from ..config import load_yaml_params, split_params
    from ..core.frames import optical_to_body_extrinsic
    _, node_cfg = split_params(load_yaml_params(params))
    return optical_to_body_extrinsic(node_cfg.T_base_cam_xyz, node_cfg.T_base_cam_xyzw)


def camera_trajectory(odom: list, T_base_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Odometry (base frame in odom) back to the camera optical frame: (stamps_s, T)."""
    from .. import bridge as conv
    from ..core import geometry as geo
    T_cam_base = geo.invert_T(T_base_cam)
    stamps, poses = [], []
    for msg in odom:
        T_odom_base, _, _, _ = conv.odometry_to_pose(msg)
        # invert T_odom_base = T_base_cam T_world_cam T_base_cam^-1 (vo_node's output map)
        poses.append(T_cam_base @ T_odom_base @ T_base_cam)
        stamps.append(conv.stamp_to_ns(msg.header.stamp) * 1e-9)
    return np.array(stamps), np.array(poses) if poses else np.zeros((0, 4, 4))


def report(args: argparse.Namespace, result, n_frames: int, n_odom: int, n_map: int,
           wall: float, est_tum: Path) -> None:
    """Plot, write summary.json and print the summary table."""
    from .evaluate import format_table, plot_result
    plot_result(result, args.out / 'trajectory.png', title='ekf_vo demo: online odometry')
    summary = result.to_dict()
    summary.update({'frames_played': n_frames, 'odometry_messages': n_odom,
                    'map_points_late_subscriber': n_map, 'wall_time_s': wall})
    (args.out / 'summary.json').write_text(json.dumps(summary, indent=1, default=float))
    print()
    print(format_table(result))
    print(f'{"Odometry messages":<38}{n_odom} for {n_frames} frames played')
    print(f'{"Map points (late subscriber)":<38}{n_map}')
    print(f'{"Wall time":<38}{wall:.1f} s')
    print(f'[demo] wrote {est_tum}, {args.out / "trajectory.png"}, '
          f'{args.out / "summary.json"}')


def check_inputs(args: argparse.Namespace) -> str | None:
    """Why the demo cannot run (bag, params file, output folder), before any node starts;
    None when it can."""
    from ..bridge.topics import TopicError, select_camera_topics
    from ..config import ConfigError
    from ..io.bag import BagError, bag_topics
    try:
        select_camera_topics(bag_topics(args.bag))
        base_cam_extrinsic(args.params)
        check_writable(args.out / 'summary.json', '--out')
    except (BagError, TopicError, ConfigError, UsageError) as exc:
        return str(exc)
    return None


@entry_point
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    problem = check_inputs(args)
    if problem is not None:
        print(f'ekf-vo-demo: error: {problem}', file=sys.stderr)
        return 2
    # private, localhost-only DDS traffic: the demo must not talk to a robot on the LAN
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    t_start = time.perf_counter()
    from .. import bridge as conv
    from ..io import bag as bagio
    from ..io.trajectory import write_tum
    from .evaluate import evaluate

    args.out.mkdir(parents=True, exist_ok=True)
    T_base_cam = base_cam_extrinsic(args.params)
    odom, clouds, stats, image_topic = run_nodes(args)
    n_frames = stats.get('per_topic', {}).get(image_topic, 0)
    stamps, poses = camera_trajectory(odom, T_base_cam)
    est_tum = args.out / 'estimate_tum.txt'
    write_tum(est_tum, stamps, poses)
    gt_ns, gt_T = bagio.read_ground_truth(args.bag)
    write_tum(args.out / 'groundtruth_tum.txt', gt_ns * 1e-9, gt_T)
    wall = time.perf_counter() - t_start
    if len(stamps) < 3:
        print(f'[demo] FAILED: only {len(stamps)} odometry messages; see '
              f'{args.out / "nodes.log"}')
        return 1
    result = evaluate(gt_ns * 1e-9, gt_T, stamps, poses, n_frames_total=n_frames)
    n_map = len(conv.pointcloud2_to_xyz(clouds[-1])) if clouds else 0
    report(args, result, n_frames, len(stamps), n_map, wall, est_tum)
    return 0


if __name__ == '__main__':
    sys.exit(main())

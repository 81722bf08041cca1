"""Replay is repeatable: the same bag played twice into a fresh vo_node with
`queue_policy: all`, while another process loads the CPU, gives identical odometry (every
pose and covariance), and the same trajectory as `ekf-vo-run` on that bag."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from ekf_vo import bridge as conv
from ekf_vo.config import NodeConfig
from ekf_vo.core import geometry as geo
from ekf_vo.core.frames import optical_to_body_extrinsic
from ekf_vo.ros.harness import Harness, NodeProcess, domain_id_for, ros_env
from ekf_vo.ros.player import play_bag
from ekf_vo.tools.demo import demo_bag
from ekf_vo.tools.run import run_bag

pytestmark = pytest.mark.ros
DOMAIN = domain_id_for(__name__)
IMAGE, INFO = '/camera/image_raw/compressed', '/camera/camera_info'
N_FRAMES = 300          # the whole demo bag (10 s at 30 Hz)


def _odometry_rows(msgs: list[Odometry]) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (n,) int ns, and (n, 7 + 36 + 36): pose (xyz, xyzw), pose and twist
    covariance."""
    stamps, rows = [], []
    for m in msgs:
        p, q = m.pose.pose.position, m.pose.pose.orientation
        stamps.append(conv.stamp_to_ns(m.header.stamp))
        rows.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w, *m.pose.covariance,
                     *m.twist.covariance])
    return np.array(stamps, np.int64), np.array(rows, dtype=np.float64).reshape(-1, 79)


def _start_vo_node(tmp_path, *params: str) -> NodeProcess:
    """vo_node on the demo bag's compressed topics (plus `-p` params), once ready."""
    args = ['-p', 'image_transport:=compressed', '-r', 'image:=/camera/image_raw',
            '-r', 'camera_info:=' + INFO, '-r', 'odom:=/odom']
    for p in params:
        args += ['-p', p]
    node = NodeProcess('ekf_vo.ros.vo_node', args, DOMAIN, tmp_path / 'vo_node.log')
    node.wait_for_output('vo_node ready')
    return node


def _replay(tmp_path, bag) -> tuple[np.ndarray, np.ndarray]:
    tmp_path.mkdir()
    node = _start_vo_node(tmp_path, 'queue_policy:=all')
    h = Harness(DOMAIN)
    try:
        odom = h.record(Odometry, '/odom', QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                                                      history=HistoryPolicy.KEEP_ALL))
        stats = play_bag(h.node, bag, rate=1.0, topics=[IMAGE, INFO], clock=False,
                         wait_for=['*'], wait_timeout_s=20.0)
        assert stats, 'nothing played'
        # the node answers every frame it can; wait until the answers stop coming
        h.spin_until_quiet(odom)
    finally:
        h.close()
        assert node.stop() == 0, node.output()
    return _odometry_rows(odom)


def test_replay_twice_under_load_is_identical_and_equals_the_offline_run(tmp_path):
    bag = demo_bag()
    load = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    try:
        runs = [_replay(tmp_path / f'run{k}', bag) for k in range(2)]
    finally:
        load.kill()
        load.wait()
    (stamps_a, a), (stamps_b, b) = runs
    assert len(a) > 0.8 * N_FRAMES, f'only {len(a)} odometry messages for {N_FRAMES} frames'
    assert a.shape == b.shape, f'{len(a)} vs {len(b)} odometry messages'
    assert np.array_equal(stamps_a, stamps_b), 'different frames answered'
    assert np.allclose(a, b, rtol=0, atol=1e-9), np.abs(a - b).max()

    offline = run_bag(bag, image_topic=IMAGE, info_topic=INFO)
    # ekf-vo-run reports stamps in float seconds: equal to well within 1 us
    assert len(offline.est_stamps_s) == len(stamps_a), 'node and ekf-vo-run differ in frames'
    assert np.all(np.abs(offline.est_stamps_s * 1e9 - stamps_a) < 1e3)
    cfg = NodeConfig()
    T_base_cam = optical_to_body_extrinsic(cfg.T_base_cam_xyz, cfg.T_base_cam_xyzw)
    T_odom_base = T_base_cam @ offline.est_T_world_cam @ np.linalg.inv(T_base_cam)
    assert np.allclose(T_odom_base[:, :3, 3], a[:, :3], rtol=0, atol=1e-9)
    # orientations: the node's quaternion xyzw against the offline rotation
    R_node = np.stack([geo.quat_to_matrix(np.r_[q[3], q[:3]]) for q in a[:, 3:7]])
    assert np.allclose(R_node, T_odom_base[:, :3, :3], rtol=0, atol=1e-9)


def test_player_paced_by_odometry_never_outruns_a_live_node(tmp_path):
    """`ekf-vo-play --pace-topic /odom` at 20x into vo_node with the live policy (latest,
    queue of 2): the player waits for each frame's odometry, so the node drops nothing and
    answers as many frames as the offline run does."""
    from diagnostic_msgs.msg import DiagnosticArray

    bag = demo_bag()
    node = _start_vo_node(tmp_path, 'reliable_qos:=true')
    h = Harness(DOMAIN)
    try:
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        odom = h.record(Odometry, '/odom', reliable)
        status = h.record(DiagnosticArray, '/vo_node/status', reliable)
        player = subprocess.Popen(
            [sys.executable, '-m', 'ekf_vo.ros.player', str(bag), '--rate', '20',
             '--no-clock', '--topics', IMAGE, INFO, '--wait-for', '*',
             '--pace-topic', '/odom', '--pace-timeout-s', '0.5'],
            env=ros_env(DOMAIN), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # record while it plays (a recorder that is not spun keeps only its last 100)
        assert h.spin_until(lambda: player.poll() is not None, 300.0), 'player hangs'
        out, err = player.communicate()
        assert player.returncode == 0, err
        h.spin_for(1.5)
    finally:
        h.close()
        assert node.stop() == 0, node.output()
    values = {kv.key: kv.value for kv in status[-1].status[0].values}
    assert int(values.get('dropped_behind', 0)) == 0, values
    # the local map (on by default) reports its keyframes and adjustments on ~/status
    assert int(values['keyframes']) >= 5 and int(values['ba_runs']) >= 3, values
    assert float(values['ba_max_ms']) > 0, values
    offline = run_bag(bag, image_topic=IMAGE, info_topic=INFO)
    assert len(odom) >= offline.frames_ok - 3, (len(odom), offline.frames_ok, out)

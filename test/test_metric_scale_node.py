"""vo_node in metres over DDS: the rendered ground robot with a wheel odometry on
/scale_odom, replayed (queue_policy all) into a fresh node, publishes the same metric
odometry as `ekf-vo-run` on that bag, and says so on ~/status."""
from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from ekf_vo import bridge as conv
from ekf_vo.ros.harness import Harness, NodeProcess, domain_id_for
from ekf_vo.ros.player import play_bag
from ekf_vo.tools.run import run_bag
from ekf_vo.tools.synth import SynthConfig, write_bag
from ekf_vo.tools.synth_scene import GROUND_ROBOT_T_BASE_CAM_XYZ
from ekf_vo.tools.wheel_odometry import WheelNoise

pytestmark = pytest.mark.ros
DOMAIN = domain_id_for(__name__)
XYZ = '[%s]' % ','.join(str(float(v)) for v in GROUND_ROBOT_T_BASE_CAM_XYZ)


def test_vo_node_publishes_metres_from_a_wheel_odometry(tmp_path):
    bag = tmp_path / 'robot'
    write_bag(SynthConfig(trajectory='ground_robot', frames=170), bag,
              wheel_odom=WheelNoise())
    offline = run_bag(bag, {'T_base_cam_xyz': list(GROUND_ROBOT_T_BASE_CAM_XYZ)},
                      {'scale_source': 'odometry'})
    args = ['-r', 'image:=/camera/image_raw', '-r', 'camera_info:=/camera/camera_info',
            '-r', 'odom:=/odom', '-r', 'scale_odom:=/scale_odom', '-p', 'queue_policy:=all',
            '-p', 'scale_source:=odometry', '-p', f'T_base_cam_xyz:={XYZ}']
    node = NodeProcess('ekf_vo.ros.vo_node', args, DOMAIN, tmp_path / 'vo_node.log')
    node.wait_for_output('vo_node ready')
    h = Harness(DOMAIN)
    try:
        keep_all = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                              history=HistoryPolicy.KEEP_ALL)
        odom = h.record(Odometry, '/odom', keep_all)
        status = h.record(DiagnosticArray, '/vo_node/status', keep_all)
        play_bag(h.node, bag, rate=1.0, topics=['/camera/image_raw', '/camera/camera_info',
                                                '/scale_odom'],
                 clock=False, wait_for=['*'], wait_timeout_s=20.0)
        h.spin_until_quiet(odom)
    finally:
        h.close()
        assert node.stop() == 0, node.output()
    # the same frames published as offline (nothing before the first scale measurement)
    assert len(odom) == offline.frames_ok > 0
    stamps = np.array([conv.stamp_to_ns(m.header.stamp) * 1e-9 for m in odom])
    assert np.allclose(stamps, offline.est_stamps_s)
    # base positions in metres: their path is the offline camera path's (same scale)
    base = np.array([[m.pose.pose.position.x, m.pose.pose.position.y,
                      m.pose.pose.position.z] for m in odom])
    cam = np.array(offline.est_T_world_cam)[:, :3, 3]
    assert np.linalg.norm(base[-1] - base[0]) == pytest.approx(
        np.linalg.norm(cam[-1] - cam[0]), rel=0.01)
    assert offline.eval is not None and abs(offline.eval.scale_error_pct) < 3.0
    waiting = [a.status[0] for a in status if 'waiting for the metric scale' in
               a.status[0].message]
    assert waiting and all(st.level == DiagnosticStatus.WARN for st in waiting)
    values = {kv.key: kv.value for kv in status[-1].status[0].values}
    assert values['scale_source'] == 'odometry'
    assert values['scale_state'] in ('metric', 'coasting')
    assert float(values['scale']) == pytest.approx(offline.scale['scale'], rel=0.01)

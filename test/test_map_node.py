"""map_node in its own process over real DDS: upsert/delete by id, latched map, ~/clear,
bad input survival, exit code on bad parameters."""
from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from ekf_vo.bridge import pointcloud2_to_numpy, points_to_pointcloud2
from ekf_vo.ros.harness import Harness, NodeProcess, ros_env

pytestmark = pytest.mark.ros

#: Per-run namespace: two runs of this module at once (same domain) must not cross-talk.
NAMESPACE = f'/t{os.getpid()}_{uuid.uuid4().hex[:6]}'
STAMP0 = 1_700_000_000_000_000_000

LANDMARKS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                           reliability=ReliabilityPolicy.RELIABLE)
LATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture
def map_node_proc(tmp_path: Path, domain_id: int):
    """map_node as its own process at 5 Hz in NAMESPACE; stopped with SIGINT."""
    node = NodeProcess('ekf_vo.ros.map_node', ['-r', f'__ns:={NAMESPACE}',
                                              '-p', 'publish_rate_hz:=5.0'],
                       domain_id, tmp_path / 'map_node.log')
    try:
        yield node
    finally:
        node.stop()


@pytest.fixture
def landmarks(harness: Harness):
    """The harness's publisher of NAMESPACE/landmarks."""
    return harness.node.create_publisher(PointCloud2, 'landmarks', LANDMARKS_QOS)


def clear_map(harness: Harness) -> Trigger.Response:
    return harness.call(Trigger, f'{NAMESPACE}/map_node/clear')


def landmarks_msg(ids, xyz, n_obs=None, removed=None, frame='odom', stamp_ns=STAMP0,
                  fields=('id', 'n_obs', 'removed')) -> PointCloud2:
    ids = np.asarray(ids, dtype=np.uint32)
    n = ids.size
    columns = {'id': ids,
               'n_obs': np.asarray(n_obs if n_obs is not None else np.ones(n), np.uint32),
               'removed': np.asarray(removed if removed is not None else np.zeros(n), np.uint8)}
    extra = {k: v for k, v in columns.items() if k in fields}
    return points_to_pointcloud2(np.asarray(xyz, float).reshape(n, 3), stamp_ns, frame, extra)


def cloud_map(msg: PointCloud2) -> dict[int, tuple[np.ndarray, int]]:
    cols = pointcloud2_to_numpy(msg)
    assert set(cols) == {'x', 'y', 'z', 'id', 'n_obs'}
    xyz = np.stack([cols['x'], cols['y'], cols['z']], axis=1)
    return {int(i): (xyz[k], int(cols['n_obs'][k])) for k, i in enumerate(cols['id'])}


def assert_map(msg: PointCloud2, expected: dict[int, tuple[tuple, int]]) -> None:
    assert msg.header.frame_id == 'odom'
    assert msg.height == 1 and msg.width == len(expected)
    assert msg.is_dense
    got = cloud_map(msg)
    assert sorted(got) == sorted(expected)
    for i, (pos, n_obs) in expected.items():
        np.testing.assert_allclose(got[i][0], np.asarray(pos, np.float32), rtol=0, atol=1e-6)
        assert got[i][1] == n_obs


def matches(received: list[PointCloud2], expected: dict) -> Callable[[], bool]:
    def check() -> bool:
        return bool(received) and sorted(cloud_map(received[-1])) == sorted(expected)
    return check


def test_map_upsert_delete_late_joiner_and_clear(map_node_proc: NodeProcess, harness: Harness,
                                                  landmarks) -> None:
    early = harness.record(PointCloud2, 'map_points',
                           QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    assert harness.spin_until(lambda: landmarks.get_subscription_count() > 0, 15.0), \
        'map_node did not subscribe to landmarks'

    landmarks.publish(landmarks_msg(
        [1, 2, 3], [[1.0, 0.0, 2.0], [0.5, -0.5, 3.0], [-1.0, 0.25, 4.0]], n_obs=[2, 2, 3]))
    landmarks.publish(landmarks_msg(          # update id 2, add id 7
        [2, 7], [[0.6, -0.4, 3.1], [2.0, 2.0, 5.0]], n_obs=[5, 2], stamp_ns=STAMP0 + 10**8))
    landmarks.publish(landmarks_msg(          # delete id 3 (xyz NaN is allowed)
        [3], [[np.nan] * 3], n_obs=[0], removed=[1], stamp_ns=STAMP0 + 2 * 10**8))
    expected = {1: ((1.0, 0.0, 2.0), 2), 2: ((0.6, -0.4, 3.1), 5), 7: ((2.0, 2.0, 5.0), 2)}

    # The volatile subscriber sees the map converge: all three updates were applied.
    assert harness.spin_until(matches(early, expected), 10.0), \
        f'map never reached ids {sorted(expected)}; got {[m.width for m in early]}'
    assert_map(early[-1], expected)
    assert early[-1].header.stamp.sec == (STAMP0 + 2 * 10**8) // 10**9

    # A subscriber created after everything was published gets exactly the last map.
    late = harness.record(PointCloud2, 'map_points', LATE_QOS)
    assert harness.spin_until(lambda: bool(late), 10.0), 'late joiner got no map_points'
    assert_map(late[0], expected)

    # Nothing changes -> nothing is republished (the rate is 5 Hz; wait > 2 periods).
    n_before = len(late)
    harness.spin_until(lambda: False, 0.6)
    assert len(late) == n_before

    response = clear_map(harness)
    assert response.success and '3' in response.message
    assert harness.spin_until(lambda: len(late) > n_before and late[-1].width == 0, 10.0)
    assert late[-1].header.frame_id == 'odom' and late[-1].is_dense
    assert map_node_proc.alive()


def test_bad_input_does_not_kill_the_node(map_node_proc: NodeProcess, harness: Harness,
                                          landmarks) -> None:
    late = harness.record(PointCloud2, 'map_points', LATE_QOS)
    assert harness.spin_until(lambda: landmarks.get_subscription_count() > 0, 15.0)
    assert harness.spin_until(lambda: bool(late), 10.0), 'no initial (empty) map'
    assert late[-1].width == 0

    no_id = landmarks_msg([4], [[1.0, 2.0, 3.0]], fields=('n_obs',))
    truncated = landmarks_msg([5], [[1.0, 2.0, 3.0]])
    truncated.data = truncated.data[:-3]
    wrong_frame = landmarks_msg([6], [[1.0, 2.0, 3.0]], frame='camera_optical')
    for msg in (no_id, truncated, wrong_frame):
        landmarks.publish(msg)
    # Then a good one: it must still be processed.
    landmarks.publish(landmarks_msg([8], [[0.0, 1.0, 2.0]], n_obs=[4]))
    expected = {8: ((0.0, 1.0, 2.0), 4)}
    assert harness.spin_until(matches(late, expected), 10.0), 'good input after bad ignored'
    assert_map(late[-1], expected)

    assert map_node_proc.alive(), 'map_node died on bad input'
    assert clear_map(harness).success, 'map_node stopped answering'

    assert map_node_proc.stop() == 0        # SIGINT: a clean exit
    text = map_node_proc.output()
    # Three bad messages within 5 s: one throttled warning, naming the first problem.
    assert text.count('dropped bad message') == 1, text
    assert "missing field(s) ['id']" in text, text


def test_bad_parameter_exits_nonzero(domain_id: int) -> None:
    result = subprocess.run(
        [sys.executable, '-m', 'ekf_vo.ros.map_node', '--ros-args',
         '-p', 'publish_rate_hz:=500.0'],
        env=ros_env(domain_id), capture_output=True, text=True, timeout=20)
    assert result.returncode == 1
    assert 'invalid parameters' in result.stderr and 'publish_rate_hz' in result.stderr

"""map_node in its own process over real DDS: upsert/delete by id, latched map, ~/clear,
bad input survival, exit code on bad parameters."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from ekf_vo.ros.conversions import pointcloud2_to_numpy, points_to_pointcloud2

pytestmark = pytest.mark.ros

#: One DDS domain per test module (50..99) so parallel test runs do not cross-talk.
DOMAIN_ID = 50 + zlib.crc32(__name__.rpartition('.')[2].encode()) % 50
#: Per-run namespace: two runs of this module at once (same domain) must not cross-talk.
NAMESPACE = f'/t{os.getpid()}_{uuid.uuid4().hex[:6]}'
ROOT = Path(__file__).resolve().parents[1]
STAMP0 = 1_700_000_000_000_000_000

LANDMARKS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                           reliability=ReliabilityPolicy.RELIABLE)
LATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _env() -> dict[str, str]:
    return dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1')


@pytest.fixture
def map_node_proc(tmp_path: Path):
    """map_node as a subprocess at 5 Hz; yields (Popen, stderr log path); stopped with SIGINT."""
    log = tmp_path / 'map_node.log'
    with open(log, 'wb') as out:
        proc = subprocess.Popen(
            [sys.executable, '-m', 'ekf_vo.ros.map_node',
             '--ros-args', '-r', f'__ns:={NAMESPACE}', '-p', 'publish_rate_hz:=5.0'],
            cwd=ROOT, env=_env(), stdout=out, stderr=subprocess.STDOUT)
    try:
        yield proc, log
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


class Harness:
    """A test-side node and executor with polling helpers."""

    def __init__(self, context: Context) -> None:
        self.node = Node('map_node_test', namespace=NAMESPACE, context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.landmarks = self.node.create_publisher(PointCloud2, 'landmarks', LANDMARKS_QOS)

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return predicate()

    def subscribe_map(self, qos: QoSProfile) -> list[PointCloud2]:
        received: list[PointCloud2] = []
        self.node.create_subscription(PointCloud2, 'map_points', received.append, qos)
        return received

    def clear(self, timeout_s: float = 10.0) -> Trigger.Response:
        client = self.node.create_client(Trigger, f'{NAMESPACE}/map_node/clear')
        assert self.spin_until(client.service_is_ready, timeout_s), '~/clear not available'
        future = client.call_async(Trigger.Request())
        assert self.spin_until(future.done, timeout_s), '~/clear did not answer'
        return future.result()

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def harness(context: Context):
    h = Harness(context)
    yield h
    h.close()


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


def test_map_upsert_delete_late_joiner_and_clear(map_node_proc, harness: Harness) -> None:
    proc, _ = map_node_proc
    early = harness.subscribe_map(QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    assert harness.spin_until(lambda: harness.landmarks.get_subscription_count() > 0, 15.0), \
        'map_node did not subscribe to landmarks'

    harness.landmarks.publish(landmarks_msg(
        [1, 2, 3], [[1.0, 0.0, 2.0], [0.5, -0.5, 3.0], [-1.0, 0.25, 4.0]], n_obs=[2, 2, 3]))
    harness.landmarks.publish(landmarks_msg(          # update id 2, add id 7
        [2, 7], [[0.6, -0.4, 3.1], [2.0, 2.0, 5.0]], n_obs=[5, 2], stamp_ns=STAMP0 + 10**8))
    harness.landmarks.publish(landmarks_msg(          # delete id 3 (xyz NaN is allowed)
        [3], [[np.nan] * 3], n_obs=[0], removed=[1], stamp_ns=STAMP0 + 2 * 10**8))
    expected = {1: ((1.0, 0.0, 2.0), 2), 2: ((0.6, -0.4, 3.1), 5), 7: ((2.0, 2.0, 5.0), 2)}

    # The volatile subscriber sees the map converge: all three updates were applied.
    assert harness.spin_until(matches(early, expected), 10.0), \
        f'map never reached ids {sorted(expected)}; got {[m.width for m in early]}'
    assert_map(early[-1], expected)
    assert early[-1].header.stamp.sec == (STAMP0 + 2 * 10**8) // 10**9

    # A subscriber created after everything was published gets exactly the last map.
    late = harness.subscribe_map(LATE_QOS)
    assert harness.spin_until(lambda: bool(late), 10.0), 'late joiner got no map_points'
    assert_map(late[0], expected)

    # Nothing changes -> nothing is republished (the rate is 5 Hz; wait > 2 periods).
    n_before = len(late)
    harness.spin_until(lambda: False, 0.6)
    assert len(late) == n_before

    response = harness.clear()
    assert response.success and '3' in response.message
    assert harness.spin_until(lambda: len(late) > n_before and late[-1].width == 0, 10.0)
    assert late[-1].header.frame_id == 'odom' and late[-1].is_dense
    assert proc.poll() is None


def test_bad_input_does_not_kill_the_node(map_node_proc, harness: Harness) -> None:
    proc, log = map_node_proc
    late = harness.subscribe_map(LATE_QOS)
    assert harness.spin_until(lambda: harness.landmarks.get_subscription_count() > 0, 15.0)
    assert harness.spin_until(lambda: bool(late), 10.0), 'no initial (empty) map'
    assert late[-1].width == 0

    no_id = landmarks_msg([4], [[1.0, 2.0, 3.0]], fields=('n_obs',))
    truncated = landmarks_msg([5], [[1.0, 2.0, 3.0]])
    truncated.data = truncated.data[:-3]
    wrong_frame = landmarks_msg([6], [[1.0, 2.0, 3.0]], frame='camera_optical')
    for msg in (no_id, truncated, wrong_frame):
        harness.landmarks.publish(msg)
    # Then a good one: it must still be processed.
    harness.landmarks.publish(landmarks_msg([8], [[0.0, 1.0, 2.0]], n_obs=[4]))
    expected = {8: ((0.0, 1.0, 2.0), 4)}
    assert harness.spin_until(matches(late, expected), 10.0), 'good input after bad ignored'
    assert_map(late[-1], expected)

    assert proc.poll() is None, 'map_node died on bad input'
    assert harness.clear().success, 'map_node stopped answering'

    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 0
    text = log.read_text(errors='replace')
    # Three bad messages within 5 s: one throttled warning, naming the first problem.
    assert text.count('dropped bad message') == 1, text
    assert "missing field(s) ['id']" in text, text


def test_bad_parameter_exits_nonzero() -> None:
    result = subprocess.run(
        [sys.executable, '-m', 'ekf_vo.ros.map_node', '--ros-args',
         '-p', 'publish_rate_hz:=500.0'],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=20)
    assert result.returncode == 1
    assert 'invalid parameters' in result.stderr and 'publish_rate_hz' in result.stderr

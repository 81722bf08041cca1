"""ekf_vo.ros.player over real DDS: all messages arrive with their stamps, /clock follows the
bag (also through a use_sim_time node), topic filter/remap, loop + stop, and the CLI."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image

from ekf_vo.bridge import image_to_numpy, stamp_to_ns
from ekf_vo.ros.harness import Harness, ros_env
from ekf_vo.io import bag as bagio
from ekf_vo.ros.player import PlayError, parse_remaps, play_bag, resolve_msg_class

pytestmark = pytest.mark.ros

#: Per-run topic prefix: two runs of this module at once (same domain) must not cross-talk.
RUN = f'/t{os.getpid()}_{uuid.uuid4().hex[:6]}'
IMAGE_TOPIC = f'{RUN}/cam/image_raw'
INFO_TOPIC = f'{RUN}/cam/camera_info'
CLOCK_TOPIC = f'{RUN}/clock'
N_FRAMES = 10
STAMP0 = 1_700_000_000_000_000_000
PERIOD_NS = 50_000_000
STAMPS = [STAMP0 + i * PERIOD_NS for i in range(N_FRAMES)]
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
K = np.array([[100.0, 0.0, 16.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp('play') / 'bag'
    with bagio.BagWriter(path) as writer:
        for i, stamp in enumerate(STAMPS):
            img = np.full((24, 32), i * 10, dtype=np.uint8)
            writer.add_image(IMAGE_TOPIC, img, stamp, 'cam_optical')
            writer.add_camera_info(INFO_TOPIC, 32, 24, K, [0.0] * 5, 'plumb_bob',
                                   stamp, 'cam_optical')
    return path


def play_in_thread(context: Context, bag: Path, **kwargs: Any
                   ) -> tuple[threading.Thread, dict, Node]:
    """play_bag from its own node in a background thread; result lands in the dict."""
    player = Node('player', context=context)
    result: dict = {}

    def run() -> None:
        try:
            result.update(play_bag(player, bag, **kwargs))
        except Exception as exc:  # noqa: BLE001 - reported by the test
            result['error'] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, result, player


def test_all_images_with_stamps_and_clock(context: Context, harness: Harness,
                                          bag: Path) -> None:
    images = harness.record(Image, IMAGE_TOPIC, RELIABLE)
    infos = harness.record(CameraInfo, INFO_TOPIC, qos_profile_sensor_data)
    clocks = harness.record(Clock, CLOCK_TOPIC, RELIABLE)
    # A node on sim time (rclpy's TimeSource subscribes /clock best effort, depth 1).
    sim = Node('sim_time_node', context=context,
               cli_args=['--ros-args', '-r', f'/clock:={CLOCK_TOPIC}'],
               parameter_overrides=[Parameter('use_sim_time', value=True)])
    harness.executor.add_node(sim)
    thread, result, player = play_in_thread(context, bag, rate=2.0, start_paused_s=0.2,
                                            wait_for=['*'], remap={'/clock': CLOCK_TOPIC})
    try:
        assert harness.spin_until(lambda: len(images) >= N_FRAMES and 'messages' in result,
                                   15.0), f'got {len(images)} images; {result}'
        thread.join(5.0)
        assert 'error' not in result, result.get('error')
        assert [stamp_to_ns(m.header.stamp) for m in images] == STAMPS
        assert [int(image_to_numpy(m)[0, 0]) for m in images] == [i * 10 for i in range(10)]
        assert images[0].header.frame_id == 'cam_optical'

        assert harness.spin_until(lambda: len(infos) >= N_FRAMES, 5.0)
        assert [stamp_to_ns(m.header.stamp) for m in infos] == STAMPS
        np.testing.assert_allclose(np.asarray(infos[0].k).reshape(3, 3), K)

        assert harness.spin_until(lambda: len(clocks) >= 2 * N_FRAMES, 5.0)  # one per message
        harness.spin_until(lambda: False, 0.2)           # no extra ones arrive
        clock_ns = [stamp_to_ns(m.clock) for m in clocks]
        assert len(clock_ns) == 2 * N_FRAMES
        assert clock_ns == sorted(clock_ns) and clock_ns[0] == STAMP0
        assert clock_ns[-1] == STAMPS[-1]
        assert harness.spin_until(
            lambda: sim.get_clock().now().nanoseconds == STAMPS[-1], 5.0), \
            f'sim time {sim.get_clock().now().nanoseconds} != {STAMPS[-1]}'

        assert result['messages'] == 2 * N_FRAMES and result['loops'] == 1
        assert result['per_topic'] == {IMAGE_TOPIC: 10, INFO_TOPIC: 10}
        assert result['bag_duration_s'] == pytest.approx((STAMPS[-1] - STAMP0) / 1e9)
        # Paced at rate 2: 0.45 s of bag in about 0.225 s of wall time.
        assert 0.2 <= result['wall_s'] < 1.5
        assert not result['stopped'] and result['unmatched'] == []
    finally:
        thread.join(5.0)
        harness.executor.remove_node(sim)
        sim.destroy_node()
        player.destroy_node()


def test_topic_filter_remap_loop_and_stop(context: Context, harness: Harness,
                                          bag: Path) -> None:
    infos = harness.record(CameraInfo, f'{RUN}/other/info', RELIABLE)
    images = harness.record(Image, IMAGE_TOPIC, RELIABLE)
    clocks = harness.record(Clock, CLOCK_TOPIC, RELIABLE)
    stop = threading.Event()
    thread, result, player = play_in_thread(
        context, bag, rate=5.0, topics=[INFO_TOPIC.lstrip('/')],    # relative name works too
        remap=parse_remaps([f'{INFO_TOPIC}:={RUN}/other/info', f'/clock:={CLOCK_TOPIC}']),
        loop=True, stop_event=stop, start_paused_s=0.2, wait_for=[f'{RUN}/other/info'])
    try:
        # More than one pass: the loop restarted (and the clock went back to the start).
        assert harness.spin_until(lambda: len(infos) >= N_FRAMES + 3, 15.0), len(infos)
        stop.set()
        thread.join(5.0)
        assert not thread.is_alive(), 'play_bag did not honour stop_event'
        assert 'error' not in result, result.get('error')
        assert result['stopped'] and result['loops'] >= 2
        assert images == []
        stamps = [stamp_to_ns(m.header.stamp) for m in infos]
        assert stamps[:N_FRAMES + 1] == STAMPS + [STAMP0]
        clock_ns = [stamp_to_ns(m.clock) for m in clocks]
        assert any(b < a for a, b in zip(clock_ns, clock_ns[1:])), 'clock never jumped back'
    finally:
        stop.set()
        thread.join(5.0)
        player.destroy_node()


def test_errors_and_type_resolution(context: Context, tmp_path: Path, bag: Path) -> None:
    assert resolve_msg_class('sensor_msgs/msg/Image') is Image
    assert resolve_msg_class('sensor_msgs/Image') is Image
    with pytest.raises(PlayError):
        resolve_msg_class('no_such_pkg/msg/Thing')
    with pytest.raises(PlayError):
        parse_remaps(['/a=/b'])
    node = Node('player_errors', context=context)
    try:
        with pytest.raises(PlayError, match='does not exist'):
            play_bag(node, tmp_path / 'missing')
        with pytest.raises(PlayError, match='rate'):
            play_bag(node, bag, rate=0.0)
        with pytest.raises(PlayError, match='no playable topic'):
            play_bag(node, bag, topics=['/not/there'])
        with pytest.raises(PlayError, match='not played'):
            play_bag(node, bag, topics=[IMAGE_TOPIC], wait_for=[INFO_TOPIC])
        # Publishers created before the error are destroyed again.
        names = [n for n, _ in node.get_publisher_names_and_types_by_node('player_errors', '/')]
        assert not [n for n in names if n.startswith(RUN)], names
    finally:
        node.destroy_node()


def test_console_script(harness: Harness, bag: Path, domain_id: int) -> None:
    images = harness.record(Image, f'{RUN}/remapped/image', RELIABLE)
    clocks = harness.record(Clock, CLOCK_TOPIC, RELIABLE)
    proc = subprocess.Popen(
        [sys.executable, '-m', 'ekf_vo.ros.player', str(bag), '--rate', '4',
         '--remap', f'{IMAGE_TOPIC}:={RUN}/remapped/image', f'/clock:={CLOCK_TOPIC}',
         '--no-clock',
         # Cross-process discovery here can take > 3 s: wait for the match, not a fixed time.
         '--wait-for', f'{RUN}/remapped/image', '--wait-timeout-s', '15',
         '--start-paused-s', '0.3'],
        env=ros_env(domain_id), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert harness.spin_until(lambda: len(images) >= N_FRAMES, 25.0), \
            [stamp_to_ns(m.header.stamp) for m in images]
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert [stamp_to_ns(m.header.stamp) for m in images] == STAMPS
        assert 'played 20 messages on 2 topics' in out, out
        assert 'effective rate' in out
        assert clocks == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

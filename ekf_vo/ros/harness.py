"""Drive real rclpy nodes over DDS from a test, a benchmark or the demo (no mocks): node
processes, a driver node with polling and recording, a frame feeder, and the one DDS
domain-id scheme (a domain per test module or benchmark)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

#: Domain ids handed out by domain_id_for: 1..101. 0 is every robot's default; ids above
#: 101 use ports in Linux's ephemeral range (ROS 2 docs, "The ROS_DOMAIN_ID").
DOMAIN_ID_FIRST, DOMAIN_ID_COUNT = 1, 101


def domain_id_for(name: str) -> int:
    """The DDS domain of a test module or benchmark (its module name; only the last dotted
    part counts): parallel runs of different modules mostly land on different domains.
    Two names can share one (it is a hash): tests that must not cross-talk with a second
    run of themselves also use a per-run namespace (test_map_node, test_play)."""
    return DOMAIN_ID_FIRST + zlib.crc32(name.rpartition('.')[2].encode()) % DOMAIN_ID_COUNT


def ros_env(domain_id: int) -> dict[str, str]:
    """The environment of a child process on `domain_id` (unbuffered, so logs are live)."""
    return dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')


class NodeProcess:
    """A node started as its own process (`python -m module --ros-args ...`)."""

    def __init__(self, module: str, ros_args: list[str], domain_id: int, log: Path) -> None:
        self.log = log
        with open(log, 'wb') as out:
            self.proc = subprocess.Popen([sys.executable, '-m', module, '--ros-args',
                                          *ros_args], env=ros_env(domain_id), stdout=out,
                                         stderr=subprocess.STDOUT)

    def output(self) -> str:
        return self.log.read_text(errors='replace')

    def wait_for_output(self, text: str, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f'{text!r} not printed; output:\n{self.output()}')

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


class Harness:
    """A driver node with its own executor: polling, recording topics, calling services.

    Without `context` it initialises its own rclpy context on `domain_id` (and shuts it
    down on close); with one (e.g. the tests' `context` fixture) it joins it."""

    def __init__(self, domain_id: int | None = None, name: str = 'test_harness', *,
                 context: Context | None = None, **node_kwargs: Any) -> None:
        self._owns_context = context is None
        if context is None:
            os.environ['ROS_DOMAIN_ID'] = str(domain_id)
            context = Context()
            rclpy.init(context=context, domain_id=domain_id)
        self.context = context
        self.node = Node(name, context=context, **node_kwargs)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return condition()

    def spin_until_quiet(self, received: list, period_s: float = 0.5,
                         quiet_periods: int = 3) -> None:
        """Spin until `received` (a `record` list) has not grown for `quiet_periods`
        periods of `period_s`: the node under test has answered all it will."""
        n_last, quiet = -1, 0
        while quiet < quiet_periods:
            self.spin_for(period_s)
            quiet = quiet + 1 if len(received) == n_last else 0
            n_last = len(received)

    def record(self, msg_type: type, topic: str, qos: Any) -> list:
        """A new subscription on `topic`; returns the list its messages are appended to."""
        received: list = []
        self.node.create_subscription(msg_type, topic, received.append, qos)
        return received

    def call(self, srv_type: type, name: str, request: Any = None,
             timeout: float = 10.0) -> Any:
        """Call a service once it is available; returns the response."""
        client = self.node.create_client(srv_type, name)
        assert self.spin_until(client.service_is_ready, timeout), f'{name} not available'
        future = client.call_async(request if request is not None else srv_type.Request())
        assert self.spin_until(future.done, timeout), f'{name} did not answer'
        return future.result()

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown()
        self.node.destroy_node()
        if self._owns_context:
            rclpy.try_shutdown(context=self.context)


def encode(gray: np.ndarray, encoding: str) -> np.ndarray:
    """A grey frame as an array of the given sensor_msgs/Image encoding."""
    if encoding == 'mono8':
        return gray
    if encoding == 'mono16':
        return gray.astype(np.uint16) * 257
    rgb = np.dstack([gray] * 3)
    if encoding in ('rgba8', 'bgra8'):
        return np.dstack((rgb, np.full_like(gray, 255)))
    return rgb


class Feeder:
    """Publishes frames + CameraInfo at a rate and records vo_node's odometry and status.

    Records, per odometry message, the wall time it arrived, so publish-to-odometry
    latency can be measured end to end over DDS."""

    def __init__(self, h: Harness, info: dict, compressed: bool = False,
                 prefix: str = '/cam', reliable: bool = True) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        from ekf_vo import bridge as conv
        self.conv = conv
        self.h, self.info = h, info
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        pub_qos = qos if reliable else qos_profile_sensor_data
        n = h.node
        self.info_pub = n.create_publisher(CameraInfo, f'{prefix}/camera_info', pub_qos)
        self.img_pub = n.create_publisher(CompressedImage if compressed else Image,
                                          f'{prefix}/image/compressed' if compressed
                                          else f'{prefix}/image', pub_qos)
        self.odom: list = []
        self.odom_wall: dict[int, float] = {}
        self.sent_wall: dict[int, float] = {}
        self.status: list = []
        n.create_subscription(Odometry, '/odom', self._on_odom, qos)
        n.create_subscription(DiagnosticArray, '/vo_node/status', self.status.append, qos)

    def _on_odom(self, msg) -> None:
        self.odom.append(msg)
        self.odom_wall[self.conv.stamp_to_ns(msg.header.stamp)] = time.perf_counter()

    def wait_connected(self, timeout: float = 20.0) -> None:
        assert self.h.spin_until(lambda: self.img_pub.get_subscription_count() > 0
                                 and self.info_pub.get_subscription_count() > 0, timeout), \
            'vo_node did not subscribe'
        self.h.spin_for(0.3)

    def publish(self, frames, make_msg, rate_hz: float = 20.0, info_after: bool = False,
                make_info=None) -> list[int]:
        """Publish (stamp_ns, gray) frames; make_msg(k, stamp, gray) builds the image,
        make_info(k, stamp) its CameraInfo (default: the calibration, same stamp), sent
        before the image or, `info_after`, after it (image_transport's publisher order)."""
        stamps = []
        t_next = time.perf_counter()
        for k, (stamp, gray) in enumerate(frames):
            info = make_info(k, stamp) if make_info else self.camera_info(stamp)
            if not info_after:
                self.info_pub.publish(info)
            msg = make_msg(k, stamp, gray)
            self.sent_wall[stamp] = time.perf_counter()
            self.img_pub.publish(msg)
            if info_after:
                self.info_pub.publish(info)
            stamps.append(stamp)
            t_next += 1.0 / rate_hz
            while time.perf_counter() < t_next:
                self.h.executor.spin_once(timeout_sec=max(0.0, min(
                    0.005, t_next - time.perf_counter())))
        return stamps

    def camera_info(self, stamp: int):
        """The calibration as a CameraInfo stamped `stamp`."""
        return self.conv.camera_info_from_params(
            self.info['width'], self.info['height'], self.info['K'], self.info['D'],
            self.info['distortion_model'], stamp, 'camera_optical')

    def wait_last(self, stamp: int, timeout: float = 10.0) -> None:
        self.h.spin_until(lambda: stamp in self.odom_wall, timeout)

    def latencies_ms(self) -> np.ndarray:
        """Publish-to-odometry latency over DDS per frame that produced odometry."""
        return np.array([(self.odom_wall[s] - self.sent_wall[s]) * 1e3
                         for s in self.odom_wall if s in self.sent_wall])

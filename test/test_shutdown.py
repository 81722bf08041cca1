"""SIGINT and SIGTERM stop vo_node and ekf_vo_nodes cleanly while frames stream: within
1 s, exit code 0, nothing logged as an error (no publishing after the context went)."""
from __future__ import annotations

import signal
import time

import pytest

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames

pytestmark = pytest.mark.ros
DOMAIN = domain_id_for(__name__)
RATE_HZ = 30.0
#: frames published before the signal: idle (none yet), bootstrapping, tracking
STATES = {'idle': 0, 'bootstrapping': 4, 'tracking': 45}


@pytest.fixture(scope='module')
def demo():
    info, frames = load_demo_frames()
    return info, frames[:60]


@pytest.fixture(scope='module')
def harness():
    h = Harness(DOMAIN)
    yield h
    h.close()


def _raw(conv):
    return lambda k, stamp, gray: conv.numpy_to_image(gray, 'mono8', stamp, 'camera_optical')


@pytest.mark.parametrize('module', ['ekf_vo.ros.vo_node', 'ekf_vo.ros.run_all'])
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
@pytest.mark.parametrize('state', list(STATES))
def test_signal_stops_the_node_within_a_second(tmp_path, demo, harness, module, sig, state):
    info, frames = demo
    node = NodeProcess(module, ['-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
                                '-r', 'odom:=/odom', '-p', 'reliable_qos:=true'],
                       DOMAIN, tmp_path / 'node.log')
    try:
        node.wait_for_output('vo_node ready')
        feed = Feeder(harness, info)
        feed.wait_connected()
        n = STATES[state]
        make = _raw(feed.conv)
        feed.publish(frames[:n], make, RATE_HZ)
        node.proc.send_signal(sig)
        t_signal = time.monotonic()
        # frames keep streaming while the node stops
        feed.publish(frames[n:n + 6], make, RATE_HZ)
        code = node.proc.wait(timeout=max(0.05, 1.0 - (time.monotonic() - t_signal)))
        elapsed = time.monotonic() - t_signal
    finally:
        node.stop()
    out = node.output()
    assert code == 0, out
    assert elapsed <= 1.0, f'stopped after {elapsed:.2f} s'
    for bad in ('[ERROR]', '[FATAL]', 'Traceback', 'context is invalid'):
        assert bad not in out, out

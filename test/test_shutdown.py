"""SIGINT and SIGTERM stop vo_node and ekf_vo_nodes cleanly while frames stream: within
1 s, exit code 0, nothing logged as an error (no publishing after the context went)."""
from __future__ import annotations

import signal
import subprocess
import time

import pytest

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames

pytestmark = pytest.mark.ros
DOMAIN = domain_id_for(__name__)
RATE_HZ = 60.0
#: frames published before the signal: idle (none yet), bootstrapping, tracking
STATES = {'idle': 0, 'bootstrapping': 4, 'tracking': 45, 'first frames': 1}


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


#: runs per (executable, signal): the states cycle, so each is hit several times
RUNS = 20


def _stop_once(tmp_path, info, frames, harness, module, sig, n_before) -> tuple[int, float, str]:
    """Start the node, stream `n_before` frames, signal it while frames keep streaming.
    Returns (exit code, seconds from the signal to the exit, the node's output)."""
    node = NodeProcess(module, ['-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
                                '-r', 'odom:=/odom', '-p', 'reliable_qos:=true'],
                       DOMAIN, tmp_path / 'node.log')
    try:
        node.wait_for_output('vo_node ready')
        feed = Feeder(harness, info)
        feed.wait_connected()
        make = _raw(feed.conv)
        feed.publish(frames[:n_before], make, RATE_HZ)
        node.proc.send_signal(sig)
        t_signal = time.monotonic()
        feed.publish(frames[n_before:n_before + 6], make, RATE_HZ)    # still streaming
        try:
            code = node.proc.wait(timeout=max(0.05, 1.0 - (time.monotonic() - t_signal)))
        except subprocess.TimeoutExpired:
            code = None
        elapsed = time.monotonic() - t_signal
    finally:
        node.stop()
    return code, elapsed, node.output()


@pytest.mark.parametrize('module', ['ekf_vo.ros.vo_node', 'ekf_vo.ros.run_all'])
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_stops_the_node_within_a_second(tmp_path, demo, harness, module, sig):
    """20 runs, cycling over the states: idle, bootstrapping, tracking (and whatever frame
    the worker is in the middle of when the signal comes)."""
    info, frames = demo
    states = list(STATES.items())
    for run in range(RUNS):
        state, n_before = states[run % len(states)]
        run_dir = tmp_path / f'run{run}'
        run_dir.mkdir()
        code, elapsed, out = _stop_once(run_dir, info, frames, harness, module, sig, n_before)
        where = f'run {run} ({state})'
        assert code == 0, f'{where}: exit code {code}\n{out}'
        assert elapsed <= 1.0, f'{where}: stopped after {elapsed:.2f} s'
        for bad in ('[ERROR]', '[FATAL]', 'Traceback', 'context is invalid'):
            assert bad not in out, f'{where}:\n{out}'

"""Latency of vo_node: image published -> odometry received, at 30 Hz 640x480 input.

vo_node runs in its own process with its default (sensor-data) QoS; this process plays
the demo bag's frames as mono8 Images at 30 Hz like a camera driver and times, per frame,
the publish-to-odometry delay over DDS (end to end) and reads the node's own
receive-to-publish figures from ~/status.

    python -m bench.latency [--frames 300] [--rate 30]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames
from .common import machine

DOMAIN = domain_id_for(__name__)


def measure(frames: int = 300, rate_hz: float = 30.0) -> dict:
    info, all_frames = load_demo_frames()
    frames_used = all_frames[:frames]
    with tempfile.TemporaryDirectory() as tmp:
        vo = NodeProcess('ekf_vo.ros.vo_node', [
            '-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
            '-r', 'odom:=/odom'], DOMAIN, Path(tmp) / 'vo_node.log')
        vo.wait_for_output('vo_node ready')
        h = Harness(DOMAIN, 'latency_bench')
        try:
            from ekf_vo import bridge as conv
            feed = Feeder(h, info, reliable=False)
            feed.wait_connected()
            stamps = feed.publish(frames_used, lambda k, s, g: conv.numpy_to_image(
                g, 'mono8', s, 'camera_optical'), rate_hz)
            feed.wait_last(stamps[-1], 5.0)
            h.spin_for(1.0)
            lat = feed.latencies_ms()
            status = {kv.key: kv.value for kv in feed.status[-1].status[0].values} \
                if feed.status else {}
        finally:
            h.close()
            vo.stop()
    n_odom = len(feed.odom_wall)
    return {'frames_sent': len(stamps), 'odometry_received': n_odom,
            'rate_hz': rate_hz, 'resolution': f'{info["width"]}x{info["height"]}',
            'e2e_p50_ms': float(np.percentile(lat, 50)), 'e2e_p95_ms':
            float(np.percentile(lat, 95)), 'e2e_max_ms': float(lat.max()),
            'node_p50_ms': float(status.get('latency_p50_ms', 'nan')),
            'node_p95_ms': float(status.get('latency_p95_ms', 'nan')),
            'dropped_behind': int(status.get('dropped_behind', 0)),
            'node_fps': float(status.get('fps', 'nan')), 'machine': machine()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=300)
    parser.add_argument('--rate', type=float, default=30.0)
    args = parser.parse_args(argv)
    r = measure(args.frames, args.rate)
    print(f'machine: {r["machine"]}; {r["frames_sent"]} frames {r["resolution"]} at '
          f'{r["rate_hz"]:.0f} Hz, {r["odometry_received"]} odometry messages')
    print(f'publish -> odometry over DDS: p50 {r["e2e_p50_ms"]:.1f} ms, p95 '
          f'{r["e2e_p95_ms"]:.1f} ms, max {r["e2e_max_ms"]:.1f} ms')
    print(f'inside vo_node (receive -> publish): p50 {r["node_p50_ms"]:.1f} ms, p95 '
          f'{r["node_p95_ms"]:.1f} ms; dropped (behind) {r["dropped_behind"]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Latency of vo_node: image published -> odometry received over DDS, with drop counts.

vo_node runs in its own process with its default (sensor-data) QoS and, by default,
map_node beside it in another process (subscribed to vo_node's ``landmarks``, publishing
``map_points``, which this bench records to show map_node really receives and works). This
process plays a sequence's frames as mono8 Images like a camera driver and times, per frame,
the publish-to-odometry delay over DDS (end to end); it reads the node's own
receive-to-publish figures and its counters (received / processed / published /
dropped_behind / rejections) from ~/status.

Sequences: ``demo`` = the bundled demo bag, 640x480, 30 Hz (300 frames); ``kitti`` =
KITTI 06 f0-50 from ../shared/data, 1226x370, 10 Hz (51 frames; skipped with a message
when absent). Each frame is sent once, in order (no looping: a jump back to frame 0 would
reset the estimator). Targets (p95): < 20 ms for demo at 30 Hz, < 30 ms for kitti at 10 Hz.

    python -m bench.latency [--sequence demo|kitti] [--frames N] [--rate HZ]
                            [--map-node | --no-map-node] [--json PATH]

`measure()` (used by bench.throughput) keeps its old defaults: demo, 300 frames, 30 Hz,
no map_node.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames
from .common import machine, write_json

DOMAIN = domain_id_for(__name__)
#: per sequence: default rate [Hz] and the issue's p95 target [ms] at that rate
SEQUENCES = {'demo': (30.0, 20.0), 'kitti': (10.0, 30.0)}
#: vo_node's counters on ~/status that say what happened to the frames it was sent
COUNTER_KEYS = ('received', 'processed', 'published', 'dropped_behind', 'duplicate_stamp',
                'out_of_order', 'future_stamp', 'bad_image', 'time_resets',
                'internal_errors')


def load_sequence(sequence: str) -> tuple[dict, list] | str:
    """(camera info, [(stamp_ns, gray)]) of `sequence`, or why it is unavailable."""
    if sequence == 'demo':
        return load_demo_frames()
    if sequence == 'kitti':
        from .speed import load_kitti_frames
        kitti = load_kitti_frames()
        return kitti if kitti is not None else \
            'kitti skipped: ../shared/data/kitti06_f0-50 is absent'
    raise ValueError(f'unknown sequence {sequence!r}; known: {sorted(SEQUENCES)}')


def _start_nodes(tmp: Path, with_map_node: bool) -> dict[str, NodeProcess]:
    """vo_node (and map_node on vo_node's landmarks) as processes, ready."""
    nodes = {'vo_node': NodeProcess('ekf_vo.ros.vo_node', [
        '-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
        '-r', 'odom:=/odom', '-r', 'landmarks:=/landmarks'], DOMAIN, tmp / 'vo_node.log')}
    if with_map_node:
        nodes['map_node'] = NodeProcess('ekf_vo.ros.map_node', [
            '-r', 'landmarks:=/landmarks', '-r', 'map_points:=/map_points'],
            DOMAIN, tmp / 'map_node.log')
    try:
        nodes['vo_node'].wait_for_output('vo_node ready')
        if with_map_node:
            nodes['map_node'].wait_for_output('map_node: landmarks -> map_points')
    except AssertionError:
        for node in nodes.values():
            node.stop()
        raise
    return nodes


def _log_warnings(text: str, limit: int = 5) -> list[str]:
    """The first `limit` WARN / ERROR lines of a node's log."""
    return [line.strip() for line in text.splitlines()
            if '[WARN]' in line or '[ERROR]' in line][:limit]


def _play(frames: list, info: dict, rate_hz: float, with_map_node: bool) -> dict:
    """Start the nodes, play `frames`, collect what came back (raw)."""
    from sensor_msgs.msg import PointCloud2
    from ekf_vo import bridge as conv
    from ekf_vo.ros.map_node import MAP_QOS
    with tempfile.TemporaryDirectory() as tmp:
        nodes = _start_nodes(Path(tmp), with_map_node)
        h = Harness(DOMAIN, 'latency_bench')
        try:
            clouds = h.record(PointCloud2, '/map_points', MAP_QOS)
            feed = Feeder(h, info, reliable=False)
            feed.wait_connected()
            if with_map_node:    # map_node on /landmarks, its latched start-up map here
                assert h.spin_until(lambda: h.node.count_subscribers('/landmarks') > 0
                                    and clouds, 20.0), 'map_node not connected'
            stamps = feed.publish(frames, lambda k, s, g: conv.numpy_to_image(
                g, 'mono8', s, 'camera_optical'), rate_hz)
            feed.wait_last(stamps[-1], 5.0)
            h.spin_for(2.5 if with_map_node else 1.0)   # map_node publishes at 1 Hz
            alive = {name: node.alive() for name, node in nodes.items()}
        finally:
            h.close()
            codes = {name: node.stop() for name, node in nodes.items()}
        logs = {name: _log_warnings(node.output()) for name, node in nodes.items()}
    return {'feed': feed, 'stamps': stamps, 'clouds': clouds, 'alive': alive,
            'exit_codes': codes, 'log_warnings': logs}


def _drops(feed: Feeder, stamps: list[int]) -> dict:
    """Frames sent vs odometry, and vo_node's counters from its last ~/status (published
    at most twice a second, so it may not cover the last few frames: `status_covers`)."""
    odom = set(feed.odom_wall)
    first = min(odom) if odom else None
    res = {'frames_sent': len(stamps), 'odometry_received': len(odom),
           'dropped': len(stamps) - len(odom),
           'no_odometry_after_first': sum(1 for s in stamps if first is not None
                                          and s >= first and s not in odom),
           # which frames (0-based, in the order sent): where the node fell behind
           'missing_after_first_frames': [k for k, s in enumerate(stamps) if first is not None
                                          and s >= first and s not in odom]}
    if not feed.status:
        return dict(res, node_counters={}, status_covers=0, status={})
    last = feed.status[-1]
    status = {kv.key: kv.value for kv in last.status[0].values}
    stamp = feed.conv.stamp_to_ns(last.header.stamp)
    counters = {k: int(status.get(k, 0)) for k in COUNTER_KEYS}
    return dict(res, node_counters=counters, status=status,
                status_covers=sum(1 for s in stamps if s <= stamp),
                dropped_behind=counters['dropped_behind'])


def _map_summary(clouds: list, with_map_node: bool) -> dict:
    if not with_map_node:
        return {'map_node': False}
    widths = [int(c.width) * int(c.height) for c in clouds]
    return {'map_node': True, 'map_clouds_received': len(clouds),
            'map_clouds_nonempty': sum(1 for w in widths if w > 0),
            'map_points_final': widths[-1] if widths else 0}


def measure(frames: int | None = 300, rate_hz: float | None = None,
            sequence: str = 'demo', map_node: bool = False) -> dict:
    """Play `frames` (None: all) of `sequence` at `rate_hz` (None: the sequence's rate)
    to vo_node (with map_node beside it when `map_node`); returns the result dict, or
    {'skipped': why} when the sequence's data is absent."""
    loadavg = os.getloadavg()
    loaded = load_sequence(sequence)
    if isinstance(loaded, str):
        return {'skipped': loaded, 'sequence': sequence}
    info, all_frames = loaded
    default_rate, target = SEQUENCES[sequence]
    rate = default_rate if rate_hz is None else rate_hz
    raw = _play(all_frames[:frames], info, rate, map_node)
    feed = raw['feed']
    lat = feed.latencies_ms()
    if lat.size == 0:
        lat = np.array([np.nan])
    res = {'sequence': sequence, 'rate_hz': rate,
           'resolution': f'{info["width"]}x{info["height"]}',
           'e2e_p50_ms': float(np.percentile(lat, 50)),
           'e2e_p95_ms': float(np.percentile(lat, 95)), 'e2e_max_ms': float(np.max(lat)),
           'e2e_samples': int(np.isfinite(lat).sum()),
           'target_p95_ms': target if rate == default_rate else None,
           'dropped_behind': 0, 'machine': machine(),
           'loadavg_start': [round(x, 2) for x in loadavg]}
    res.update(_drops(feed, raw['stamps']))
    status = res.pop('status')
    res.update({'node_p50_ms': float(status.get('latency_p50_ms', 'nan')),
                'node_p95_ms': float(status.get('latency_p95_ms', 'nan')),
                'node_fps': float(status.get('fps', 'nan')),
                'vo_map_points': int(status.get('map_points', 0)),
                'node_alive_at_end': raw['alive'], 'node_exit_codes': raw['exit_codes'],
                'node_log_warnings': raw['log_warnings']})
    res.update(_map_summary(raw['clouds'], map_node))
    return res


def report(r: dict) -> None:
    """Print a result of measure()."""
    if 'skipped' in r:
        print(r['skipped'])
        return
    print(f'machine: {r["machine"]}; load average at start '
          f'{", ".join(f"{x:.2f}" for x in r["loadavg_start"])}')
    print(f'{r["sequence"]}: {r["frames_sent"]} frames {r["resolution"]} at '
          f'{r["rate_hz"]:g} Hz, map_node beside: {"yes" if r["map_node"] else "no"}')
    target = r['target_p95_ms']
    verdict = '' if target is None else \
        f' (target p95 < {target:g} ms: {"met" if r["e2e_p95_ms"] < target else "NOT met"})'
    print(f'publish -> odometry over DDS ({r["e2e_samples"]} frames): p50 '
          f'{r["e2e_p50_ms"]:.1f} ms, p95 {r["e2e_p95_ms"]:.1f} ms, max '
          f'{r["e2e_max_ms"]:.1f} ms{verdict}')
    print(f'inside vo_node (receive -> publish): p50 {r["node_p50_ms"]:.1f} ms, p95 '
          f'{r["node_p95_ms"]:.1f} ms; {r["node_fps"]:.1f} frames/s')
    missing = r['missing_after_first_frames']
    print(f'frames: sent {r["frames_sent"]}, odometry {r["odometry_received"]}, sent - '
          f'odometry {r["dropped"]} (bootstrap frames give none; missing after the first '
          f'odometry: {r["no_odometry_after_first"]}{f", frames {missing}" if missing else ""}'
          f'; target: none {"met" if not missing else "NOT met"})')
    c = r['node_counters']
    other = {k: v for k, v in c.items() if v and k not in
             ('received', 'processed', 'published', 'dropped_behind')}
    print(f'vo_node ~/status (covers frames 1-{r["status_covers"]}): received '
          f'{c.get("received", 0)}, processed {c.get("processed", 0)}, published '
          f'{c.get("published", 0)}, dropped_behind {c.get("dropped_behind", 0)}, '
          f'rejected {other or "none"}')
    if r['map_node']:
        print(f'map_node: {r["map_clouds_received"]} map_points clouds received '
              f'({r["map_clouds_nonempty"]} non-empty), final map {r["map_points_final"]} '
              f'points (vo_node map at its last status: {r["vo_map_points"]})')
    dead = [n for n, ok in r['node_alive_at_end'].items() if not ok]
    if dead:
        print(f'note: exited before the end: {", ".join(dead)}')
    for name, lines in r['node_log_warnings'].items():
        if lines:
            print(f'{name} log: {len(lines)}{"+" if len(lines) >= 5 else ""} WARN/ERROR '
                  f'lines, first: {lines[0].split("]: ", 1)[-1][:90]}')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--sequence', choices=sorted(SEQUENCES), default='demo')
    parser.add_argument('--frames', type=int, default=None, help='default: all')
    parser.add_argument('--rate', type=float, default=None,
                        help='Hz; default 30 for demo, 10 for kitti')
    parser.add_argument('--map-node', action=argparse.BooleanOptionalAction, default=True,
                        help='run map_node beside vo_node (default: yes)')
    parser.add_argument('--json', type=Path, default=None, help='write the result here')
    args = parser.parse_args(argv)
    r = measure(args.frames, args.rate, args.sequence, args.map_node)
    report(r)
    if args.json is not None:
        write_json(args.json, r)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Soak: vo_node + map_node (one process) fed N synthetic frames over DDS.

The demo bag's 300 frames are played forwards then backwards (ping-pong: continuous
motion with a sharp reversal at each end) with ever-increasing stamps, so the estimator
keeps tracking, losing and re-bootstrapping for as long as asked. Every `--sample` frames
it records the node process's resident memory (/proc/PID/status VmRSS), its frames/s,
map size and counters from ~/status. Writes soak.json and soak.png; prints a summary.

    python -m bench.soak --frames 20000 --rate 60 --out bench/results/soak
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ekf_vo.ros.harness import Feeder, Harness, NodeProcess, domain_id_for
from ekf_vo.tools.demo import load_demo_frames
from .common import machine, pyplot, write_json

DOMAIN = domain_id_for(__name__)


def rss_mb(pid: int) -> float:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def soak(n_frames: int, rate_hz: float, out: Path, sample_every: int = 500) -> dict:
    from ekf_vo import bridge as conv
    info, frames = load_demo_frames()
    cycle = frames + frames[::-1][1:-1]
    dt = frames[1][0] - frames[0][0]
    out.mkdir(parents=True, exist_ok=True)
    node = NodeProcess('ekf_vo.ros.run_all', [
        '-r', 'image:=/cam/image', '-r', 'camera_info:=/cam/camera_info',
        '-r', 'odom:=/odom'], DOMAIN, out / 'nodes.log')
    node.wait_for_output('vo_node ready', 60.0)
    h = Harness(DOMAIN, 'soak')
    samples = []
    t0 = time.perf_counter()
    try:
        feed = Feeder(h, info, reliable=False)
        feed.wait_connected()
        stamp0 = frames[0][0]
        make = lambda k, s, g: conv.numpy_to_image(g, 'mono8', s, 'camera_optical')  # noqa
        sent = 0
        while sent < n_frames:
            n = min(sample_every, n_frames - sent)
            chunk = [(stamp0 + (sent + i) * dt, cycle[(sent + i) % len(cycle)][1])
                     for i in range(n)]
            feed.publish(chunk, make, rate_hz)
            sent += n
            status = {kv.key: kv.value for kv in feed.status[-1].status[0].values} \
                if feed.status else {}
            samples.append({'frames_sent': sent, 'rss_mb': rss_mb(node.proc.pid),
                            'wall_s': time.perf_counter() - t0,
                            'odometry': len(feed.odom_wall),
                            'node_fps': float(status.get('fps', 'nan')),
                            'map_points': int(status.get('map_points', 0)),
                            'resets': int(status.get('resets', 0)),
                            'dropped_behind': int(status.get('dropped_behind', 0)),
                            'internal_errors': int(status.get('internal_errors', 0))})
            feed.odom.clear()   # keep the driver's own memory flat
            print(f'[soak] {sent:6d} frames, RSS {samples[-1]["rss_mb"]:.1f} MB, '
                  f'fps {samples[-1]["node_fps"]:.1f}, map {samples[-1]["map_points"]}, '
                  f'resets {samples[-1]["resets"]}', flush=True)
        alive = node.alive()
    finally:
        h.close()
        node.stop()
    rss = np.array([s['rss_mb'] for s in samples])
    half = len(rss) // 2
    result = {'machine': machine(), 'frames': n_frames, 'rate_hz': rate_hz,
              'wall_s': time.perf_counter() - t0, 'alive_at_end': alive,
              'rss_first_mb': float(rss[0]), 'rss_last_mb': float(rss[-1]),
              'rss_max_mb': float(rss.max()),
              'rss_growth_second_half_mb': float(rss[-1] - rss[half]),
              'odometry_messages': int(samples[-1]['odometry']),
              'fps_min': float(np.nanmin([s['node_fps'] for s in samples])),
              'fps_max': float(np.nanmax([s['node_fps'] for s in samples])),
              'internal_errors': samples[-1]['internal_errors'], 'samples': samples}
    write_json(out / 'soak.json', result)
    _plot(samples, out / 'soak.png')
    return result


def _plot(samples: list, png: Path) -> None:
    plt = pyplot(png.parent)
    x = [s['frames_sent'] for s in samples]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    ax[0].plot(x, [s['rss_mb'] for s in samples])
    ax[0].set_title('vo_node + map_node RSS [MB]')
    ax[1].plot(x, [s['node_fps'] for s in samples])
    ax[1].set_title('estimator frames/s')
    ax[2].plot(x, [s['map_points'] for s in samples])
    ax[2].set_title('map points')
    for a in ax:
        a.set_xlabel('frames')
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--frames', type=int, default=20000)
    parser.add_argument('--rate', type=float, default=60.0)
    parser.add_argument('--out', type=Path, default=Path('bench/results/soak'))
    args = parser.parse_args(argv)
    r = soak(args.frames, args.rate, args.out)
    print(f'soak: {r["frames"]} frames at {r["rate_hz"]:.0f} Hz in {r["wall_s"]:.0f} s on '
          f'{r["machine"]}; alive: {r["alive_at_end"]}; RSS first/last/max '
          f'{r["rss_first_mb"]:.1f}/{r["rss_last_mb"]:.1f}/{r["rss_max_mb"]:.1f} MB '
          f'(second-half growth {r["rss_growth_second_half_mb"]:+.1f} MB); estimator fps '
          f'{r["fps_min"]:.1f}-{r["fps_max"]:.1f}; odometry {r["odometry_messages"]}; '
          f'internal errors {r["internal_errors"]}')
    return 0 if r['alive_at_end'] and r['internal_errors'] == 0 else 1


if __name__ == '__main__':
    sys.exit(main())

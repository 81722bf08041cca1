"""Speed of the core (frames/s, per-stage ms) and the ROS node's latency.

Wraps `speed.time_core` at 640x480 (the bundled demo bag, 300 frames) and 1226x370
(KITTI 06 f0-50, when ../shared/data is present), images decoded beforehand, best of
`repeat` passes; and `latency.measure` (vo_node in its own process, frames published at
30 Hz over DDS, publish -> odometry delay). The latency part needs ROS 2 (rclpy); it is
reported as skipped with the reason when it cannot run.

    python -m bench.throughput [--quick] [--out DIR]
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

from ekf_vo.tools.demo import load_demo_frames
from .common import machine, pyplot, section_main
from .speed import load_kitti_frames, time_core

logger = logging.getLogger(__name__)


def run(quick: bool = False, out: Path | None = None) -> dict:
    repeat = 1 if quick else 3
    import os
    res: dict = {'machine': machine(), 'repeat': repeat,
                 'loadavg': ', '.join(f'{x:.1f}' for x in os.getloadavg())}
    res['demo_640x480'] = time_core(*load_demo_frames(), repeat=repeat)
    kitti = load_kitti_frames()
    res['kitti_1226x370'] = time_core(*kitti, repeat=repeat) if kitti is not None else \
        {'skipped': '../shared/data/kitti06_f0-50 is absent'}
    # the speed issue's setting: a map_node beside vo_node, each in its own process
    for key, kwargs in (('latency', {'frames': 100 if quick else 300}),
                        ('latency_kitti', {'frames': None, 'sequence': 'kitti'})):
        try:
            from .latency import measure
            res[key] = measure(map_node=True, **kwargs)
        except Exception as exc:  # noqa: BLE001 - ROS missing or DDS trouble: report it
            logger.warning('latency measurement skipped: %s', exc)
            res[key] = {'skipped': f'{type(exc).__name__}: {exc}'}
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    runs = [(k, res[k]) for k in ('demo_640x480', 'kitti_1226x370') if 'fps' in res[k]]
    fig, ax = plt.subplots(figsize=(8, 4))
    stages = ['predict', 'track', 'update', 'top_up', 'map']
    for i, (name, r) in enumerate(runs):
        left = 0.0
        for st, c in zip(stages, ('tab:gray', 'tab:blue', 'tab:orange', 'tab:cyan',
                                  'tab:green')):
            w = r['stage_ms_mean'].get(st, 0.0)
            ax.barh(i, w, left=left, color=c, label=st if i == 0 else None)
            left += w
        other = r['stage_ms_mean']['total'] - left
        ax.barh(i, max(other, 0.0), left=left, color='tab:purple',
                label='other (bootstrap, output)' if i == 0 else None)
        ax.text(r['stage_ms_mean']['total'] + 0.3, i, f'{r["fps"]:.0f} frames/s', va='center')
    ax.set_yticks(range(len(runs)), [f'{n}' for n, _ in runs])
    ax.set(xlabel='mean ms per frame', title=f'core time per frame ({res["machine"]})')
    ax.legend(fontsize=8, loc='lower right')
    ax.grid(alpha=0.3, axis='x')
    fig.tight_layout()
    p = out / 'speed.png'
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return [p.name]


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'throughput')


if __name__ == '__main__':
    sys.exit(main())

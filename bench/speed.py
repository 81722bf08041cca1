"""Speed of the core: frames/s and per-stage milliseconds (images decoded beforehand).

640x480: the bundled demo bag (synthetic hand-held, 30 Hz). 1226x370: KITTI 06 f0-50 when
../shared/data is present. Times are wall-clock on this machine, single process.
``--detect-threads 1`` runs the corner detection in the calling thread only, as releases
before docs/method.md §17.8 did (the corners are the same; only the time differs).

    python -m bench.speed [--repeat 3] [--detect-threads 1] [--set NAME=VALUE ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core import features
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.demo import load_demo_frames
from .common import machine, overrides_or_report, shared_data

def load_kitti_frames() -> tuple[dict, list] | None:
    from ekf_vo.io.dataset import load_folder
    folder = shared_data('kitti06_f0-50')
    if folder is None:
        return None
    data = load_folder(folder)
    return data.camera, list(data.frames())


def time_core(info: dict, frames: list, cfg: VoConfig | None = None, repeat: int = 3
              ) -> dict:
    """Best-of-`repeat` frames/s and mean / p95 per-stage ms over the frames."""
    best = None
    for rep in range(repeat):
        stream = VoStream(cfg or VoConfig(), seed=rep)
        stream.set_camera(info)
        stages: dict[str, list] = {}
        t0 = time.perf_counter()
        for stamp, gray in frames:
            res = stream.process(gray, stamp)
            for key, ms in res.timings_ms.items():
                stages.setdefault(key, []).append(ms)
        wall = time.perf_counter() - t0
        fps = len(frames) / wall
        if best is None or fps > best['fps']:
            best = {'fps': fps, 'frames': len(frames),
                    'stage_ms_mean': {k: float(np.mean(v)) for k, v in stages.items()},
                    'stage_ms_p95': {k: float(np.percentile(v, 95)) for k, v in
                                     stages.items()}}
    best['resolution'] = f'{info["width"]}x{info["height"]}'
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--detect-threads', type=int, choices=(1, 2), default=2,
                        help='1: detection in the calling thread only (the release '
                        'before docs/method.md §17.8)')
    parser.add_argument('--set', nargs='+', default=[], metavar='NAME=VALUE',
                        help='configuration overrides (the defaults otherwise)')
    args = parser.parse_args(argv)
    overrides = overrides_or_report(args.set, 'bench.speed')
    if overrides is None:
        return 2
    cfg = dataclasses.replace(VoConfig(), **overrides).validate()
    if args.detect_threads == 1:
        features._PARALLEL_MIN_CELLS = sys.maxsize
    print(f'machine: {machine()}, detection on {args.detect_threads} thread(s)'
          + (f', overrides {overrides}' if overrides else ''))
    runs = [('demo bag', load_demo_frames())]
    kitti = load_kitti_frames()
    if kitti is not None:
        runs.append(('KITTI 06', kitti))
    for name, (info, frames) in runs:
        r = time_core(info, frames, cfg, repeat=args.repeat)
        stages = ', '.join(f'{k} {v:.1f}' for k, v in r['stage_ms_mean'].items()
                           if k != 'total')
        print(f'{name:<9} {r["resolution"]:>9}: {r["fps"]:6.1f} frames/s, total '
              f'{r["stage_ms_mean"]["total"]:.1f} ms mean / {r["stage_ms_p95"]["total"]:.1f} '
              f'ms p95; stages (mean ms): {stages}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

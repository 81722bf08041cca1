"""Where the time goes: per-stage milliseconds and the functions that cost most.

The speed issue's first step: before optimising anything, a profile of the core with
everything on (the defaults: local map and its adjustment thread included) at 640x480
(the bundled demo bag) and 1226x370 (KITTI 06 f0-50, when ../shared/data is present).
Images are decoded beforehand (bench.speed and ekf-vo-run measure the decode). Per
sequence: the mean / p95 of each pipeline stage (FrameResult.timings_ms, measured
without the profiler) and cProfile's top functions by internal time and by cumulative
time (measured in a second run: the profiler slows Python code ~2x, so its milliseconds
are for ranking, not for targets). The adjustment runs in a worker thread, which
cProfile does not see; its time is in `stage local_map` only as far as the frame loop
waits for it, and the worker's own time is printed from the local map's figures.

    python -m bench.profile_core [--top 15] [--out bench/results/profile.md]
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
from pathlib import Path


from ekf_vo.config import VoConfig
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.demo import load_demo_frames
from .common import machine
from .speed import load_kitti_frames, time_core


#: stages whose time is a part of another's
_STAGE_LABELS = {'detect': 'detect (a part of top_up; of track before the first map)',
                 'top_up': 'top_up (new corners, after the pose)',
                 'to_pose': 'to_pose (start of the frame to its final pose)'}


def _profile(info: dict, frames: list, top: int) -> tuple[str, str, dict]:
    """cProfile of one run: top functions by tottime and by cumtime, local-map figures."""
    stream = VoStream(VoConfig(), seed=0)
    stream.set_camera(info)
    prof = cProfile.Profile()
    prof.enable()
    for stamp, gray in frames:
        stream.process(gray, stamp)
    prof.disable()
    tables = []
    for key in ('tottime', 'cumulative'):
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).strip_dirs().sort_stats(key).print_stats(top)
        text = buf.getvalue()
        tables.append(text[text.find('ncalls'):].rstrip())
    return tables[0], tables[1], stream.local_map_stats()


def run(top: int) -> str:
    """The profile of both sequences as markdown."""
    runs = [('demo bag', load_demo_frames())]
    kitti = load_kitti_frames()
    if kitti is not None:
        runs.append(('KITTI 06 f0-50', kitti))
    parts = [f'# Profile of the core (python -m bench.profile_core)\n\nMachine: {machine()}; '
             'single process, images decoded beforehand, the defaults (local map on).\n']
    for name, (info, frames) in runs:
        t = time_core(info, frames, repeat=1)
        rows = '\n'.join(
            f'| {_STAGE_LABELS.get(k, k)} | {v:.2f} | {t["stage_ms_p95"][k]:.2f} |'
            for k, v in t['stage_ms_mean'].items())
        by_self, by_cum, lm = _profile(info, frames, top)
        parts.append(
            f'\n## {name}, {t["resolution"]}, {t["frames"]} frames: {t["fps"]:.1f} '
            f'frames/s\n\n| stage | mean ms | p95 ms |\n|---|---|---|\n{rows}\n\n'
            f'Adjustment worker (its own thread): {lm.get("ba_runs", 0)} runs, mean '
            f'{lm.get("ba_mean_ms", 0)} ms, max {lm.get("ba_max_ms", 0)} ms, the frame loop '
            f'waited {lm.get("ba_wait_ms_total", 0)} ms in total.\n\n'
            f'Top {top} functions by internal time (cProfile, for ranking):\n\n```\n{by_self}'
            f'\n```\n\nTop {top} by cumulative time:\n\n```\n{by_cum}\n```\n')
    return ''.join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--top', type=int, default=15)
    parser.add_argument('--out', type=Path, default=None, help='also write the markdown here')
    args = parser.parse_args(argv)
    text = run(args.top)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())

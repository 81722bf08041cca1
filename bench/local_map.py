"""KITTI 06 frames 0-50 through bags as a camera driver records them: does the result depend
on the message order or on JPEG, and what does the local map change?

Four bags are converted from the developers' ``kitti06_f0-50`` folder with ekf-vo-convert's
Python API: raw mono8 Image or JPEG (quality 75, what image_transport's ``compressed``
publisher records), each with the CameraInfo logged before its image (the converter's
default) or after it (a live camera publisher's order). Each bag is run offline
(:func:`ekf_vo.tools.run.run_bag`, the core's defaults plus ``--set`` overrides) once per
seed. Per run: the first frame with a pose (counting the processed images from 0), the frames
without a pose after it ("lost after first"), ATE after Sim(3) as % of the path, the mean
rotation error after that alignment ("rot"; loosely fixed on this almost straight drive, it
scatters by degrees between seeds), the mean rotation drift from the first pose ("drift",
the steadier figure) and the resets. The table gives, per bag, the mean / max ATE % over the
seeds, the worst first-pose frame and lost-after-first, and per image kind the spread
between the two orders (|mean ATE before - mean ATE after|): the order only decides when a
waiting first image is processed, so a spread well above the seed-to-seed scatter would be
a bug.

    python -m bench.local_map [--seeds 8] [--variants raw-before ...] [--set NAME=VALUE ...]
                              [--work DIR] [--json OUT]

e.g. ``--set local_map=true`` for the keyframe / windowed-adjustment local map.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .common import machine, shared_data, write_json

SEQUENCE = 'kitti06_f0-50'
JPEG_QUALITY = 75
#: bag name -> converter options (the image kind is the name's first part)
VARIANTS: dict[str, dict[str, Any]] = {
    'raw-before': {'jpeg_quality': None, 'info_after_image': False},
    'raw-after': {'jpeg_quality': None, 'info_after_image': True},
    'jpeg-before': {'jpeg_quality': JPEG_QUALITY, 'info_after_image': False},
    'jpeg-after': {'jpeg_quality': JPEG_QUALITY, 'info_after_image': True},
}


class BenchError(ValueError):
    """Bad options or missing data: one line, exit 2."""


def build_bags(folder: Path, work: Path, variants: Sequence[str]) -> dict[str, Path]:
    """Convert ``folder`` (KITTI layout) once per variant into ``work/<variant>``; a bag of
    that name left by an earlier ``--work`` run is replaced (it may predate a converter
    change)."""
    from ekf_vo.tools.convert import convert
    bags = {}
    for name in variants:
        bags[name] = work / name
        convert('kitti', folder, bags[name], overwrite=True, **VARIANTS[name])
    return bags


def run_one(bag: Path, overrides: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """One offline run of ``bag``: the per-run figures of the module docstring."""
    from ekf_vo.tools.run import run_bag
    s = run_bag(bag, overrides=overrides, seed=seed)
    ok = [row.ok for row in s.frame_stats]
    first = ok.index(True) if True in ok else None
    ev = s.eval
    return {'seed': seed, 'frames': s.frames, 'frames_skipped': s.frames_skipped,
            'frames_ok': s.frames_ok, 'first_pose_frame': first,
            'lost_after_first': None if first is None else ok[first:].count(False),
            'ate_pct_path': None if ev is None else float(ev.ate_sim3_pct_of_path),
            'ate_sim3_rmse_m': None if ev is None else float(ev.ate_sim3_rmse),
            'rot_err_mean_deg': None if ev is None else float(ev.rot_err_mean_deg),
            'rot_drift_mean_deg': None if ev is None else float(ev.rot_err_origin_mean_deg),
            'resets': s.n_resets, 'eval_error': s.eval_error, 'wall_s': s.wall_s,
            'frames_per_s': s.fps, 'adjustment': dict(s.local_map)}


def _stat(runs: Sequence[dict], key: str, how) -> float | None:
    """``how`` (np.mean / np.max) of ``key`` over the runs that have it (a run's own
    figures, or its adjustment figures), None if none."""
    vals = [r.get(key, r['adjustment'].get(key)) for r in runs]
    vals = [v for v in vals if v is not None]
    return float(how(vals)) if vals else None


def aggregate(runs: Sequence[dict]) -> dict[str, Any]:
    """Per-variant figures over the seeds; a run without a pose (or evaluation) counts in
    ``no_pose`` / ``no_eval`` rather than silently in the means."""
    return {'ate_pct_mean': _stat(runs, 'ate_pct_path', np.mean),
            'ate_pct_max': _stat(runs, 'ate_pct_path', np.max),
            'ate_pct_std': _stat(runs, 'ate_pct_path', np.std),
            'rot_err_mean_deg': _stat(runs, 'rot_err_mean_deg', np.mean),
            'rot_drift_mean_deg': _stat(runs, 'rot_drift_mean_deg', np.mean),
            'first_pose_frame_max': _stat(runs, 'first_pose_frame', np.max),
            'lost_after_first_max': _stat(runs, 'lost_after_first', np.max),
            'resets_max': _stat(runs, 'resets', np.max),
            'ba_runs_mean': _stat(runs, 'ba_runs', np.mean),
            'ba_mean_ms': _stat(runs, 'ba_mean_ms', np.mean),
            'ba_max_ms': _stat(runs, 'ba_max_ms', np.max),
            'ba_frames_waited_max': _stat(runs, 'ba_frames_waited', np.max),
            'frames_per_s_mean': _stat(runs, 'frames_per_s', np.mean),
            'no_pose': sum(r['first_pose_frame'] is None for r in runs),
            'no_eval': sum(r['ate_pct_path'] is None for r in runs)}


def order_spread(variants: Mapping[str, dict]) -> dict[str, float | None]:
    """Per image kind with both orders run: |mean ATE % before - mean ATE % after|."""
    out: dict[str, float | None] = {}
    for kind in ('raw', 'jpeg'):
        a, b = variants.get(f'{kind}-before'), variants.get(f'{kind}-after')
        if a is None or b is None:
            continue
        ma, mb = a['summary']['ate_pct_mean'], b['summary']['ate_pct_mean']
        out[kind] = None if ma is None or mb is None else abs(ma - mb)
    return out


def run_variants(variants: Sequence[str], seeds: int, overrides: Mapping[str, Any],
                 work: Path | None = None) -> dict[str, Any]:
    """Build the bags (in ``work`` or a temporary folder) and run every variant x seed."""
    folder = shared_data(SEQUENCE)
    if folder is None:
        raise BenchError(f"../shared/data/{SEQUENCE} is absent (the developers' data "
                         'folder; set EKF_VO_SHARED_DATA)')
    t0 = time.perf_counter()
    place = (tempfile.TemporaryDirectory(prefix='ekf_vo_local_map_') if work is None
             else contextlib.nullcontext(str(work)))
    with place as tmp:
        root = Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        bags = build_bags(folder, root, variants)
        res: dict[str, dict] = {}
        for name in variants:
            runs = []
            for seed in range(seeds):
                r = run_one(bags[name], overrides, seed)
                print(f'  {name} seed {seed}: first pose {r["first_pose_frame"]}, lost '
                      f'{r["lost_after_first"]}, ATE {_fmt(r["ate_pct_path"])} % path',
                      file=sys.stderr, flush=True)
                runs.append(r)
            res[name] = {'options': VARIANTS[name], 'runs': runs, 'summary': aggregate(runs)}
    return {'sequence': SEQUENCE, 'seeds': seeds, 'overrides': dict(overrides),
            'jpeg_quality': JPEG_QUALITY, 'machine': machine(),
            'wall_s': time.perf_counter() - t0, 'variants': res,
            'order_spread_ate_pct': order_spread(res)}


#: the report's comparison: today's defaults against the points triangulated once
REPORT_CONFIGS = {'local map (defaults)': {}, 'triangulated once': {'local_map': False}}


def run(quick: bool = False, out: Path | None = None) -> dict[str, Any]:
    """The bench.run_all section: every variant, both configurations (8 seeds; 2 quick)."""
    if shared_data(SEQUENCE) is None:
        return {'skipped': f"{SEQUENCE} is not in the developers' data folder"}
    seeds = 2 if quick else 8
    return {name: run_variants(list(VARIANTS), seeds, over)
            for name, over in REPORT_CONFIGS.items()}


def summary_rows(res: dict[str, Any]) -> list[list[str]]:
    """bench.run_all summary: worst ATE over the variants, per configuration."""
    rows = []
    for name, r in res.items():
        s = [v['summary'] for v in r['variants'].values()]
        worst = max(x['ate_pct_max'] for x in s if x['ate_pct_max'] is not None)
        first = max(x['first_pose_frame_max'] for x in s
                    if x['first_pose_frame_max'] is not None)
        rows.append([f'KITTI 06 raw/JPEG x CameraInfo order, {name}: worst ATE % path, '
                     f'last first pose', f'{worst:.3f} %, frame {first:.0f}',
                     'target <= 0.10 %, frame 3', 'met' if worst <= 0.10 and first <= 3
                     else '**not met**'])
    return rows


def report_section(res: dict[str, Any], quick: bool) -> str:
    """bench.run_all report section: one table per configuration."""
    lines = ['## Local map: KITTI 06 f0-50 as recorded bags (bench.local_map)\n',
             'Four bags through ekf-vo-convert: raw mono8 or JPEG 75, CameraInfo logged before '
             'or after its image; each run offline (ekf-vo-run\'s run_bag) per seed. ATE after '
             'Sim(3), % of path; "drift" = mean rotation error from the first pose; the '
             'order spread is |mean ATE before - after| (docs/method.md §12).\n']
    for name, r in res.items():
        lines += [f'\n### {name} ({r["seeds"]} seeds)\n',
                  '| bag | ATE % mean | ATE % max | ATE % std | drift deg | first pose (max) '
                  '| lost after it (max) | resets (max) | frames/s | adjustments per run, '
                  'mean / max ms, frames waited (max) |',
                  '|---|---|---|---|---|---|---|---|---|---|']
        for bag, v in r['variants'].items():
            s = v['summary']
            lines.append(f'| {bag} | {_fmt(s["ate_pct_mean"], 3)} | {_fmt(s["ate_pct_max"], 3)} '
                         f'| {_fmt(s["ate_pct_std"], 3)} | {_fmt(s["rot_drift_mean_deg"])} | '
                         f'{_fmt(s["first_pose_frame_max"], 0)} | '
                         f'{_fmt(s["lost_after_first_max"], 0)} | {_fmt(s["resets_max"], 0)} | '
                         f'{_fmt(s["frames_per_s_mean"], 0)} | {_adjustments(s)} |')
        spread = ', '.join(f'{k} {_fmt(v, 3)}' for k, v in r['order_spread_ate_pct'].items())
        lines.append(f'\nOrder spread (ATE % path): {spread}.\n')
    return '\n'.join(lines) + '\n'


def _adjustments(s: dict) -> str:
    """The adjustment cell of the report: '-' when the local map was off."""
    if s['ba_runs_mean'] is None:
        return '-'
    return (f'{s["ba_runs_mean"]:.0f}, {s["ba_mean_ms"]:.0f} / {s["ba_max_ms"]:.0f} ms, '
            f'{s["ba_frames_waited_max"]:.0f}')


def _fmt(v: float | None, p: int = 2) -> str:
    return '-' if v is None else f'{v:.{p}f}'


def print_table(res: dict[str, Any]) -> None:
    """The per-variant table and the order spreads."""
    sets = ' '.join(f'{k}={v}' for k, v in res['overrides'].items()) or 'defaults'
    print(f"{res['sequence']}: {res['seeds']} seeds per bag, {sets}; ATE after Sim(3) "
          f"({res['wall_s']:.0f} s)")
    print(f'{"bag":<12} {"ATE % mean":>10} {"ATE % max":>10} {"rot deg":>8} {"drift deg":>9} '
          f'{"1st pose max":>12} {"lost max":>9} {"resets max":>10} {"no eval":>8}')
    for name, v in res['variants'].items():
        s = v['summary']
        print(f'{name:<12} {_fmt(s["ate_pct_mean"]):>10} {_fmt(s["ate_pct_max"]):>10} '
              f'{_fmt(s["rot_err_mean_deg"]):>8} {_fmt(s["rot_drift_mean_deg"]):>9} '
              f'{_fmt(s["first_pose_frame_max"], 0):>12} '
              f'{_fmt(s["lost_after_first_max"], 0):>9} {_fmt(s["resets_max"], 0):>10} '
              f'{s["no_eval"]:>8}')
    for kind, spread in res['order_spread_ate_pct'].items():
        print(f'order spread {kind}: |mean ATE % before - after| = {_fmt(spread, 3)}')


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m bench.local_map',
                                description=__doc__.split('\n')[0])
    p.add_argument('--seeds', type=int, default=8, help='seeds 0..N-1 per bag (default 8)')
    p.add_argument('--variants', nargs='+', choices=list(VARIANTS), default=list(VARIANTS),
                   help='bags to build and run (default: all four)')
    p.add_argument('--set', dest='overrides', nargs='+', default=[], metavar='NAME=VALUE',
                   help='core parameter overrides, as ekf-vo-run --set')
    p.add_argument('--work', type=Path, default=None,
                   help='build the bags here and keep them (default: a temporary folder)')
    p.add_argument('--json', type=Path, default=None, help='write everything to this file')
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # KITTI frame 0 is stamped t = 0, which the ground-truth reader flags (and then reads
    # right) on every run: not news here
    logging.getLogger('ekf_vo.io.bag').addFilter(
        lambda rec: 'zero header stamp' not in rec.getMessage())
    from ekf_vo.config import ConfigError
    from ekf_vo.tools.convert import ConvertError
    from ekf_vo.tools.run import RunError, make_config, parse_overrides
    try:
        if args.seeds < 1:
            raise BenchError(f'--seeds must be at least 1, got {args.seeds}')
        overrides = parse_overrides(args.overrides)
        make_config(None, overrides)      # a bad value fails before minutes of conversion
        variants = list(dict.fromkeys(args.variants))
        res = run_variants(variants, args.seeds, overrides, args.work)
    except (BenchError, ConfigError, ConvertError, RunError) as exc:
        print(f'bench.local_map: error: {exc}', file=sys.stderr)
        return 2
    if args.json:
        write_json(args.json, res)
    print_table(res)
    return 0


if __name__ == '__main__':
    sys.exit(main())

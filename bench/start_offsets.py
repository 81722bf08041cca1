"""The filter against per-frame EPnP on the demo, from several start frames.

One run of the demo bag is one draw: a setting one frame away moves its ATE by up to 2x
(docs/method.md §9.4), and EPnP has no random seed of its own to average over. Every
estimator is run on the same images from each of the first `--offsets` frames (the
bootstrap then takes a different pair, which issue 14 asks not to matter) and compared
on the distribution: ATE after Sim(3) (m), RPE per frame (m) and the largest rotation
error (deg); and, pair by pair, at how many starts each estimator's ATE is the lower.

    python -m bench.start_offsets [--estimators ekf epnp] [--offsets 8] [--seed 0]
                                  [--set NAME=VALUE ...] [--json OUT]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
from pathlib import Path

import numpy as np

from .common import machine, overrides_or_report, write_json

STATS = ('ate_sim3_rmse', 'rpe_trans_rmse', 'rot_err_max_deg')


def run_from(frames, info, gt_s, gt_T, start: int, overrides: dict, seed: int) -> dict:
    """One run of `frames[start:]`: the evaluation's figures and the frames published."""
    from ekf_vo.config import VoConfig
    from ekf_vo.core.camera import PinholeCamera
    from ekf_vo.core.stream import VoStream
    from ekf_vo.tools.evaluate import evaluate
    stream = VoStream(dataclasses.replace(VoConfig(), **overrides).validate(), seed=seed)
    stream.set_camera(PinholeCamera.from_camera_info(info))
    stamps, poses = [], []
    for t, g in frames[start:]:
        r = stream.process(g, t)
        if r.ok:
            stamps.append(t * 1e-9)
            poses.append(r.T_world_cam)
    if stream.vo is not None:
        stream.vo.close()
    ev = evaluate(gt_s, gt_T, np.array(stamps), np.array(poses), max_time_diff_s=1e-3,
                  n_frames_total=len(frames) - start)
    return {'start': start, 'published': len(stamps),
            **{k: float(getattr(ev, k)) for k in STATS}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--estimators', nargs='+', default=['ekf', 'epnp'],
                   choices=('ekf', 'iekf', 'epnp'))
    p.add_argument('--offsets', type=int, default=8, help='start frames 0 .. N-1')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--set', nargs='+', default=[], metavar='NAME=VALUE')
    p.add_argument('--json', type=Path, default=None)
    args = p.parse_args(argv)
    overrides = overrides_or_report(args.set, 'bench.start_offsets')
    if overrides is None:
        return 2
    if 'estimator' in overrides:      # --estimators chooses; a --set would be overridden
        print('bench.start_offsets: choose the estimator with --estimators, not --set',
              file=sys.stderr)
        return 2
    from ekf_vo.io.bag import read_ground_truth
    from ekf_vo.tools.demo import demo_bag, load_demo_frames
    info, frames = load_demo_frames()
    gt_ns, gt_T = read_ground_truth(demo_bag())
    gt_s = np.asarray(gt_ns) * 1e-9
    out = {'machine': machine(), 'overrides': overrides, 'seed': args.seed, 'runs': {}}
    print(f'demo bag, start frames 0-{args.offsets - 1}; ATE after Sim(3) [m], RPE per '
          'frame [m], largest rotation error [deg]')
    print('| estimator | ATE mean | median | max | RPE mean | rot. err. max |')
    print('|---|---|---|---|---|---|')
    for est in args.estimators:
        runs = [run_from(frames, info, gt_s, gt_T, k, dict(overrides, estimator=est),
                         args.seed) for k in range(args.offsets)]
        out['runs'][est] = runs
        ate = np.array([r['ate_sim3_rmse'] for r in runs])
        print(f'| {est} | {ate.mean():.4f} | {np.median(ate):.4f} | {ate.max():.4f} | '
              f"{np.mean([r['rpe_trans_rmse'] for r in runs]):.4f} | "
              f"{max(r['rot_err_max_deg'] for r in runs):.2f} |", flush=True)
    pairs = paired_lower_ate(out['runs'])
    if pairs:
        out['paired_lower_ate'] = pairs
        print('start by start (the same images), lower ATE: ' + '; '.join(
            f'{pair} {n[0]} : {n[1]}' for pair, n in pairs.items()) + f' of {args.offsets}')
    if args.json:
        write_json(args.json, out)
    return 0


def paired_lower_ate(runs: dict[str, list[dict]]) -> dict[str, list[int]]:
    """For each pair of estimators 'a vs b': at how many start frames a's ATE is lower
    than b's, and b's than a's (a tie counts for neither). The means alone hide whether
    one estimator wins most starts or a few by much."""
    ate = {est: np.array([r['ate_sim3_rmse'] for r in rs]) for est, rs in runs.items()}
    return {f'{a} vs {b}': [int(np.sum(ate[a] < ate[b])), int(np.sum(ate[b] < ate[a]))]
            for a, b in itertools.combinations(runs, 2)}


if __name__ == '__main__':
    sys.exit(main())

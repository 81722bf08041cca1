"""The keyframes' rotation checks against the ground truth, pair by pair.

docs/method.md §15.2 and §15.11: at each keyframe the filter's rotation since the last one
is compared with the two-view geometry of the tracks they share, and what the pairs
report is the drift the published covariance is made to hold. On a rendered sequence
(ekf-vo-synth, the names of bench.rotation_nees) this reads every check the pipeline
takes in a tracked frame from the frames' results (`FrameResult.keyframe_pair_check`:
the pair, the filter's orientations it was judged with, the verdict and the candidates
weighed; a check taken at a reset or a loss, or still pending at the end, is not
there), and sets each pair beside the truth:
- reported: the discrepancy the check found (filter minus two-view, deg);
- true: the filter's actual error over the pair (its relative rotation against the ground
  truth's, deg), what a perfect two-view check would report;
- judged: the error of the two-view rotation the check judged against (deg), and of each
  candidate an ambiguous pair had (the essential matrix's, the homography's).
The vector sums of reported and true discrepancies say how much of the filter's drift the
checks can see at all.

    python -m bench.keyframe_pairs --sequence orbit_narrow --seed 8 [--json OUT]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ekf_vo.core import geometry as geo
from .common import machine, write_json


def _rotvec(R: np.ndarray) -> np.ndarray:
    return geo.quat_to_rotvec(geo.matrix_to_quat(R))


def pair_truth(R_world_a: np.ndarray, R_world_b: np.ndarray, R_gt_a: np.ndarray,
               R_gt_b: np.ndarray) -> np.ndarray:
    """The filter's true error over a keyframe pair as the check would report it: the
    rotation vector (world, the filter's frame at a) of R_ab,filter R_ab,true^T. A world
    rotation of the ground truth (its gauge) does not change it."""
    R_ab_filter = R_world_a.T @ R_world_b
    R_ab_true = R_gt_a.T @ R_gt_b
    return R_world_a @ _rotvec(R_ab_filter @ R_ab_true.T)


def records_of(results) -> list:
    """The keyframe-pair checks (rotation_check.KeyframePairCheck) in the frames'
    results, in the order they were taken."""
    return [res.keyframe_pair_check for res in results
            if res.keyframe_pair_check is not None]


def summarise(records: list, gt_T: np.ndarray) -> dict:
    """Per pair (records: KeyframePairCheck) and summed: reported and true
    discrepancies, the judged rotation's error (all in deg; see the module docstring)."""
    pairs = []
    reported, true_judged, true_all = np.zeros(3), np.zeros(3), np.zeros(3)
    for record in records:
        a, b, out = record.frame_a, record.frame_b, record.check
        d_true = pair_truth(record.R_world_a, record.R_world_b, gt_T[a][:3, :3],
                            gt_T[b][:3, :3])
        true_all += d_true
        row = {'a': a, 'b': b, 'true_deg': float(np.degrees(np.linalg.norm(d_true))),
               'judged': out is not None}
        if out is not None:
            reported += out.discrepancy_world
            true_judged += d_true
            R_ab_true = gt_T[a][:3, :3].T @ gt_T[b][:3, :3]
            row.update({
                'ambiguous': bool(out.ambiguous), 'reported_deg': out.angle_deg,
                'parallax_deg': out.parallax_deg,
                # the two-view rotation judged, as an error against the truth
                'judged_error_deg': float(np.degrees(np.linalg.norm(
                    out.discrepancy_world - d_true))),
                'candidate_errors_deg': [
                    {'plane': plane, 'error_deg': geo.rotation_angle_deg(R_ba.T, R_ab_true)}
                    for R_ba, plane in out.candidates]})
        pairs.append(row)
    deg = lambda v: float(np.degrees(np.linalg.norm(v)))   # noqa: E731
    return {'pairs': pairs, 'n_pairs': len(pairs),
            'n_judged': sum(p['judged'] for p in pairs),
            'n_ambiguous': sum(p.get('ambiguous', False) for p in pairs),
            'reported_sum_deg': deg(reported), 'true_sum_judged_deg': deg(true_judged),
            'true_sum_all_deg': deg(true_all)}


def run(sequence: str, seed: int) -> dict:
    from functools import partial

    from . import rotation_nees
    if rotation_nees._synthetic_name(sequence) is None:
        raise ValueError(f'{sequence}: not a rendered sequence of bench.rotation_nees')
    trajectory, speedup, still, fault, camera = rotation_nees._synthetic_name(sequence)
    results = []
    gt_s, gt_T, stream_out = rotation_nees._synthetic(
        trajectory, seed, {}, speedup, still, fault, camera=camera,
        run=partial(rotation_nees._run_stream, on_result=results.append))
    figures = rotation_nees.figures(sequence, seed, gt_s, gt_T, stream_out)
    out = summarise(records_of(results), np.asarray(gt_T))
    out.update({'sequence': sequence, 'seed': seed,
                'rot_err_max_deg': figures['rot_err_max_deg'],
                'rot_nees_median': figures['rot_nees_median'],
                'rot_nees_pct_above_99_9': figures['rot_nees_pct_above_99_9']})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--sequence', default='orbit_narrow')
    parser.add_argument('--seed', type=int, default=8)
    parser.add_argument('--json', type=Path)
    args = parser.parse_args(argv)
    try:
        out = run(args.sequence, args.seed)
    except ValueError as exc:
        print(f'bench.keyframe_pairs: {exc}', file=sys.stderr)
        return 2
    print(f'{out["sequence"]} seed {out["seed"]}: max rotation error '
          f'{out["rot_err_max_deg"]:.1f} deg, NEES median {out["rot_nees_median"]:.2f}, '
          f'{out["rot_nees_pct_above_99_9"]:.1f} % above')
    print(f'{out["n_pairs"]} keyframe-pair checks, {out["n_judged"]} judged, '
          f'{out["n_ambiguous"]} ambiguous; discrepancies summed: reported '
          f'{out["reported_sum_deg"]:.1f} deg, true over the judged pairs '
          f'{out["true_sum_judged_deg"]:.1f}, over all {out["true_sum_all_deg"]:.1f}')
    print('| pair | ambiguous | reported deg | true deg | judged rotation off by deg |')
    print('|---|---|---|---|---|')
    for p in out['pairs']:
        if p['judged']:
            print(f'| {p["a"]}-{p["b"]} | {"yes" if p["ambiguous"] else "no"} | '
                  f'{p["reported_deg"]:.2f} | {p["true_deg"]:.2f} | '
                  f'{p["judged_error_deg"]:.2f} |')
        else:
            print(f'| {p["a"]}-{p["b"]} | not judged | | {p["true_deg"]:.2f} | |')
    if args.json:
        write_json(args.json, {'machine': machine(), **out})
    return 0


if __name__ == '__main__':
    sys.exit(main())

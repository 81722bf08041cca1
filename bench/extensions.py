"""Estimator extensions: in-filter map refinement and multi-view bootstrap vs the hybrid default.

Four variants of the full pipeline (images in, no ground truth inside the estimator):
    default     bootstrap two_view,   map_refinement none     (docs/method.md §1)
    filter      bootstrap two_view,   map_refinement filter   (point_filter.py, sec. 3)
    multi_view  bootstrap multi_view, map_refinement none     (multiview.py, sec. 3)
    both        bootstrap multi_view, map_refinement filter
Sequences: rendered synthetic scenes (tools/synth.py, 640x480, 30 Hz, `walk` and `orbit`;
the seed changes the scene texture, the noise and the pipeline's RANSAC), KITTI 06 frames
0-50 (monocular bootstrap) and Middlebury dino (the paper's ground-truth bootstrap of the
first two views, real_data.PRESETS) from ../shared/data when present (seed = pipeline
RANSAC seed). Metrics per run: frames tracked (%), ATE after Sim(3) alignment (% of the
path length), mean rotation drift w.r.t. the first pose after alignment (deg), the
precise-point ratio of Li et al. (mean over frames of the fraction of observed map points
reprojecting within 1 px under the estimated pose, precise_points.precise_fraction) and
frames/s of the whole run (tracking, bootstrap and map included).

    python -m bench.extensions [--quick] [--seeds 3] [--out DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.evaluate import evaluate
from .common import machine, shared_data, write_json
from .precise_points import precise_fraction

VARIANTS = {
    'default': {},
    'filter': {'map_refinement': 'filter'},
    'multi_view': {'bootstrap': 'multi_view'},
    'both': {'map_refinement': 'filter', 'bootstrap': 'multi_view'},
}
METRICS = ('pct_tracked', 'ate_pct_path', 'rot_drift_deg', 'precise_ratio', 'fps')


def run_frames(frames: list, camera: PinholeCamera, cfg: VoConfig, gt_s: np.ndarray,
               gt_T: np.ndarray, seed: int, known_T: list | None = None) -> dict:
    """One pipeline run over (stamp_ns, gray) frames; metrics against the ground truth.

    known_T: per-frame GT poses handed to the pipeline while it initialises (the paper's
    GT bootstrap; the pipeline reads them for its first map only), or None for the
    monocular bootstrap."""
    stream = VoStream(cfg, seed=seed)
    stream.set_camera(camera)
    vo = stream.vo      # the estimator behind the front door, for its internals
    stamps, poses, precise = [], [], []
    t0 = time.perf_counter()
    for k, (stamp, gray) in enumerate(frames):
        known = known_T[k] if known_T is not None and vo.state.value == 'initialising' \
            else None
        res = stream.process(gray, stamp, known_T_world_cam=known)
        if res.ok:
            stamps.append(stamp * 1e-9)
            poses.append(res.T_world_cam)
        if vo.state.value == 'tracking':
            f, n, _ = precise_fraction(vo, res)
            if n:
                precise.append(f)
    wall = time.perf_counter() - t0
    ev = evaluate(gt_s, gt_T, np.array(stamps), np.array(poses), max_time_diff_s=1e-3,
                  n_frames_total=len(frames))
    out = {'pct_tracked': ev.pct_tracked, 'ate_pct_path': ev.ate_sim3_pct_of_path,
           'ate_sim3_rmse': ev.ate_sim3_rmse, 'rot_drift_deg': ev.rot_err_origin_mean_deg,
           'precise_ratio': float(np.mean(precise)) if precise else float('nan'),
           'fps': len(frames) / wall, 'n_resets': vo.n_resets, 'map_size': len(vo.map)}
    if vo.points is not None:
        out['frozen'] = vo.points.n_frozen
        out['dropped'] = vo.points.n_dropped
    return out


def _synthetic(trajectory: str, n_frames: int, seed: int):
    from ekf_vo.tools.synth import SynthConfig, render_sequence
    scfg = SynthConfig(frames=n_frames, trajectory=trajectory, seed=seed)
    data = list(render_sequence(scfg))
    camera = PinholeCamera(scfg.width, scfg.height, scfg.K())
    frames = [(s, img) for s, img, _ in data]
    return (frames, camera, np.array([s * 1e-9 for s, _, _ in data]),
            np.array([T for _, _, T in data]), None)


def _real(name: str):
    from ekf_vo.io.dataset import load_folder
    from .real_data import GT_BOOTSTRAP
    folder = shared_data(name)
    if folder is None:
        return None
    data = load_folder(folder)
    frames = list(data.frames())
    known = [data.gt_at(k) for k in range(len(frames))] if GT_BOOTSTRAP.get(name) else None
    return (frames, PinholeCamera.from_camera_info(data.camera), data.gt_stamps_s,
            data.gt_T_world_cam, known)


def _summary(runs: list[dict]) -> dict:
    out = {}
    for k in METRICS:
        v = np.array([r[k] for r in runs], float)
        out[k] = {'mean': float(np.nanmean(v)), 'std': float(np.nanstd(v)),
                  'values': v.tolist()}
    out['n_resets'] = int(sum(r['n_resets'] for r in runs))
    return out


def run(quick: bool = False, seeds: int | None = None) -> dict:
    """All variants on all sequences; mean/std over seeds. Returns a JSON-able dict."""
    from .real_data import PRESETS
    n_seeds = seeds if seeds is not None else (1 if quick else 3)
    n_frames = 120 if quick else 300
    result = {'machine': machine(), 'seeds': list(range(n_seeds)), 'frames': n_frames,
              'variants': VARIANTS, 'sequences': {}}
    jobs = [(f'synth_{t}', t) for t in ('walk', 'orbit')]
    if not quick:
        jobs += [('kitti06_f0-50', None), ('middlebury_dino', None)]
    for name, traj in jobs:
        per_variant = {v: [] for v in VARIANTS}
        real = None if traj is not None else _real(name)
        if traj is None and real is None:
            continue
        for seed in range(n_seeds):
            data = _synthetic(traj, n_frames, seed) if traj is not None else real
            frames, camera, gt_s, gt_T, known = data
            base = dict(PRESETS.get(name, {}))
            for v, over in VARIANTS.items():
                cfg = dataclasses.replace(VoConfig(), **dict(base, **over)).validate()
                per_variant[v].append(run_frames(frames, camera, cfg, gt_s, gt_T, seed,
                                                 known))
        result['sequences'][name] = {v: dict(_summary(rs), runs=rs)
                                     for v, rs in per_variant.items()}
    return result


def format_table(result: dict) -> str:
    lines = [f'machine: {result["machine"]}; seeds {result["seeds"]}; synthetic '
             f'{result["frames"]} frames; mean +- std over seeds',
             f'{"sequence":<16} {"variant":<11} {"tracked %":>9} {"ATE % path":>13} '
             f'{"rot drift deg":>14} {"precise <1px":>13} {"frames/s":>9} {"resets":>6}']
    for name, variants in result['sequences'].items():
        for v, r in variants.items():
            def f(k, p):
                return f'{r[k]["mean"]:.{p}f}+-{r[k]["std"]:.{p}f}'
            lines.append(f'{name:<16} {v:<11} {r["pct_tracked"]["mean"]:9.1f} '
                         f'{f("ate_pct_path", 2):>13} {f("rot_drift_deg", 2):>14} '
                         f'{f("precise_ratio", 3):>13} {r["fps"]["mean"]:9.1f} '
                         f'{r["n_resets"]:6d}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true')
    parser.add_argument('--seeds', type=int, default=None)
    parser.add_argument('--out', type=Path, default=None, help='write extensions.json here')
    args = parser.parse_args(argv)
    result = run(args.quick, args.seeds)
    print(format_table(result))
    if args.out is not None:
        write_json(args.out / 'extensions.json', result)
    return 0


if __name__ == '__main__':
    sys.exit(main())

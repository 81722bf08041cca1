"""Fraction of "precisely reconstructed" map points per image (docs/method.md §8 metric).

Li et al. 2016 call a point precise when its reprojection error is below 1 px, and report
per image the fraction of such points: in 80 % of their flight-test images more than 89 %
of the points were precise. Here, per frame of the full pipeline (VisualOdometry, images
in, monocular bootstrap, no ground truth):
- the points = the map points observed in that image (tracks that had a landmark before
  this frame's map growth: `FrameResult.track_has_point`), so points triangulated in this
  very frame, which reproject perfectly by construction, are not counted;
- the reprojection error = |undistort(tracked pixel) - pi(EKF pose after the update, X)|;
- a landmark culled during the frame (repeated outlier) counts as imprecise.
Sequences: a rendered synthetic room (tools/synth.py, 640x480, `walk`) and KITTI 06
frames 0-50 when ../shared/data is present.

    python -m bench.precise_points [--quick] [--out DIR]
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.pipeline import FrameResult, VisualOdometry
from ekf_vo.core.stream import VoStream
from .common import pyplot, section_main, shared_data

THRESHOLD_PX = 1.0
PAPER = {'pct_images': 80.0, 'pct_points_precise': 89.0}


def precise_fraction(vo: VisualOdometry, res: FrameResult) -> tuple[float, int, np.ndarray]:
    """(fraction of precise points, points counted, their reprojection errors [px])."""
    if not res.ok or res.track_ids is None or res.track_has_point is None:
        return float('nan'), 0, np.zeros(0)
    ids = res.track_ids[res.track_has_point]
    if len(ids) == 0:
        return float('nan'), 0, np.zeros(0)
    in_map, X = vo.map.lookup(ids)
    px = vo.camera.undistort(res.track_px[res.track_has_point][in_map])
    pred, front, _ = vo.ekf.observe(X, with_jacobian=False)
    err = np.where(front, np.linalg.norm(pred - px, axis=1), np.inf)
    return float(np.count_nonzero(err < THRESHOLD_PX) / len(ids)), len(ids), err


def run_pipeline(frames, camera: PinholeCamera, cfg: VoConfig) -> dict:
    """Run VisualOdometry over (stamp_ns, gray) frames; per-frame precise fractions."""
    stream = VoStream(cfg, seed=0)
    stream.set_camera(camera)
    vo = stream.vo      # the estimator behind the front door, for its internals
    frac, n_pts, errs = [], [], []
    n_frames = 0
    for stamp, gray in frames:
        res = stream.process(gray, stamp)
        n_frames += 1
        f, n, e = precise_fraction(vo, res)
        if n:
            frac.append(f)
            n_pts.append(n)
            errs.append(e[np.isfinite(e)])
    return summarise(np.array(frac), np.array(n_pts), np.concatenate(errs) if errs else
                     np.zeros(0), n_frames, vo.n_resets)


def summarise(frac: np.ndarray, n_pts: np.ndarray, errs: np.ndarray, n_frames: int,
              n_resets: int) -> dict:
    if len(frac) == 0:
        return {'frames': n_frames, 'frames_scored': 0}
    return {
        'frames': n_frames, 'frames_scored': len(frac), 'n_resets': n_resets,
        'points_per_image_mean': float(n_pts.mean()),
        'fraction_per_image': frac,
        'fraction_mean': float(frac.mean()),
        'fraction_median': float(np.median(frac)),
        # the paper's statement read both ways:
        # "in 80 % of the images more than P20 of the points are precise"
        'pct_points_precise_in_80pct_of_images': float(100.0 * np.percentile(frac, 20)),
        # "in X % of the images more than 89 % of the points are precise"
        'pct_images_above_89pct': float(100.0 * np.mean(frac > 0.89)),
        'reproj_err_median_px': float(np.median(errs)) if len(errs) else float('nan'),
        'reproj_err_p90_px': float(np.percentile(errs, 90)) if len(errs) else float('nan'),
    }


def synthetic_frames(n: int):
    from ekf_vo.tools.synth import SynthConfig, render_sequence
    cfg = SynthConfig(frames=n)
    camera = PinholeCamera(cfg.width, cfg.height, cfg.K())
    return ((stamp, img) for stamp, img, _ in render_sequence(cfg)), camera


def run(quick: bool = False, out: Path | None = None) -> dict:
    n = 100 if quick else 300
    frames, camera = synthetic_frames(n)
    res = {'threshold_px': THRESHOLD_PX, 'paper': PAPER,
           'synthetic_room': run_pipeline(frames, camera, VoConfig())}
    res['synthetic_room']['what'] = f'rendered room, walk trajectory, {n} frames 640x480'
    folder = shared_data('kitti06_f0-50')
    if folder is not None:
        from ekf_vo.io.dataset import load_folder
        from .real_data import PRESETS
        data = load_folder(folder)
        cfg = dataclasses.replace(VoConfig(), **PRESETS['kitti06_f0-50']).validate()
        res['kitti06'] = run_pipeline(data.frames(), PinholeCamera.from_camera_info(
            data.camera), cfg)
        res['kitti06']['what'] = 'KITTI 06 frames 0-50, 1226x370'
    else:
        res['kitti06'] = {'skipped': '../shared/data/kitti06_f0-50 is absent'}
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    seqs = [(k, res[k]) for k in ('synthetic_room', 'kitti06')
            if 'fraction_per_image' in res[k]]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    bins = np.linspace(0, 1, 41)
    for (name, r), c in zip(seqs, ('tab:blue', 'tab:orange')):
        f = np.asarray(r['fraction_per_image'])
        ax[0].hist(100 * f, bins=100 * bins, alpha=0.6, color=c, density=True,
                   label=f'{name} ({len(f)} images)')
        ax[1].plot(100 * f, '.-', color=c, ms=3, lw=0.8, label=name)
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    ax[0].axvline(PAPER['pct_points_precise'], color='k', ls=':', label='paper: 89 %')
    ax[0].set(xlabel='precise points in the image [%] (reprojection < 1 px)',
              ylabel='density of images', title='distribution over images')
    ax[1].set(xlabel='frame (scored frames)', ylabel='precise points [%]',
              title='per frame')
    fig.tight_layout()
    p = out / 'precise_points.png'
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return [p.name]


def _summarize(res: dict) -> None:
    for k in ('synthetic_room', 'kitti06'):
        print(k, {a: b for a, b in res[k].items() if a != 'fraction_per_image'})


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'precise_points', _summarize)


if __name__ == '__main__':
    sys.exit(main())

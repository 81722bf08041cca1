"""How precise are the front end's tracks themselves? KLT window size against ground truth.

The precise-points figure (bench/precise_points.py) scores the whole estimator. This bench
takes the estimator out: the tracker alone (`FeatureTracker`, no prior) runs over a
sequence, every track seen in at least 3 frames is triangulated from all its observations
under the GROUND-TRUTH poses (linear DLT, then Gauss-Newton with Huber weights, 1 px), and
the residuals of its observations are what no map, adjustment or filter can remove: the
tracker's own error. Tracks with less than 1 deg of parallax between their first and last
views are left out (their depth is unknown, so they fit anything). Per window: tracks
scored, residual median / p90 [px], and, per image, the share of observations within 1 px
(mean, and the value exceeded in 80 % of the images: the precise-points statistic).

KITTI's ground truth (GPS/INS) is itself off by a few hundredths of a degree (0.02 deg is
0.25 px at its 707 px focal length), so its figures are an upper bound of the tracker's
error; the renders' poses are exact.

    python -m bench.track_precision [--sequences kitti walk car] [--windows 21 15 13 11]
                                    [--set NAME=VALUE ...]
                                    [--json OUT]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.features import FeatureTracker
from .common import machine, overrides_or_report, shared_data, write_json

#: observations a track needs to be scored (a point from two views fits them exactly)
MIN_VIEWS = 3
#: parallax [deg] between a track's first and last rays below which it is not scored
MIN_PARALLAX_DEG = 1.0
#: Huber threshold [px] of the triangulation's refinement, and the "precise" bound
HUBER_PX = 1.0
PRECISE_PX = 1.0


def _tracks(frames, cfg: VoConfig) -> dict[int, list[tuple[int, np.ndarray]]]:
    """Track id -> [(frame index, raw px)] over the frames, tracker alone (no prior)."""
    tracker = FeatureTracker(cfg)
    obs: dict[int, list] = {}
    for k, gray in enumerate(frames):
        t = tracker.track(gray)
        for i, p in zip(t.ids.tolist(), t.px):
            obs.setdefault(i, []).append((k, p))
    tracker.close()
    return obs


def _triangulate(P: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """A point from n >= 3 views: DLT on the projection matrices P (n,3,4), then 10
    Huber-weighted Gauss-Newton steps on the undistorted pixels uv (n,2). None when it
    lies behind a camera."""
    A = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]])
    Xh = np.linalg.svd(A)[2][-1]
    if abs(Xh[3]) < 1e-12:
        return None
    X = Xh[:3] / Xh[3]
    for _ in range(10):
        x = np.einsum('nij,j->ni', P[:, :, :3], X) + P[:, :, 3]
        if np.any(x[:, 2] <= 0):
            return None
        r = (x[:, :2] / x[:, 2:]) - uv
        # d(x/z)/dX for each view (2x3), from the rows of P
        J = (P[:, :2, :3] - (x[:, :2, None] / x[:, 2:, None]) * P[:, 2:, :3]) / x[:, 2:, None]
        norm = np.linalg.norm(r, axis=1)
        w = np.where(norm <= HUBER_PX, 1.0, HUBER_PX / np.maximum(norm, 1e-12))
        JtJ = np.einsum('nki,n,nkj->ij', J, w, J)
        step = np.linalg.solve(JtJ + 1e-9 * np.eye(3), -np.einsum('nki,n,nk->i', J, w, r))
        X = X + step
        if np.linalg.norm(step) < 1e-9 * max(1.0, np.linalg.norm(X)):
            break
    return X


def floor(obs: dict, T_world_cam: np.ndarray, camera: PinholeCamera) -> dict:
    """Residuals of each scored track against its ground-truth triangulation."""
    K = camera.K
    T_cam_world = np.linalg.inv(T_world_cam)
    P_all = np.einsum('ij,njk->nik', K, T_cam_world[:, :3, :])
    centres = T_world_cam[:, :3, 3]
    per_frame: dict[int, list[float]] = {}
    n_scored = 0
    for views in obs.values():
        if len(views) < MIN_VIEWS:
            continue
        fr = np.array([v[0] for v in views])
        uv = camera.undistort(np.array([v[1] for v in views], np.float64))
        X = _triangulate(P_all[fr], uv)
        if X is None:
            continue
        a, b = X - centres[fr[0]], X - centres[fr[-1]]
        cos = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) < MIN_PARALLAX_DEG:
            continue
        x = np.einsum('nij,j->ni', P_all[fr, :, :3], X) + P_all[fr, :, 3]
        err = np.linalg.norm(x[:, :2] / x[:, 2:] - uv, axis=1)
        n_scored += 1
        for f, e in zip(fr.tolist(), err.tolist()):
            per_frame.setdefault(f, []).append(e)
    if not per_frame:
        return {'tracks_scored': 0}
    errs = np.concatenate([np.asarray(v) for v in per_frame.values()])
    share = np.array([np.mean(np.asarray(v) < PRECISE_PX) for v in per_frame.values()
                      if len(v) >= 10])
    return {'tracks_scored': n_scored,
            'residual_median_px': float(np.median(errs)),
            'residual_p90_px': float(np.percentile(errs, 90)),
            'precise_share_mean': float(share.mean()) if share.size else float('nan'),
            'precise_share_in_80pct_of_images': float(np.percentile(share, 20))
            if share.size else float('nan')}


def _sequence(name: str):
    """(camera, grey frames, T_world_cam (n,4,4)) of 'kitti' or a rendered trajectory;
    None when KITTI's folder is absent."""
    if name == 'kitti':
        folder = shared_data('kitti06_f0-50')
        if folder is None:
            return None
        from ekf_vo.io.dataset import load_folder
        data = load_folder(folder)
        frames = [g for _, g in data.frames()]
        T = np.array([data.gt_at(k) for k in range(len(frames))])
        return PinholeCamera.from_camera_info(data.camera), frames, T
    from .rotation_nees import SYNTHETIC, TRAJECTORY_CAMERAS
    from ekf_vo.tools.synth import SynthConfig, render_sequence
    scfg = SynthConfig(frames=SYNTHETIC[name], seed=0, trajectory=name,
                       **TRAJECTORY_CAMERAS.get(name, {}))
    seq = list(render_sequence(scfg))
    info = {'width': scfg.width, 'height': scfg.height, 'K': scfg.K(), 'D': scfg.D(),
            'distortion_model': 'plumb_bob'}
    return (PinholeCamera.from_camera_info(info), [im for _, im, _ in seq],
            np.array([T for _, _, T in seq]))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='bench.track_precision', description=__doc__.split('\n')[0])
    p.add_argument('--sequences', nargs='+', default=['kitti', 'walk', 'car'])
    p.add_argument('--windows', nargs='+', type=int, default=[21, 15, 13, 11])
    p.add_argument('--set', nargs='+', default=[], metavar='NAME=VALUE',
                   help='configuration overrides beside each window (the defaults '
                   'otherwise)')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    overrides = overrides_or_report(args.set, 'bench.track_precision')
    if overrides is None:
        return 2
    print(f'machine: {machine()}' + (f', overrides {overrides}' if overrides else ''))
    out: dict = {'machine': machine(), 'overrides': overrides, 'results': []}
    print('| sequence | window px | tracks scored | residual median / p90 px | '
          'precise: mean / in 80 % of images |')
    print('|---|---|---|---|---|')
    for name in args.sequences:
        seq = _sequence(name)
        if seq is None:
            print(f'| {name} | skipped: ../shared/data/kitti06_f0-50 is absent | | | |')
            continue
        camera, frames, T = seq
        for w in args.windows:
            cfg = dataclasses.replace(VoConfig(), **{**overrides, 'klt_window_px': w}
                                      ).validate()
            r = {'sequence': name, 'window_px': w,
                 **floor(_tracks(frames, cfg), T, camera)}
            out['results'].append(r)
            if not r['tracks_scored']:
                print(f'| {name} | {w} | 0 | | |')
                continue
            print(f"| {name} | {w} | {r['tracks_scored']} | "
                  f"{r['residual_median_px']:.3f} / {r['residual_p90_px']:.2f} | "
                  f"{100 * r['precise_share_mean']:.1f} / "
                  f"{100 * r['precise_share_in_80pct_of_images']:.1f} % |", flush=True)
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""More trials of the EKFPnP paper's synthetic protocol: our filter vs EPnP+LM, same inputs.

The generator (the test vector's README, ../shared/data/ekfpnp_synthetic_sigma3): K =
[[800,0,0],[0,800,0],[0,0,1]], 100 points X ~ U(-2,2) x U(-2,2) x U(4,8), every point seen
in every frame; noise of point p in frame k: N(0, (s_p f_k)^2) per axis with
s_p ~ U(0, level) kept for the whole run and f_k = log10(1 + 100 k / 200) / 2. The camera
path is the test vector's own spiral (its gt_poses.csv: 200 frames, 0.35-0.95 units and
4-10 deg between frames), so this needs the developers' data folder; points and noise are
drawn anew per trial (seed = 1000 level + trial). Each trial is written in the test
vector's layout (K.csv, points_world.csv, gt_poses.csv with the nominal `ekf_R_diag` =
level f_k, obs.csv, est_EPnP_GN.csv) and run by bench.reference_vector: our filter told the
nominal sigma only (fixed and adaptive noise), EPnP+LM (OpenCV's EPnP then its
Levenberg-Marquardt refinement of the reprojection error) on the identical observations,
in the file the layout calls EPnP_GN. It is a STRONGER baseline than the toolbox's
"EPnP+GN" (on the test vector: 0.087 deg / 0.094 % against the toolbox's 0.143 / 0.161,
i.e. EKFPnP's level), so our ratios are not directly the paper's: EKFPnP reaches
0.43-0.59 against the toolbox's EPnP+GN; against EPnP+LM it is ~1 (docs/method.md §13.3).

    python -m bench.ekfpnp_trials [--levels 1 3 5] [--trials 5] [--work DIR] [--json OUT]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from . import reference_vector as rv
from .common import shared_data, write_json

N_POINTS = 100


def _write_csv(path: Path, header: str, rows: np.ndarray) -> None:
    np.savetxt(path, rows, delimiter=',', header=header, comments='', fmt='%.17g')


def _epnp_gn(obs: np.ndarray, X: np.ndarray, K: np.ndarray, R_gt: np.ndarray,
             t_gt: np.ndarray) -> np.ndarray:
    """est_EPnP_GN.csv rows: per frame EPnP + LM refinement on that frame's observations."""
    rows = []
    for k in range(len(R_gt)):
        o = obs[obs[:, 0] == k]
        z = np.ascontiguousarray(o[:, 2:4]).reshape(-1, 1, 2)
        Xk = np.ascontiguousarray(X[o[:, 1].astype(int)])
        ok, rvec, tvec = cv2.solvePnP(Xk, z, K, None, flags=cv2.SOLVEPNP_EPNP)
        if ok:
            rvec, tvec = cv2.solvePnPRefineLM(Xk, z, K, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0] if ok else np.full((3, 3), np.nan)
        t = tvec.ravel() if ok else np.full(3, np.nan)
        rot = rv._rot_err_deg(R, R_gt[k]) if ok else np.nan
        tr = rv._trans_err_pct(t, t_gt[k]) if ok else np.nan
        rows.append(np.concatenate(([k, float(ok)], R.ravel(), t, [rot, tr, 0.0])))
    return np.array(rows)


def make_trial(vector: Path, out: Path, level: float, trial: int) -> Path:
    """Write one trial of the protocol at noise `level` [px] into `out`."""
    _, gt0 = rv._read_csv(vector / 'gt_poses.csv')
    K = np.loadtxt(vector / 'K.csv', delimiter=',')
    rng = np.random.default_rng(1000 * int(level) + trial)
    n_frames = len(gt0)
    X = np.column_stack((rng.uniform(-2, 2, N_POINTS), rng.uniform(-2, 2, N_POINTS),
                         rng.uniform(4, 8, N_POINTS)))
    s_p = rng.uniform(0, level, N_POINTS)
    f = np.log10(1 + 100 * np.arange(n_frames) / 200) / 2
    R_gt = gt0[:, 1:10].reshape(-1, 3, 3)
    t_gt = gt0[:, 10:13]
    obs = []
    for k in range(n_frames):
        Xc = X @ R_gt[k].T + t_gt[k]
        clean = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
        sigma = s_p * f[k]
        noisy = clean + rng.normal(size=clean.shape) * sigma[:, None]
        obs.append(np.column_stack((np.full(N_POINTS, k), np.arange(N_POINTS), noisy, clean,
                                    sigma)))
    obs = np.concatenate(obs)
    gt = gt0.copy()
    gt[:, 16] = f
    gt[:, 17] = level * f                    # the nominal every reference method gets
    out.mkdir(parents=True, exist_ok=True)
    np.savetxt(out / 'K.csv', K, delimiter=',')
    _write_csv(out / 'points_world.csv', 'point_id,X,Y,Z,sigma_px',
               np.column_stack((np.arange(N_POINTS), X, s_p)))
    with open(vector / 'gt_poses.csv', encoding='utf-8') as fh:
        header = fh.readline().strip()
    _write_csv(out / 'gt_poses.csv', header, gt)
    _write_csv(out / 'obs.csv', 'frame,point_id,u,v,u_clean,v_clean,sigma_eff_px', obs)
    _write_csv(out / 'est_EPnP_GN.csv', 'frame,status,r11,r12,r13,r21,r22,r23,r31,r32,r33,'
               'tx,ty,tz,rot_err_deg,trans_err_pct,time_ms',
               _epnp_gn(obs, X, K, R_gt, t_gt))
    return out


def run_trials(levels: list[float], trials: int, work: Path) -> list[dict]:
    vector = shared_data('ekfpnp_synthetic_sigma3')
    if vector is None:
        raise FileNotFoundError('../shared/data/ekfpnp_synthetic_sigma3 is absent (the '
                                'camera path of the protocol)')
    rows = []
    for level in levels:
        for trial in range(trials):
            folder = make_trial(vector, work / f'level{level:g}_trial{trial}', level, trial)
            row = {'level_px': level, 'trial': trial}
            for model in ('fixed', 'adaptive'):
                r = rv.run(folder, 'nominal', model)
                ref = r['reference']['EPnP_GN']
                row[model] = {
                    'rot_ratio': r['ours']['rot_err_deg_mean'] / ref['rot_err_deg_mean'],
                    'trans_ratio': r['ours']['trans_err_pct_mean'] /
                    ref['trans_err_pct_mean'],
                    'nees_mean': r['ours']['nees_mean']}
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--levels', nargs='+', type=float, default=[1.0, 3.0, 5.0])
    p.add_argument('--trials', type=int, default=5)
    p.add_argument('--work', type=Path, help='write the trial folders here (kept)')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory(prefix='ekfpnp_trials_') as tmp:
            rows = run_trials(args.levels, args.trials, args.work or Path(tmp))
    except FileNotFoundError as exc:
        print(f'bench.ekfpnp_trials: error: {exc}', file=sys.stderr)
        return 2
    print('ours / EPnP+LM (OpenCV, identical inputs) per trial, our filter told the nominal '
          'sigma only (EKFPnP: 0.43-0.59 against the weaker toolbox EPnP+GN)')
    print(f'{"level px":>8} {"trial":>5} {"fixed rot":>10} {"fixed trans":>11} '
          f'{"adaptive rot":>12} {"adaptive trans":>14} {"NEES adaptive":>13}')
    for r in rows:
        print(f'{r["level_px"]:8g} {r["trial"]:5d} {r["fixed"]["rot_ratio"]:10.2f} '
              f'{r["fixed"]["trans_ratio"]:11.2f} {r["adaptive"]["rot_ratio"]:12.2f} '
              f'{r["adaptive"]["trans_ratio"]:14.2f} {r["adaptive"]["nees_mean"]:13.2f}')
    for model in ('fixed', 'adaptive'):
        rot = [r[model]['rot_ratio'] for r in rows]
        tr = [r[model]['trans_ratio'] for r in rows]
        print(f'{model}: rotation ratio {min(rot):.2f}-{max(rot):.2f} (mean {np.mean(rot):.2f}),'
              f' translation {min(tr):.2f}-{max(tr):.2f} (mean {np.mean(tr):.2f})')
    if args.json:
        write_json(args.json, {'rows': rows})
    return 0


if __name__ == '__main__':
    sys.exit(main())

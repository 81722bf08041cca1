"""Real sequences: EKF vs iterated EKF vs per-frame EPnP (docs/method.md §9.4, "Real").

Wraps `real_data.compare` (the core offline, images in) on KITTI 06 frames 0-50
(monocular bootstrap from the images, ATE after Sim(3) alignment) and Middlebury dino
views 1-48 (the paper's protocol: the first two ground-truth poses fix the scale), several
seeds per estimator (RANSAC and the 1-point hypotheses are random), mean and std.

    python -m bench.real_compare [--quick] [--out DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

from .common import pyplot, section_main, shared_data
from .real_data import compare

SEQUENCES = ('kitti06_f0-50', 'middlebury_dino')
ESTIMATORS = ('ekf', 'iekf', 'epnp')


def run(quick: bool = False, out: Path | None = None) -> dict:
    runs = 2 if quick else 8
    res: dict = {'runs': runs}
    for name in SEQUENCES:
        if shared_data(name) is None:
            res[name] = {'skipped': f'../shared/data/{name} is absent'}
            continue
        res[name] = compare(name, ESTIMATORS, runs)
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    seqs = [s for s in SEQUENCES if 'skipped' not in res[s]]
    if not seqs:
        return []
    metrics = (('ate_pct_path', 'ATE (Sim3) [% of path]'),
               ('rpe_rot_rmse_deg', 'RPE rotation RMSE [deg]'),
               ('rot_drift_mean_deg', 'rotation drift, mean [deg]'))
    fig, ax = plt.subplots(len(seqs), 3, figsize=(13, 3.6 * len(seqs)), squeeze=False)
    colors = {'ekf': 'tab:blue', 'iekf': 'tab:green', 'epnp': 'tab:red'}
    for i, s in enumerate(seqs):
        for j, (key, label) in enumerate(metrics):
            m = [res[s][e][key]['mean'] for e in ESTIMATORS]
            sd = [res[s][e][key]['std'] for e in ESTIMATORS]
            ax[i, j].bar(ESTIMATORS, m, yerr=sd, color=[colors[e] for e in ESTIMATORS],
                         capsize=4)
            ax[i, j].set(title=f'{s}: {label}')
            ax[i, j].grid(alpha=0.3, axis='y')
    fig.suptitle(f'real sequences, mean +- std over {res["runs"]} seeds')
    fig.tight_layout()
    p = out / 'real_data.png'
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return [p.name]


def _summarize(res: dict) -> None:
    for s in SEQUENCES:
        print(s, {e: {k: round(v['mean'], 3) for k, v in res[s][e].items()
                      if isinstance(v, dict) and 'mean' in v}
                  for e in ESTIMATORS} if 'skipped' not in res[s] else res[s])


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'real_compare', _summarize)


if __name__ == '__main__':
    sys.exit(main())

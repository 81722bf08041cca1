"""NEES of the camera EKF's pose covariance on smooth synthetic orbits (docs/method.md §11.2).

The product publishes the EKF covariance, so it must be consistent: the normalised
estimation error squared e^T P^-1 e of the 6-dof pose (position, world rotation vector)
averages 6 when the covariance is honest. Protocol: 300 points in a 4 m cube, a camera
on `synth_points.smooth_orbit` (6 m radius, all six DoF varying, 30 Hz, 200 frames), 1 px
pixel noise, exact map, ground-truth start (synth_points.run_ekf); the bunny section
adds the same figure on the paper's bunny path.

    python -m bench.consistency [--quick]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ekf_vo.tools.synth_points import Sequence, run_ekf, smooth_orbit
from .bunny import anees_bounds

SIGMA_PX = 1.0
RATE_HZ = 30.0


def run(quick: bool = False, out=None) -> dict:
    runs = 3 if quick else 10
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    nees = []
    for seed in range(runs):
        rng = np.random.default_rng([seed, 11])
        X = rng.uniform(-2.0, 2.0, (300, 3))
        T, t = smooth_orbit(200, RATE_HZ, radius=6.0, seed=seed)
        seq = Sequence(K, X, T, t)
        nees.append(run_ekf(seq, SIGMA_PX, rng)['nees'])
    nees = np.array(nees)
    lo, hi = anees_bounds(runs)
    anees = nees.mean(axis=0)
    return {'runs': runs, 'frames_per_run': nees.shape[1], 'sigma_px': SIGMA_PX,
            'nees_mean': float(nees.mean()), 'nees_median': float(np.median(nees)),
            'dof': 6, 'anees_95_bounds': [lo, hi],
            'frac_frames_anees_in_bounds': float(np.mean((anees > lo) & (anees < hi)))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true')
    args = parser.parse_args(argv)
    print(run(args.quick))
    return 0


if __name__ == '__main__':
    sys.exit(main())

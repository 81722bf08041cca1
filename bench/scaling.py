"""Cost of one EKF update against the number of observed points: hybrid vs EKF-SLAM.

The hybrid method's reason to exist (docs/method.md §1): with the map out of the state,
the camera-only update (13 states, Woodbury gain: a 13x13 solve) costs O(n) in the number
n of observed points, while filter SLAM with the points in the state (13 + 3n) needs the
2n x 2n innovation covariance and the (13+3n)^2 covariance update: O(n^3).

Timed with single-threaded BLAS (a child process), best of several repetitions.
Both updates run on the SAME data: n points 2-20 m in front of a camera, the same prior on
the camera, one noisy image of the points. The SLAM update is a minimal, correct textbook
EKF (no sparsity tricks beyond forming P H^T from the blocks of H, which every EKF-SLAM
does): z = h(camera, points), H = [H_cam | blockdiag(H_point_i)], S = H P H^T + R,
K = P H^T S^-1 (Cholesky), x += K y, P = P - K S K^T. A correctness check: with
zero point covariance its camera estimate equals the camera-only update's.

    python -m bench.scaling [--quick] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ekf_vo.core import geometry as geo
from ekf_vo.core.ekf import POS, QUAT, STATE_DIM, CameraEKF
from .common import pyplot, write_json

N_POINTS = (50, 100, 200, 500, 1000, 2000, 5000)
SIGMA_PX = 1.0
POINT_SIGMA_M = 0.05
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def make_problem(n: int, seed: int = 0) -> tuple[CameraEKF, np.ndarray, np.ndarray]:
    """A camera EKF with a prior, n points in view and their noisy pixels."""
    rng = np.random.default_rng([seed, n])
    ekf = CameraEKF(K)
    ekf.initialise(np.eye(4), np.array([0.5, 0, 0]), np.zeros(3), 0.01, 0.1, 0.1)
    depth = rng.uniform(2.0, 20.0, n)
    px = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    X = np.column_stack(((px[:, 0] - 320) / 500 * depth, (px[:, 1] - 240) / 500 * depth,
                         depth))
    true_T = geo.make_T(geo.quat_to_matrix(geo.rotvec_to_quat(np.array([0.003, -0.002, 0.001]))),
                        np.array([0.01, -0.005, 0.008]))
    Xc = geo.transform_points(geo.invert_T(true_T), X)
    z = np.column_stack((500 * Xc[:, 0] / Xc[:, 2] + 320, 500 * Xc[:, 1] / Xc[:, 2] + 240))
    return ekf, X, z + rng.normal(0, SIGMA_PX, z.shape)


def slam_update(x_cam: np.ndarray, X: np.ndarray, P: np.ndarray, z: np.ndarray,
                sigma_px: float, ekf: CameraEKF) -> tuple[np.ndarray, np.ndarray]:
    """One full-state EKF-SLAM update. State [camera (13), X_1..X_n (3 each)], P (13+3n)^2.

    The observation of point i depends on the camera pose and on X_i only:
    d(u,v)/dX_i = -d(u,v)/dr (the point enters as X_i - r). Returns (x+, P+)."""
    n = len(X)
    px, _, Hc = ekf.observe(X, x_cam)                       # (n,2), H_cam (2n,13)
    Hp = -Hc.reshape(n, 2, STATE_DIM)[:, :, POS]            # (n,2,3) point blocks
    y = (z - px).reshape(-1)
    # P H^T from the blocks: camera columns plus each point's own 3 columns
    PHt = P[:, :STATE_DIM] @ Hc.T                           # (D, 2n)
    Pp = P[:, STATE_DIM:].reshape(len(P), n, 3)             # (D, n, 3)
    PHt += np.einsum('dni,nri->dnr', Pp, Hp).reshape(len(P), 2 * n)
    # S = H (P H^T) + R: rows of H are sparse the same way
    HPHt = Hc @ PHt[:STATE_DIM]
    HPHt += np.einsum('nri,nic->nrc', Hp, PHt[STATE_DIM:].reshape(n, 3, 2 * n)
                      ).reshape(2 * n, 2 * n)
    S = HPHt + np.eye(2 * n) * sigma_px ** 2
    cf = cho_factor(S, lower=True, check_finite=False)
    Kt = cho_solve(cf, PHt.T, check_finite=False)           # (2n, D) = K^T
    x = np.concatenate((x_cam, X.reshape(-1))) + Kt.T @ y
    P = P - PHt @ Kt                                        # P - K S K^T = P - K H P
    return x, 0.5 * (P + P.T)


def slam_prior(ekf: CameraEKF, n: int, point_sigma: float) -> np.ndarray:
    D = STATE_DIM + 3 * n
    P = np.zeros((D, D))
    P[:STATE_DIM, :STATE_DIM] = ekf.P
    P[STATE_DIM:, STATE_DIM:] = np.eye(3 * n) * point_sigma ** 2
    return P


def _times_ms(fn, reps: int) -> tuple[float, float]:
    """(minimum, median) wall time of `reps` calls, ms. The slopes are fitted on the
    minimum: on a shared machine the median picks up other processes' load (BLAS threads
    waiting for a core), the minimum is the cost of the computation itself."""
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.min(ts)) * 1e3, float(np.median(ts)) * 1e3


def check_equivalence(n: int = 50) -> float:
    """Max |camera state difference| between the SLAM update with (near) zero point
    covariance and the camera-only update; ~0 if both are correct."""
    ekf, X, z = make_problem(n)
    x0 = ekf.x.copy()
    x_slam, _ = slam_update(x0, X, slam_prior(ekf, n, 0.0), z, SIGMA_PX, ekf)
    ekf.update(z, X, SIGMA_PX, iterations=1)
    q = x_slam[QUAT] / np.linalg.norm(x_slam[QUAT])
    return float(max(np.max(np.abs(x_slam[POS] - ekf.x[POS])), np.max(np.abs(
        q - ekf.x[QUAT]))))


def fit_slope(n: list, t: list, n_min: int = 200) -> float:
    """Least-squares slope of log t against log n over n >= n_min (the asymptotic part;
    fixed per-call overheads dominate below)."""
    n, t = np.asarray(n, float), np.asarray(t, float)
    sel = n >= n_min
    if np.count_nonzero(sel) < 2:
        sel = np.ones_like(n, bool)
    return float(np.polyfit(np.log(n[sel]), np.log(t[sel]), 1)[0])


def run(quick: bool = False, out: Path | None = None) -> dict:
    """Measure in a child process with single-threaded BLAS (OPENBLAS_NUM_THREADS=1 etc.
    must be set before numpy loads): one core per update is the fair comparison, and on a
    shared machine multi-threaded BLAS timings mostly measure waiting for the other core."""
    if os.environ.get('OPENBLAS_NUM_THREADS') == '1':
        res = measure(quick)
    else:
        env = dict(os.environ, OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1',
                   MKL_NUM_THREADS='1')
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, '-m', 'bench.scaling', '--measure-only',
                   '--out', tmp] + (['--quick'] if quick else [])
            subprocess.run(cmd, env=env, check=True, cwd=Path(__file__).resolve().parents[1])
            res = json.loads((Path(tmp) / 'scaling.json').read_text())
    res['blas_threads'] = 1
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def measure(quick: bool = False) -> dict:
    slam_cap = 1000 if quick else 2000
    ns = [n for n in N_POINTS if not quick or n <= 2000]
    cam_ms, slam_n, slam_ms, slam_mb = [], [], [], []
    cam_med, slam_med = [], []
    for n in ns:
        ekf, X, z = make_problem(n)
        x0, P0 = ekf.x.copy(), ekf.P.copy()

        def cam():
            ekf.x, ekf.P = x0.copy(), P0.copy()
            ekf.update(z, X, SIGMA_PX, iterations=1)
        t_min, t_med = _times_ms(cam, 11 if quick else 31)
        cam_ms.append(t_min)
        cam_med.append(t_med)
        if n <= slam_cap:
            P = slam_prior(ekf, n, POINT_SIGMA_M)
            reps = 7 if n <= 200 else (3 if n <= 500 else (2 if n <= 1000 else 1))
            t_min, t_med = _times_ms(lambda: slam_update(x0, X, P, z, SIGMA_PX, ekf), reps)
            slam_ms.append(t_min)
            slam_med.append(t_med)
            slam_n.append(n)
            D = STATE_DIM + 3 * n
            slam_mb.append((D * D + 2 * (2 * n) ** 2 + 2 * D * 2 * n) * 8 / 2 ** 20)
    res = {'n_points': ns, 'camera_only_ms': cam_ms, 'slam_n_points': slam_n,
           'slam_ms': slam_ms, 'camera_only_ms_median': cam_med, 'slam_ms_median': slam_med, 'slam_working_set_mb': slam_mb, 'slam_cap': slam_cap,
           'camera_only_slope': fit_slope(ns, cam_ms),
           'slam_slope': fit_slope(slam_n, slam_ms),
           'equivalence_max_abs_diff': check_equivalence(),
           'slope_fit_from_n': 200}
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.loglog(res['n_points'], res['camera_only_ms'], 'bo-',
              label=f'camera-only EKF, 13 states (slope {res["camera_only_slope"]:.2f})')
    ax.loglog(res['slam_n_points'], res['slam_ms'], 'rs-',
              label=f'EKF-SLAM, 13+3n states (slope {res["slam_slope"]:.2f})')
    n = np.array(res['n_points'], float)
    for p, ls in ((1, ':'), (3, '--')):
        ref = res['camera_only_ms'][-1] * (n / n[-1]) ** p if p == 1 else \
            res['slam_ms'][-1] * (n / res['slam_n_points'][-1]) ** p
        ax.loglog(n, ref, 'k' + ls, alpha=0.4, lw=1, label=f'O(n^{p}) reference')
    ax.set(xlabel='observed points n', ylabel='one update [ms] (best of several)',
           title='EKF update cost vs number of points')
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = out / 'scaling.png'
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return [p.name]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true')
    parser.add_argument('--out', type=Path, default=Path('bench/results'))
    parser.add_argument('--measure-only', action='store_true',
                        help='measure in this process, no plot (run() uses it)')
    args = parser.parse_args(argv)
    res = measure(args.quick) if args.measure_only else run(args.quick, args.out)
    write_json(args.out / 'scaling.json', res)
    if not args.measure_only:
        print(res)
    return 0


if __name__ == '__main__':
    sys.exit(main())

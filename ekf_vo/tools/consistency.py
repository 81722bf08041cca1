"""Rotation NEES of published poses against a ground truth: is the covariance honest?

docs/method.md §11.2. Each estimated pose's rotation error against the ground truth, with
the orientation aligned at the first associated frame (R_align = R_gt,0 R_est,0^T: a
position-based alignment says little about orientation when the camera barely moves),
is compared with the rotation block of its published covariance:

    e_k = log(R_gt,k (R_align R_est,k)^T)         world-frame rotation vector [rad]
    NEES_k = e_k^T (R_align Sigma_rot,k R_align^T)^-1 e_k     (3 dof)

An honest covariance gives a mean of 3 (median 2.37), and 0.1 % of the frames above the
chi-square(3) 99.9 % bound, 16.27. Poses and covariances are associated by stamp.

For a metric estimate (ekf-vo-eval --se3 --cov), :func:`pose_nees` checks the whole 6x6:
rigid alignment at the same first frame, T_align = T_gt,0 T_est,0^-1 (no scale), and

    e_k = (p_gt,k - p_est_aligned,k, log(R_gt,k R_est_aligned,k^T))       [m, rad]
    NEES_k = e_k^T (A Sigma_k A^T)^-1 e_k,  A = diag(R_align, R_align)      (6 dof)

mean 6 when honest, 0.1 % of the frames above the chi-square(6) 99.9 % bound, 22.46.

:func:`twist_nees` checks the published twist (what robot_localization fuses in
differential mode) against the ground truth's central differences, linear and angular
parts separately (3 dof each; the linear one needs a metric estimate).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core import geometry as geo

#: chi-square(3) 99.9 % quantile
CHI2_3DOF_999 = 16.266
#: chi-square(6) 99.9 % quantile
CHI2_6DOF_999 = 22.458
#: a covariance is skipped by :func:`pose_nees` when the smallest eigenvalue of its
#: correlation matrix is below this (singular / not positive definite), or it is non-finite
MIN_CORR_EIG = 1e-12


@dataclass
class RotationNees:
    """Rotation NEES per associated frame, and its summary."""

    mean: float
    median: float
    pct_above_999: float          #: % of frames above CHI2_3DOF_999
    n_frames: int
    times_s: np.ndarray = field(repr=False)      #: (n,) stamps of the frames
    nees: np.ndarray = field(repr=False)         #: (n,)
    err_deg: np.ndarray = field(repr=False)      #: (n,) rotation error angle
    sigma3_deg: np.ndarray = field(repr=False)   #: (n,) 3 sqrt(largest eigenvalue)

    def to_dict(self) -> dict:
        return {'rot_nees_mean': self.mean, 'rot_nees_median': self.median,
                'rot_nees_pct_above_99_9': self.pct_above_999,
                'rot_nees_frames': self.n_frames}


def _associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i into a, j into b) of the nearest stamps within max_dt."""
    order = np.argsort(a)
    pos = np.clip(np.searchsorted(a[order], b), 1, len(a) - 1)
    left, right = order[pos - 1], order[pos]
    best = np.where(np.abs(a[left] - b) <= np.abs(a[right] - b), left, right)
    ok = np.abs(a[best] - b) <= max_dt
    return best[ok], np.flatnonzero(ok)


def _matched(gt_stamps: np.ndarray, gt_T: np.ndarray, est_stamps: np.ndarray,
             est_T: np.ndarray, cov_stamps: np.ndarray, cov: np.ndarray,
             max_time_diff_s: float) -> tuple[np.ndarray, ...]:
    """(stamps, gt_T, est_T, cov) of the estimated poses that have a covariance (same stamp)
    and a ground-truth pose within max_time_diff_s. Raises ValueError when none does."""
    i_cov, j_est = _associate(np.asarray(cov_stamps, float), np.asarray(est_stamps, float),
                              1e-6)
    est_s, est_T, cov = est_stamps[j_est], est_T[j_est], cov[i_cov]
    i_gt, j = _associate(np.asarray(gt_stamps, float), est_s, max_time_diff_s)
    if len(j) == 0:
        raise ValueError('no estimated pose with a covariance matches the ground truth')
    return est_s[j], gt_T[i_gt], est_T[j], cov[j]


def _rot_err(R_gt: np.ndarray, R_est_aligned: np.ndarray) -> np.ndarray:
    """World-frame rotation vector [rad] of R_gt R_est_aligned^T."""
    return geo.quat_to_rotvec(geo.matrix_to_quat(R_gt @ R_est_aligned.T))


def rotation_nees(gt_stamps: np.ndarray, gt_T: np.ndarray, est_stamps: np.ndarray,
                  est_T: np.ndarray, cov_stamps: np.ndarray, cov: np.ndarray,
                  max_time_diff_s: float = 0.01) -> RotationNees:
    """Rotation NEES of the estimate (T_world_cam (n,4,4), covariances (m,6,6) with their
    stamps) against the ground truth. Raises ValueError when nothing associates."""
    stamps, gt_T, est_T, cov = _matched(gt_stamps, gt_T, est_stamps, est_T, cov_stamps,
                                        cov, max_time_diff_s)
    R_gt = gt_T[:, :3, :3]
    R_est = est_T[:, :3, :3]
    R_align = R_gt[0] @ R_est[0].T
    nees, err, sig3 = [], [], []
    for Rg, Re, C in zip(R_gt, R_est, cov):
        e = _rot_err(Rg, R_align @ Re)
        S = R_align @ C[3:, 3:] @ R_align.T
        nees.append(float(e @ np.linalg.solve(S, e)))
        err.append(np.degrees(np.linalg.norm(e)))
        sig3.append(3 * np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(S)))))
    nees = np.array(nees)
    return RotationNees(float(np.mean(nees)), float(np.median(nees)),
                        float(100 * np.mean(nees > CHI2_3DOF_999)), len(nees), stamps,
                        nees, np.array(err), np.array(sig3))


@dataclass
class PoseNees:
    """6-DoF pose NEES (position [m] + world rotation vector [rad]) per usable frame."""

    mean: float
    median: float
    pct_above_999: float          #: % of the usable frames above CHI2_6DOF_999
    n_frames: int                 #: usable frames (the NEES statistics are over these)
    n_skipped: int                #: matched frames skipped: non-finite or singular covariance
    times_s: np.ndarray = field(repr=False)      #: (n_frames,) stamps
    nees: np.ndarray = field(repr=False)         #: (n_frames,)

    def to_dict(self) -> dict:
        return {'pose_nees_mean': self.mean, 'pose_nees_median': self.median,
                'pose_nees_pct_above_99_9': self.pct_above_999,
                'pose_nees_frames': self.n_frames, 'pose_nees_skipped': self.n_skipped}


def _usable(S: np.ndarray) -> bool:
    """True if the covariance is finite and numerically positive definite (its correlation
    matrix's smallest eigenvalue > MIN_CORR_EIG): unit-free, so metres and radians mix."""
    if not np.all(np.isfinite(S)):
        return False
    d = np.diag(S)
    if np.any(d <= 0):
        return False
    corr = S / np.sqrt(np.outer(d, d))
    return bool(np.min(np.linalg.eigvalsh(0.5 * (corr + corr.T))) > MIN_CORR_EIG)


def pose_nees(gt_stamps: np.ndarray, gt_T: np.ndarray, est_stamps: np.ndarray,
              est_T: np.ndarray, cov_stamps: np.ndarray, cov: np.ndarray,
              max_time_diff_s: float = 0.01) -> PoseNees:
    """6-DoF pose NEES of a metric estimate (T_world_cam (n,4,4); covariances (m,6,6) over
    position and world rotation vector, with their stamps) against the ground truth, after a
    rigid alignment at the first matched pose (no scale). Frames whose covariance is
    non-finite or singular (see :func:`_usable`) are skipped and counted. Raises ValueError
    when nothing associates or no frame has a usable covariance."""
    stamps, gt_T, est_T, cov = _matched(gt_stamps, gt_T, est_stamps, est_T, cov_stamps,
                                        cov, max_time_diff_s)
    T_align = gt_T[0] @ geo.invert_T(est_T[0])
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = T_align[:3, :3]
    nees, keep = [], []
    for k, (Tg, Te, C) in enumerate(zip(gt_T, est_T, cov)):
        S = A @ C @ A.T
        if not _usable(S):
            continue
        Ta = T_align @ Te
        e = np.concatenate([Tg[:3, 3] - Ta[:3, 3], _rot_err(Tg[:3, :3], Ta[:3, :3])])
        nees.append(float(e @ np.linalg.solve(S, e)))
        keep.append(k)
    if not nees:
        raise ValueError(f'pose NEES: none of the {len(cov)} matched covariances is finite '
                         'and positive definite')
    nees = np.array(nees)
    return PoseNees(float(np.mean(nees)), float(np.median(nees)),
                    float(100 * np.mean(nees > CHI2_6DOF_999)), len(nees),
                    len(cov) - len(nees), stamps[keep], nees)


@dataclass
class TwistNees:
    """NEES of the published twist (camera frame) against the ground truth's, 3 dof each
    for the linear [m/s] and angular [rad/s] parts."""

    linear_mean: float
    linear_median: float
    linear_pct_above_999: float   #: % of frames above CHI2_3DOF_999
    angular_mean: float
    angular_median: float
    angular_pct_above_999: float
    n_frames: int

    def to_dict(self) -> dict:
        return {'twist_nees_linear_mean': self.linear_mean,
                'twist_nees_linear_median': self.linear_median,
                'twist_nees_linear_pct_above_99_9': self.linear_pct_above_999,
                'twist_nees_angular_mean': self.angular_mean,
                'twist_nees_angular_median': self.angular_median,
                'twist_nees_angular_pct_above_99_9': self.angular_pct_above_999,
                'twist_nees_frames': self.n_frames}


def gt_twist(gt_stamps: np.ndarray, gt_T: np.ndarray, k: int) -> np.ndarray | None:
    """(v, w) of the ground truth at sample k in its camera frame [m/s, rad/s], by central
    differences of its neighbours (None at the ends)."""
    if k < 1 or k >= len(gt_stamps) - 1:
        return None
    dt = float(gt_stamps[k + 1] - gt_stamps[k - 1])
    if not dt > 0:
        return None
    T0, T1 = gt_T[k - 1], gt_T[k + 1]
    v = gt_T[k][:3, :3].T @ (T1[:3, 3] - T0[:3, 3]) / dt
    w = geo.quat_to_rotvec(geo.matrix_to_quat(T0[:3, :3].T @ T1[:3, :3])) / dt
    return np.concatenate([v, w])


def twist_nees(gt_stamps: np.ndarray, gt_T: np.ndarray, est_stamps: np.ndarray,
               twist: np.ndarray, twist_cov: np.ndarray,
               max_time_diff_s: float = 0.01) -> TwistNees:
    """NEES of a metric estimate's twist (n,6) (v, w in the camera frame, as
    FrameResult.twist_cam) with its covariances (n,6,6), against central differences of
    the ground truth (which should be sampled at least at the frame rate). The angular
    part is scale-free; the linear part needs metres. Raises ValueError when nothing
    associates."""
    i_gt, j = _associate(np.asarray(gt_stamps, float), np.asarray(est_stamps, float),
                         max_time_diff_s)
    lin, ang = [], []
    for i, k in zip(i_gt, j):
        truth = gt_twist(gt_stamps, gt_T, int(i))
        C = twist_cov[k]
        if truth is None or not _usable(C):
            continue
        e = truth - twist[k]
        lin.append(float(e[:3] @ np.linalg.solve(C[:3, :3], e[:3])))
        ang.append(float(e[3:] @ np.linalg.solve(C[3:, 3:], e[3:])))
    if not lin:
        raise ValueError('twist NEES: no estimated twist matches the ground truth')
    lin, ang = np.array(lin), np.array(ang)
    return TwistNees(float(lin.mean()), float(np.median(lin)),
                     float(100 * np.mean(lin > CHI2_3DOF_999)), float(ang.mean()),
                     float(np.median(ang)), float(100 * np.mean(ang > CHI2_3DOF_999)),
                     len(lin))


def plot_rotation_nees(r: RotationNees, out_png: str | Path, title: str = '') -> Path:
    """Rotation error against 3 sigma over time, and the NEES with its 99.9 % bound."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    t = r.times_s - r.times_s[0]
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a.plot(t, r.err_deg, label='rotation error')
    a.plot(t, r.sigma3_deg, label='3 sigma (largest axis)')
    a.set_ylabel('deg')
    a.legend()
    a.set_title(title or 'rotation error vs published covariance')
    b.semilogy(t, np.maximum(r.nees, 1e-6), label='rotation NEES')
    b.axhline(CHI2_3DOF_999, color='r', ls='--', label='chi2(3) 99.9 %')
    b.axhline(3.0, color='g', ls=':', label='ideal mean 3')
    b.set_xlabel('time since first pose [s]')
    b.legend()
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out

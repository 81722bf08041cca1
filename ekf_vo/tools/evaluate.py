"""Trajectory evaluation against ground truth, built on evo's own machinery.

Pipeline (all evo 1.38 API, nothing re-implemented):

1. wrap both inputs in :class:`evo.core.trajectory.PoseTrajectory3D`;
2. associate by timestamp with :func:`evo.core.sync.associate_trajectories`
   (nearest stamp, ``max_diff`` seconds);
3. align a *copy* of the associated estimate to ground truth with Umeyama
   (:meth:`PoseTrajectory3D.align`, ``correct_scale=True`` -> Sim(3); a second copy with
   ``correct_scale=False`` -> SE(3));
4. compute :class:`evo.core.metrics.APE` / :class:`evo.core.metrics.RPE`.

Frames: all poses are ``T_world_cam`` (camera optical frame -> world).  The estimate's world
frame (and, for monocular VO, its scale) is arbitrary; the alignment maps it onto the
ground-truth world frame: ``p_gt ~= s * R @ p_est + t``.

Console script ``ekf-vo-eval GT EST [--json] [--plot FILE.png] [--max-diff 0.01] [--frames N]
[--se3] [--cov EST.cov]``; ``--se3`` is for a metric estimate: the SE(3) figures (no scale
fitted) head the output, and with ``--cov`` the 6-DoF pose NEES is reported too.
"""
from __future__ import annotations

import argparse
import copy
import json
import logging
import math
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ekf_vo.cli import UsageError, check_writable, entry_point
from ekf_vo.io.trajectory import GT_TOPIC, check_poses, is_bag_path, read_trajectory

logger = logging.getLogger(__name__)


class EvaluationError(RuntimeError):
    """The inputs cannot be evaluated (too few matches, degenerate geometry, bad shapes)."""


#: Minimum number of associated poses for a Sim(3) alignment.
MIN_MATCHED = 3


@dataclass
class EvalResult:
    """Evaluation of an estimated trajectory against ground truth.

    Units: metres, degrees, seconds.  "Aligned" means the estimate after the Sim(3) Umeyama
    alignment on the associated positions (scale applied), unless stated otherwise.

    Attributes:
        ate_sim3_rmse: ATE translation RMSE [m] after Sim(3) alignment (evo APE,
            ``PoseRelation.translation_part``).
        ate_sim3_mean: ATE translation mean [m] (Sim(3)).
        ate_sim3_median: ATE translation median [m] (Sim(3)).
        ate_sim3_max: ATE translation max [m] (Sim(3)).
        ate_se3_rmse: ATE translation RMSE [m] after rigid SE(3) alignment (no scale
            correction; large for monocular VO whose scale is arbitrary): the metric accuracy
            of an estimate that claims metres.
        ate_se3_pct_of_path: ``100 * ate_se3_rmse / path_length_gt_m`` [%].
        sim3_scale: Umeyama scale ``s`` applied to the estimate, ``p_gt ~= s R p_est + t``.
            If the estimate is ``k`` times the true size, ``sim3_scale ~= 1/k``.
        scale_error_pct: how far the estimate's size is from the truth,
            ``100 * (1 / sim3_scale - 1)`` [%]: positive = estimate too large (``k > 1``).
        rpe_trans_rmse: RPE translation RMSE [m] between consecutive *associated* poses
            (evo RPE, delta = 1, ``Unit.frames``), computed on the Sim(3)-aligned estimate,
            so it is in ground-truth metres.  If poses are missing, a "frame" pair spans the gap.
        rpe_rot_rmse_deg: RPE rotation-angle RMSE [deg] with the same pairs (alignment
            invariant).
        rot_err_mean_deg: mean absolute orientation error [deg] of the aligned estimate
            (evo APE, ``PoseRelation.rotation_angle_deg``).
        rot_err_max_deg: max absolute orientation error [deg] of the aligned estimate.
        rot_err_origin_mean_deg / rot_err_origin_max_deg: orientation error [deg] after
            aligning the first matched poses (evo ``align_origin``): the rotation drift
            accumulated since the start, independent of the position alignment.
        path_length_gt_m: ground-truth arc length [m] between the first and last associated
            timestamps, using every ground-truth pose in that interval.
        path_length_gt_total_m: arc length [m] of the whole ground-truth input.
        ate_sim3_pct_of_path: ``100 * ate_sim3_rmse / path_length_gt_m`` [%].
        n_gt: number of ground-truth poses given.
        n_est: number of estimated poses given.
        n_matched: number of associated (gt, est) pose pairs.
        pct_tracked: ``100 * n_matched / n_frames_total`` if ``n_frames_total`` was given,
            else ``100 * n_matched / n_gt`` [%].
        max_time_diff_s: association tolerance used [s].
        T_gt_est_sim3: (4, 4) alignment ``[[s R, t], [0, 1]]`` mapping estimate-world points
            into the ground-truth world frame.
        times_s: (M,) timestamps [s] of the associated estimate poses.
        trans_err_m: (M,) per-pose ATE translation error [m] (Sim(3)).
        rot_err_deg: (M,) per-pose orientation error [deg] (Sim(3)).
        gt_xyz: (M, 3) associated ground-truth positions (world).
        est_xyz_aligned: (M, 3) associated estimate positions after Sim(3) alignment.
        est_xyz_aligned_se3: (M, 3) associated estimate positions after SE(3) alignment.
        gt_xyz_full: (N_gt, 3) all ground-truth positions, time-sorted (for plotting).
    """

    ate_sim3_rmse: float
    ate_sim3_mean: float
    ate_sim3_median: float
    ate_sim3_max: float
    ate_se3_rmse: float
    ate_se3_pct_of_path: float
    sim3_scale: float
    scale_error_pct: float
    rpe_trans_rmse: float
    rpe_rot_rmse_deg: float
    rot_err_mean_deg: float
    rot_err_max_deg: float
    rot_err_origin_mean_deg: float
    rot_err_origin_max_deg: float
    path_length_gt_m: float
    path_length_gt_total_m: float
    ate_sim3_pct_of_path: float
    n_gt: int
    n_est: int
    n_matched: int
    pct_tracked: float
    max_time_diff_s: float
    T_gt_est_sim3: np.ndarray = field(repr=False)
    times_s: np.ndarray = field(repr=False)
    trans_err_m: np.ndarray = field(repr=False)
    rot_err_deg: np.ndarray = field(repr=False)
    gt_xyz: np.ndarray = field(repr=False)
    est_xyz_aligned: np.ndarray = field(repr=False)
    est_xyz_aligned_se3: np.ndarray = field(repr=False)
    gt_xyz_full: np.ndarray = field(repr=False)

    def to_dict(self, include_arrays: bool = False) -> dict[str, Any]:
        """JSON-serialisable dict: every scalar field plus ``T_gt_est_sim3`` (nested lists);
        per-pose arrays only if ``include_arrays``."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                if f.name == 'T_gt_est_sim3' or include_arrays:
                    out[f.name] = v.tolist()
            elif isinstance(v, (int, np.integer)):
                out[f.name] = int(v)
            else:
                out[f.name] = float(v)
        return out


def _check_input(name: str, stamps: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    try:
        stamps, T = check_poses(stamps, T)
    except ValueError as exc:
        raise EvaluationError(f'{name}: {exc}') from None
    if T.shape[0] == 0:
        raise EvaluationError(f'{name}: trajectory is empty')
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(T))):
        raise EvaluationError(f'{name}: non-finite stamps or poses')
    order = np.argsort(stamps, kind='stable')
    return stamps[order], T[order]


def _spread(xyz: np.ndarray) -> float:
    """Largest distance of a point from the centroid of (M, 3) positions."""
    return float(np.max(np.linalg.norm(xyz - xyz.mean(axis=0), axis=1)))


def evaluate(gt_stamps: np.ndarray, gt_T: np.ndarray,
             est_stamps: np.ndarray, est_T: np.ndarray,
             max_time_diff_s: float = 0.01,
             n_frames_total: Optional[int] = None) -> EvalResult:
    """Evaluate an estimated trajectory against ground truth with evo.

    Args:
        gt_stamps: (N_gt,) ground-truth timestamps [s].
        gt_T: (N_gt, 4, 4) ground-truth ``T_world_cam`` (camera optical -> world), metres.
        est_stamps: (N_est,) estimate timestamps [s], same clock as ``gt_stamps``.
        est_T: (N_est, 4, 4) estimated ``T_world_cam`` in the estimator's own world frame
            and scale.
        max_time_diff_s: max. |t_gt - t_est| for associating two poses [s].
        n_frames_total: number of camera frames fed to the estimator; denominator of
            ``pct_tracked`` (defaults to ``N_gt``).

    Returns:
        :class:`EvalResult`.

    Raises:
        EvaluationError: malformed or empty input, no / fewer than 3 associated poses,
            all-identical (or otherwise degenerate, e.g. collinear) positions.
    """
    from evo.core.trajectory import PoseTrajectory3D

    gt_stamps, gt_T = _check_input('ground truth', gt_stamps, gt_T)
    est_stamps, est_T = _check_input('estimate', est_stamps, est_T)
    n_gt, n_est = gt_T.shape[0], est_T.shape[0]

    traj_gt = PoseTrajectory3D(poses_se3=list(gt_T), timestamps=gt_stamps, name='ground truth')
    traj_est = PoseTrajectory3D(poses_se3=list(est_T), timestamps=est_stamps, name='estimate')
    gt_sync, est_sync = _associate(traj_gt, traj_est, max_time_diff_s)
    n_matched = gt_sync.num_poses
    logger.debug('associated %d of %d gt / %d est poses', n_matched, n_gt, n_est)
    est_sim3, est_se3, (r_a, t_a, s_a) = _align(gt_sync, est_sync)
    stats = _metrics(gt_sync, est_sync, est_sim3, est_se3)

    # GT arc length over the evaluated interval, at full GT rate (evo's path_length).
    t0, t1 = float(est_sync.timestamps[0]), float(est_sync.timestamps[-1])
    in_span = np.flatnonzero((gt_stamps >= t0 - max_time_diff_s)
                             & (gt_stamps <= t1 + max_time_diff_s))
    gt_span = copy.deepcopy(traj_gt)
    gt_span.reduce_to_ids(in_span)
    path_len = float(gt_span.path_length)
    pct = 100.0 / path_len if path_len > 0 else math.nan     # [% of path per metre]

    T_align = np.eye(4)
    T_align[:3, :3] = s_a * r_a
    T_align[:3, 3] = t_a

    denom = n_frames_total if n_frames_total is not None else n_gt
    if denom <= 0:
        raise EvaluationError(f'n_frames_total must be positive, got {n_frames_total}')

    result = EvalResult(
        **stats,
        sim3_scale=float(s_a),
        scale_error_pct=100.0 * (1.0 / float(s_a) - 1.0),
        path_length_gt_m=path_len,
        path_length_gt_total_m=float(traj_gt.path_length),
        ate_sim3_pct_of_path=pct * stats['ate_sim3_rmse'],
        ate_se3_pct_of_path=pct * stats['ate_se3_rmse'],
        n_gt=int(n_gt),
        n_est=int(n_est),
        n_matched=int(n_matched),
        pct_tracked=100.0 * n_matched / denom,
        max_time_diff_s=float(max_time_diff_s),
        T_gt_est_sim3=T_align,
        times_s=np.asarray(est_sync.timestamps, dtype=np.float64).copy(),
        gt_xyz=np.asarray(gt_sync.positions_xyz, dtype=np.float64).copy(),
        est_xyz_aligned=np.asarray(est_sim3.positions_xyz, dtype=np.float64).copy(),
        est_xyz_aligned_se3=np.asarray(est_se3.positions_xyz, dtype=np.float64).copy(),
        gt_xyz_full=np.asarray(traj_gt.positions_xyz, dtype=np.float64).copy(),
    )
    logger.info('ATE Sim(3) RMSE %.4f m (%.2f %% of %.2f m), scale %.4f, %d matched',
                result.ate_sim3_rmse, result.ate_sim3_pct_of_path, path_len, s_a, n_matched)
    return result


def _associate(traj_gt: Any, traj_est: Any, max_time_diff_s: float) -> tuple[Any, Any]:
    """Associated copies ``(gt_sync, est_sync)`` (evo, nearest stamp within the tolerance);
    EvaluationError for fewer than :data:`MIN_MATCHED` pairs or identical positions."""
    from evo.core import sync

    try:
        gt_sync, est_sync = sync.associate_trajectories(traj_gt, traj_est,
                                                        max_diff=max_time_diff_s)
    except sync.SyncException as exc:
        raise EvaluationError(f'no associated poses: {exc}') from exc
    n_matched = gt_sync.num_poses
    if n_matched < MIN_MATCHED:
        raise EvaluationError(
            f'only {n_matched} associated poses (need >= {MIN_MATCHED}) with max time '
            f'diff {max_time_diff_s} s')
    for name, xyz in (('ground truth', gt_sync.positions_xyz),
                      ('estimate', est_sync.positions_xyz)):
        if _spread(xyz) < 1e-9:
            raise EvaluationError(
                f'{name}: all associated positions are identical; Sim(3) alignment undefined')
    return gt_sync, est_sync


def _align(gt_sync: Any, est_sync: Any) -> tuple[Any, Any, tuple[np.ndarray, np.ndarray, float]]:
    """``(Sim(3)-aligned copy, SE(3)-aligned copy, (R, t, s) of the Sim(3) alignment)`` of the
    associated estimate (Umeyama); ``est_sync`` itself stays untouched."""
    from evo.core.geometry import GeometryException

    # evo's align() works in place: align copies, keep est_sync untouched.
    est_sim3 = copy.deepcopy(est_sync)
    est_se3 = copy.deepcopy(est_sync)
    try:
        r_a, t_a, s_a = est_sim3.align(gt_sync, correct_scale=True)
        est_se3.align(gt_sync, correct_scale=False)
    except GeometryException as exc:
        raise EvaluationError(f'degenerate geometry, Umeyama alignment failed: {exc}') from exc
    if not (np.isfinite(s_a) and s_a > 0):
        raise EvaluationError(f'degenerate Sim(3) alignment (scale {s_a})')
    return est_sim3, est_se3, (r_a, t_a, s_a)


def _metrics(gt_sync: Any, est_sync: Any, est_sim3: Any, est_se3: Any) -> dict[str, Any]:
    """The evo APE / RPE statistics and per-pose errors of :class:`EvalResult`."""
    from evo.core import metrics

    def ape(relation: Any, est: Any) -> Any:
        metric = metrics.APE(relation)
        metric.process_data((gt_sync, est))
        return metric

    def rpe(relation: Any) -> Any:
        metric = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames,
                             all_pairs=False)
        metric.process_data((gt_sync, est_sim3))
        return metric

    trans, angle = metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg
    ape_t = ape(trans, est_sim3)
    ape_r = ape(angle, est_sim3)
    ape_t_se3 = ape(trans, est_se3)
    # Orientation error relative to the start (evo align_origin): what a robot using the
    # odometry sees. The Sim(3) alignment fits positions only, so on a near-straight path
    # (KITTI) its rotation about the direction of travel is arbitrary and the aligned
    # orientation error above mostly measures that, not the estimator.
    est_origin = copy.deepcopy(est_sync)
    est_origin.align_origin(gt_sync)
    ape_r0 = ape(angle, est_origin)
    rpe_t = rpe(trans)
    rpe_r = rpe(angle)
    stat = metrics.StatisticsType
    return {
        'ate_sim3_rmse': float(ape_t.get_statistic(stat.rmse)),
        'ate_sim3_mean': float(ape_t.get_statistic(stat.mean)),
        'ate_sim3_median': float(ape_t.get_statistic(stat.median)),
        'ate_sim3_max': float(ape_t.get_statistic(stat.max)),
        'ate_se3_rmse': float(ape_t_se3.get_statistic(stat.rmse)),
        'rpe_trans_rmse': float(rpe_t.get_statistic(stat.rmse)),
        'rpe_rot_rmse_deg': float(rpe_r.get_statistic(stat.rmse)),
        'rot_err_mean_deg': float(ape_r.get_statistic(stat.mean)),
        'rot_err_max_deg': float(ape_r.get_statistic(stat.max)),
        'rot_err_origin_mean_deg': float(ape_r0.get_statistic(stat.mean)),
        'rot_err_origin_max_deg': float(ape_r0.get_statistic(stat.max)),
        'trans_err_m': np.asarray(ape_t.error, dtype=np.float64).copy(),
        'rot_err_deg': np.asarray(ape_r.error, dtype=np.float64).copy(),
    }


def format_table(r: EvalResult) -> str:
    """Human-readable aligned summary table of an :class:`EvalResult`."""
    rows = [
        ('ATE Sim(3) RMSE', f'{r.ate_sim3_rmse:.4f} m  ({r.ate_sim3_pct_of_path:.2f} % of '
                            f'{r.path_length_gt_m:.2f} m path)'),
        ('ATE SE(3) RMSE (no scale fitted)',
         f'{r.ate_se3_rmse:.4f} m  ({r.ate_se3_pct_of_path:.2f} % of path)'),
        ('ATE Sim(3) mean / median / max',
         f'{r.ate_sim3_mean:.4f} / {r.ate_sim3_median:.4f} / {r.ate_sim3_max:.4f} m'),
        ('Sim(3) scale (gt/est)', f'{r.sim3_scale:.4f}'),
        ('Scale error (est too large if +)', f'{r.scale_error_pct:+.2f} %'),
        ('RPE trans RMSE (1 frame)', f'{r.rpe_trans_rmse:.4f} m'),
        ('RPE rot RMSE (1 frame)', f'{r.rpe_rot_rmse_deg:.3f} deg'),
        ('Rotation error mean / max', f'{r.rot_err_mean_deg:.3f} / {r.rot_err_max_deg:.3f} deg'),
        ('Rotation drift from start mean / max',
         f'{r.rot_err_origin_mean_deg:.3f} / {r.rot_err_origin_max_deg:.3f} deg'),
        ('Tracked', f'{r.pct_tracked:.1f} %'),
        ('Poses gt / est / matched', f'{r.n_gt} / {r.n_est} / {r.n_matched}'),
    ]
    width = max(len(k) for k, _ in rows)
    return '\n'.join(f'{k:<{width}}  {v}' for k, v in rows)


def plot_result(r: EvalResult, out_png: str | Path, title: str = '', se3: bool = False) -> Path:
    """Write a two-panel PNG: top view of GT and aligned estimate, translation error vs time.

    The top view uses the two world axes with the largest ground-truth extent.

    Args:
        r: evaluation result.
        out_png: output image path (parent directories are created).
        title: optional figure title.
        se3: show the SE(3)-aligned estimate and its error (metric estimate, no scale
            fitted) instead of the Sim(3)-aligned one.

    Returns:
        The written path.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    extent = np.ptp(r.gt_xyz_full, axis=0)
    a, b = sorted(np.argsort(extent)[::-1][:2].tolist())
    names = 'xyz'
    if se3:
        est = r.est_xyz_aligned_se3
        err = np.linalg.norm(est - r.gt_xyz, axis=1)
        kind, rmse, pct = 'SE(3)', r.ate_se3_rmse, r.ate_se3_pct_of_path
        label = f'estimate (SE(3) aligned, scale error {r.scale_error_pct:+.1f} %)'
    else:
        est, err = r.est_xyz_aligned, r.trans_err_m
        kind, rmse, pct = 'Sim(3)', r.ate_sim3_rmse, r.ate_sim3_pct_of_path
        label = f'estimate (Sim(3) aligned, s={r.sim3_scale:.3f})'

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 5))
    ax0.plot(r.gt_xyz_full[:, a], r.gt_xyz_full[:, b], '-', color='0.3', lw=1.5,
             label='ground truth')
    ax0.plot(est[:, a], est[:, b], '-', color='tab:blue', lw=1.0, label=label)
    ax0.plot(r.gt_xyz_full[0, a], r.gt_xyz_full[0, b], 'o', color='0.3', ms=5)
    ax0.plot(est[0, a], est[0, b], 'o', color='tab:blue', ms=4)
    ax0.set_xlabel(f'{names[a]} [m]')
    ax0.set_ylabel(f'{names[b]} [m]')
    ax0.set_aspect('equal', adjustable='datalim')
    ax0.grid(True, alpha=0.3)
    ax0.legend(loc='best', fontsize=8)
    ax0.set_title(f'Top view ({names[a]}-{names[b]})')

    t = r.times_s - r.times_s[0]
    ax1.plot(t, err, '-', color='tab:red', lw=1.0, label='translation error')
    ax1.axhline(rmse, color='k', ls='--', lw=0.8, label=f'RMSE {rmse:.4f} m')
    ax1.set_xlabel('time since first matched pose [s]')
    ax1.set_ylabel(f'ATE ({kind}) [m]')
    ax1.set_ylim(bottom=0.0)
    ax1.grid(True, alpha=0.3)
    ax1.legend(loc='best', fontsize=8)
    ax1.set_title(f'ATE {kind} {pct:.2f} % of path, {r.pct_tracked:.1f} % tracked')
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)
    logger.debug('wrote plot %s', out_png)
    return out_png


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='ekf-vo-eval',
        description='Evaluate an estimated trajectory (TUM) against ground truth with evo: '
                    'ATE after Sim(3)/SE(3) Umeyama alignment, RPE per frame, rotation error.')
    p.add_argument('gt', help='ground truth: TUM file, rosbag2 bag (directory/.mcap/.db3) '
                   'or ROS 1 .bag file')
    p.add_argument('est', help='estimated trajectory, TUM file')
    p.add_argument('--gt-topic', default=GT_TOPIC,
                   help=f'PoseStamped ground-truth topic when GT is a bag (default {GT_TOPIC})')
    p.add_argument('--max-diff', type=float, default=0.01,
                   help='max. timestamp difference for association [s] (default 0.01)')
    p.add_argument('--frames', type=int, default=None,
                   help='total number of camera frames (denominator of %% tracked; '
                        'default: number of GT poses)')
    p.add_argument('--json', action='store_true', help='print all fields as JSON')
    p.add_argument('--json-arrays', action='store_true',
                   help='with --json, also include the per-pose arrays')
    p.add_argument('--plot', metavar='FILE.png', default=None,
                   help='write a top-view + error-over-time figure')
    p.add_argument('--cov', metavar='EST.cov', default=None,
                   help='the poses\' covariances (ekf-vo-run --cov): adds the rotation NEES '
                   '(orientation aligned at the first pose; docs/method.md §11.2), and with '
                   '--se3 the 6-DoF pose NEES (rigid alignment at the first pose)')
    p.add_argument('--nees-plot', metavar='FILE.png', default=None,
                   help='with --cov: rotation error against 3 sigma, and the NEES, over time')
    p.add_argument('--se3', action='store_true',
                   help='the estimate is metric (e.g. ekf-vo-run --set '
                   'scale_source=camera_height): the SE(3) ATE (no scale fitted) and the scale '
                   'error head the output, --plot shows the SE(3)-aligned estimate, and --cov '
                   'adds the 6-DoF pose NEES')
    p.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    return p


def _check_plot_path(path: str) -> None:
    """UsageError unless matplotlib can write ``path`` (format from its suffix, writable)."""
    from matplotlib.figure import Figure
    formats = Figure().canvas.get_supported_filetypes()
    suffix = Path(path).suffix.lower().lstrip('.')
    if suffix not in formats:
        raise UsageError(f'--plot {path}: unsupported image format {suffix!r} '
                         f'(use one of {", ".join(sorted(formats))})')
    check_writable(path, '--plot')


@entry_point
def main(argv: Optional[Sequence[str]] = None) -> int:
    """Console entry point ``ekf-vo-eval``. Returns the process exit code."""
    args = _build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format='%(levelname)s %(name)s: %(message)s')
    if args.nees_plot and not args.cov:
        print('ekf-vo-eval: error: --nees-plot needs --cov', file=sys.stderr)
        return 2
    for p in (args.gt, args.est) + ((args.cov,) if args.cov else ()):
        if not Path(p).exists():
            print(f'ekf-vo-eval: error: {p} does not exist', file=sys.stderr)
            return 2
    try:
        if args.plot:
            _check_plot_path(args.plot)
    except UsageError as exc:
        print(f'ekf-vo-eval: error: {exc}', file=sys.stderr)
        return 2
    try:
        gt_stamps, gt_T = read_trajectory(args.gt, args.gt_topic)
        if is_bag_path(args.est):
            print('ekf-vo-eval: error: EST must be a TUM file', file=sys.stderr)
            return 2
        est_stamps, est_T = read_trajectory(args.est)
        res = evaluate(gt_stamps, gt_T, est_stamps, est_T,
                       max_time_diff_s=args.max_diff, n_frames_total=args.frames)
        nees = pnees = None
        if args.cov:
            from ..io.trajectory import read_covariances
            from .consistency import pose_nees, rotation_nees
            covs = read_covariances(args.cov)
            nees = rotation_nees(gt_stamps, gt_T, est_stamps, est_T, *covs, args.max_diff)
            if args.se3:
                pnees = pose_nees(gt_stamps, gt_T, est_stamps, est_T, *covs, args.max_diff)
    except (ValueError, EvaluationError) as exc:
        print(f'ekf-vo-eval: error: {exc}', file=sys.stderr)
        return 1
    except OSError as exc:
        print(f'ekf-vo-eval: error: cannot read {exc.filename}: {exc.strerror}',
              file=sys.stderr)
        return 1
    if args.plot:
        plot_result(res, args.plot, title=f'{Path(args.est).name} vs {Path(args.gt).name}',
                    se3=args.se3)
    if args.nees_plot:
        from .consistency import plot_rotation_nees
        plot_rotation_nees(nees, args.nees_plot, title=f'{Path(args.est).name}')
    _print_results(args, res, nees, pnees)
    return 0


def metric_line(r: EvalResult) -> str:
    """One-line metric (SE(3), no scale fitted) summary: the headline of ``--se3``."""
    return (f'metric (SE(3), no scale fitted): ATE {r.ate_se3_rmse:.4f} m = '
            f'{r.ate_se3_pct_of_path:.2f} % of path; scale error {r.scale_error_pct:+.2f} %')


def _print_results(args: argparse.Namespace, res: EvalResult, nees: Any, pnees: Any) -> None:
    """stdout of ``ekf-vo-eval``: JSON, or the table and the NEES lines (metric line first
    with ``--se3``)."""
    if args.json:
        out = res.to_dict(include_arrays=args.json_arrays)
        for n in (nees, pnees):
            out.update(n.to_dict() if n is not None else {})
        print(json.dumps(out, indent=2))
        return
    if args.se3:
        print(metric_line(res))
    print(format_table(res))
    if nees is not None:
        print(f'rotation NEES (3 dof, 3 ideal; orientation aligned at the first pose): '
              f'mean {nees.mean:.2f}, median {nees.median:.2f}, '
              f'{nees.pct_above_999:.1f} % of {nees.n_frames} frames above the 99.9 % '
              f'bound')
    if pnees is not None:
        skipped = (f' ({pnees.n_skipped} frames skipped: non-finite or singular covariance)'
                   if pnees.n_skipped else '')
        print(f'pose NEES (6 dof, 6 ideal; rigid alignment at the first pose, no scale): '
              f'mean {pnees.mean:.2f}, median {pnees.median:.2f}, '
              f'{pnees.pct_above_999:.1f} % of {pnees.n_frames} frames above the 99.9 % '
              f'bound{skipped}')
    if args.plot:
        print(f'plot: {args.plot}')


if __name__ == '__main__':
    sys.exit(main())

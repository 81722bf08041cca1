"""Every experiment of the papers (docs/method.md) in one run: report.md, results.json, PNG plots, summary.

    python -m bench.run_all --out bench/results [--quick]

Sections (one module each, `run(quick, out) -> dict`):
  1 bunny            the EKFPnP paper's synthetic experiment + noise sweep + NEES
  2 fading_memory    turntable sequences with model error, S = 1.000..1.020
  3 precise_points   fraction of map points reprojecting within 1 px per image
  4 real_compare     KITTI 06 f0-50 and Middlebury dino: EKF / IEKF / EPnP
  5 throughput       frames/s, per-stage ms, ROS latency
  6 scaling          update time vs points: camera-only EKF vs EKF-SLAM
  7 memory           RSS, map size and frames/s over a 10,000-frame run
  + consistency      NEES on smooth synthetic orbits
  + local_map        KITTI 06 as raw / JPEG bags, CameraInfo before / after: local map vs
                     points triangulated once (bench/local_map.py builds its own rows)
`--quick` (CI) runs every section smaller (fewer runs, frames and sizes); its figures
are noisier and the report says so. A section that fails is reported and makes the exit
status non-zero; the others still run.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import math
import sys
import time
import traceback
from pathlib import Path

from .common import machine, write_json

logger = logging.getLogger(__name__)

SECTIONS = ('bunny', 'consistency', 'fading_memory', 'precise_points', 'real_compare',
            'local_map', 'throughput', 'scaling', 'memory')


def _f(x, p: int = 2) -> str:
    """Number for a table; '-' for missing / NaN."""
    if x is None:
        return '-'
    try:
        if isinstance(x, float) and not math.isfinite(x):
            return '-'
        return f'{x:.{p}f}'
    except (TypeError, ValueError):
        return str(x)


def _yes(b: bool) -> str:
    return 'yes' if b else '**no**'


def _table(header: list[str], rows: list[list]) -> str:
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(str(c) for c in r) + ' |' for r in rows]
    return '\n'.join(lines)


# ============================================================================ summary
def _rows_bunny(b: dict) -> list[list[str]]:
    """Summary rows: EKF vs EPnP on the bunny, the noise sweep, NEES."""
    rows = []
    r = b['ratio_ekf_over_epnp']
    rows.append(['bunny sigma=3px: EKF error / EPnP error (trans, rot)',
                 f'{_f(r["trans"])}, {_f(r["rot"])}',
                 'EPnP above EKF everywhere (paper, qualitative)',
                 'EKF better' if max(r.values()) < 1 else 'not reproduced'])
    c = b['checks']
    rows.append(['bunny: poses where EPnP error > EKF error (trans, rot)',
                 f'{100 * c["frac_poses_epnp_above_ekf_trans"]:.0f} %, '
                 f'{100 * c["frac_poses_epnp_above_ekf_rot"]:.0f} %', '100 %',
                 'reproduced' if c['epnp_above_ekf_everywhere_trans'] else 'not everywhere'])
    sw = b['sweep']
    rows.append(['bunny noise sweep: EPnP at 0 px / at 5 px (trans % path)',
                 f'{sw["epnp_trans"][0]:.1e} / {_f(sw["epnp_trans"][-1], 3)} '
                 f'(EKF {_f(sw["ekf_trans"][0], 3)} / {_f(sw["ekf_trans"][-1], 3)})',
                 'EPnP ~0 at 0 px, very noise-sensitive; EKF much less',
                 'partly: EPnP ~0 at 0 px, EKF grows slower' if sw['ekf_trans'][-1] <
                 sw['epnp_trans'][-1] else 'not reproduced'])
    rows.append(['bunny EKF pose NEES (mean, 6 ideal; filter told the true noise, exact '
                 'map, ground-truth start)', _f(b['nees']['ekf_mean']),
                 'n/a (not reported)', 'consistent' if 4.5 < b['nees']['ekf_mean'] < 8
                 else 'inconsistent'])
    return rows


def _rows_consistency(c: dict) -> list[list[str]]:
    """Summary rows: NEES on the smooth orbits."""
    return [['orbit EKF pose NEES (mean, 6 ideal; filter told the true noise, exact map, '
             'ground-truth start)', _f(c['nees_mean']), 'n/a',
             'consistent' if 4.5 < c['nees_mean'] < 8 else 'inconsistent']]


def _rows_fading_memory(fm: dict) -> list[list[str]]:
    """Summary rows: best S and the three turntable cases."""
    rows = []
    s = fm['focal']['summary']
    rows.append(['fading memory (2 % focal error): best S on (a)',
                 _f(s['S_tuned_on_a'], 3), '1.009', 'effect tiny, see section 2'])
    rows.append(['(b) yaw+pitch 20: heading / pitch error reduction [deg]',
                 f'{_f(s["b_yaw20_pitch20"]["heading_reduction_deg"], 4)} / '
                 f'{_f(s["b_yaw20_pitch20"]["pitch_reduction_deg"], 4)}',
                 '2.4158 / 0.1782', 'not reproduced (nothing to fix)'])
    cc = s['c_yaw70']
    rows.append(['(c) yaw 70 deg: max heading error plain / with S [deg]',
                 f'{_f(cc["plain_heading_max_abs"])} / {_f(cc["tuned_heading_max_abs"])}',
                 '> 4 / < 1.5', 'plain filter already < 1.5'
                 if cc['plain_heading_max_abs'] < 1.5 else 'see section 2'])
    return rows


def _rows_precise_points(pp: dict) -> list[list[str]]:
    """Summary rows: share of precise map points per sequence."""
    rows = []
    for key, label in (('synthetic_room', 'synthetic room'), ('kitti06', 'KITTI 06')):
        r = pp.get(key, {})
        if 'fraction_mean' in r:
            rows.append([f'precise pts ({label}): X % precise in 80 % of images',
                         f'{_f(r["pct_points_precise_in_80pct_of_images"], 1)} %', '89 %',
                         'below the paper' if r['pct_points_precise_in_80pct_of_images']
                         < 89 else 'at or above the paper'])
    return rows


def _rows_real_compare(rc: dict) -> list[list[str]]:
    """Summary rows: ATE per estimator on the real sequences."""
    rows = []
    for s in ('kitti06_f0-50', 'middlebury_dino'):
        r = rc.get(s, {})
        if 'ekf' in r:
            told = ' (ground-truth bootstrap)' if s == 'middlebury_dino' else ''
            rows.append([f'{s}{told}: ATE % of path EKF / IEKF / EPnP',
                         ' / '.join(_f(r[e]['ate_pct_path']['mean']) for e in
                                    ('ekf', 'iekf', 'epnp')),
                         'EKF error grows slower than PnP\'s (dino, qualitative)',
                         'EKF better' if min(r['ekf']['ate_pct_path']['mean'],
                                             r['iekf']['ate_pct_path']['mean'])
                         < r['epnp']['ate_pct_path']['mean'] else 'EPnP better'])
    return rows


def _rows_throughput(tp: dict) -> list[list[str]]:
    """Summary rows: core frames/s and ROS latency."""
    rows = []
    d, k = tp['demo_640x480'], tp.get('kitti_1226x370', {})
    rows.append(['core frames/s 640x480 / 1226x370', f'{_f(d["fps"], 0)} / '
                 f'{_f(k.get("fps"), 0)}', '~10 fps (Li et al., i7, 2160 frames)',
                 'faster' if min(d['fps'], k.get('fps', d['fps'])) > 10 else 'not faster'])
    for key, what in (('latency', '30 Hz 640x480'), ('latency_kitti', '10 Hz 1226x370')):
        lat = tp.get(key, {})
        if 'e2e_p50_ms' in lat:
            rows.append([f'vo_node latency p50 / p95 [ms], {what}, map_node beside',
                         f'{_f(lat["e2e_p50_ms"], 1)} / {_f(lat["e2e_p95_ms"], 1)}', '-',
                         f'{lat["odometry_received"]}/{lat["frames_sent"]} frames answered'])
    return rows


def _rows_scaling(sc: dict) -> list[list[str]]:
    """Summary rows: update cost against the number of points."""
    return [['update cost slope (log-log) camera-only / EKF-SLAM',
             f'{_f(sc["camera_only_slope"])} / {_f(sc["slam_slope"])}',
             'O(n) / O(n^3)', 'linear vs super-linear'
             if sc['camera_only_slope'] < 1.5 < sc['slam_slope'] else 'see section 6']]


def _rows_memory(m: dict) -> list[list[str]]:
    """Summary rows: RSS over the long run."""
    return [[f'memory over {m["frames"]} frames: RSS start / end / growth',
             f'{_f(m["rss_start_mb"], 0)} / {_f(m["rss_end_mb"], 0)} MiB / '
             f'{_f(m["rss_growth_second_half_mb_per_1000_frames"], 2)} MiB per 1k',
             'flat', 'flat' if m['rss_flat'] else 'growing']]


#: the summary's rows per section, in the order printed
SUMMARY_ROWS = (
    ('bunny', _rows_bunny),
    ('consistency', _rows_consistency),
    ('fading_memory', _rows_fading_memory),
    ('precise_points', _rows_precise_points),
    ('real_compare', _rows_real_compare),
    ('local_map', lambda r: importlib.import_module('bench.local_map').summary_rows(r)),
    ('throughput', _rows_throughput),
    ('scaling', _rows_scaling),
    ('memory', _rows_memory))


def summary_rows(R: dict) -> list[list[str]]:
    """(figure, ours, paper / reference, verdict) for the printed summary."""
    return [row for key, rows_of in SUMMARY_ROWS if R.get(key) and 'skipped' not in R[key]
            for row in rows_of(R[key])]


def print_summary(rows: list[list[str]]) -> str:
    w = [max(len(r[i]) for r in rows + [['figure', 'ours', 'paper / reference',
                                          'verdict']]) for i in range(4)]
    w = [min(x, 60) for x in w]
    lines = ['  '.join(h.ljust(w[i]) for i, h in enumerate(
        ('figure', 'ours', 'paper / reference', 'verdict')))]
    lines.append('  '.join('-' * x for x in w))
    for r in rows:
        lines.append('  '.join(c[:w[i]].ljust(w[i]) for i, c in enumerate(r)))
    return '\n'.join(lines)


# ============================================================================ report
def _slope_ratio(sw: dict) -> float:
    """Slope of the EKF's mean translation error against sigma over EPnP's (sigma > 0)."""
    import numpy as np
    sig = np.asarray(sw['sigma_px'])
    sel = sig > 0
    k_e = np.polyfit(sig[sel], np.asarray(sw['ekf_trans'])[sel], 1)[0]
    k_p = np.polyfit(sig[sel], np.asarray(sw['epnp_trans'])[sel], 1)[0]
    return float(k_e / k_p)


def _bunny_setup(s: dict) -> str:
    """Section 1's title and the experiment's setup."""
    return f"""## 1. Synthetic: the Stanford bunny (docs/method.md §1)

**Setup.** {s['points']} bunny vertices scaled to a 1 m object, camera {s['image']} with
f = {s['f_px']:g} px, {s['poses']} poses at {s['rate_hz']:g} Hz on a {_f(s['path_length_m'])} m path
where every DoF changes at every step (smallest per-step change: position
{', '.join(_f(v, 4) for v in s['min_step_change_pos_m'])} m, roll/pitch/yaw
{', '.join(_f(v, 3) for v in s['min_step_change_rpy_deg'])} deg); distance to the object
{_f(s['distance_m'][0], 1)} -> {_f(s['distance_m'][1], 1)} -> {_f(s['distance_m'][2], 1)} m;
every point inside the image in every frame (checked; closest {_f(s['min_border_margin_px'], 0)} px
from the border; the object spans {_f(s['object_width_px_min'], 0)}-{_f(s['object_width_px_max'], 0)} px
horizontally). The EKF starts from the ground truth of frames 0-1 and tracks frames 2-54 on
the exact map; EPnP+LM solves every frame alone (all points, no RANSAC rejection). Pixel
noise sigma = {s['sigma_px']:g} px, {s['runs']} runs. Filter process noise: sigma_a =
{s['accel_sigma']:g} m/s^2, sigma_alpha = {s['angular_accel_sigma']:g} rad/s^2 (the path's
peak accelerations are {_f(s['gt_peak_accel_m_s2'])} m/s^2 and ~0.18 rad/s^2).
Errors: translation = |camera centre error| / path length; rotation = norm of the
roll/pitch/yaw difference.

![per pose](bunny_per_pose.png)

"""


def _bunny_findings(b: dict) -> str:
    """Mean errors against EPnP, and the paper's qualitative findings checked."""
    ck, sw, m = b['checks'], b['sweep'], b['mean']
    means = _table(
        ['mean over poses 2-54', 'EKF (ours)', 'EPnP+LM', 'EKF / EPnP',
         'other protocol: EKFPnP / toolbox EPnP+GN'],
        [['translation [% of path]', _f(m['ekf_trans_pct'], 3), _f(m['epnp_trans_pct'], 3),
          _f(b['ratio_ekf_over_epnp']['trans']), '0.43-0.59 (toolbox trials, not the bunny; '
          'bench.ekfpnp_trials)'],
         ['rotation [deg]', _f(m['ekf_rot_deg'], 3), _f(m['epnp_rot_deg'], 3),
          _f(b['ratio_ekf_over_epnp']['rot']), '0.43-0.59 (idem)']])
    findings = _table(['paper\'s qualitative finding', 'reproduced?', 'detail'], [
        ['EPnP error above the EKF everywhere',
         _yes(ck['epnp_above_ekf_everywhere_trans'] and ck['epnp_above_ekf_everywhere_rot']),
         f'EPnP worse at {100 * ck["frac_poses_epnp_above_ekf_trans"]:.0f} % of poses '
         f'(translation), {100 * ck["frac_poses_epnp_above_ekf_rot"]:.0f} % (rotation)'],
        ['EPnP worst at the ends (far from the object)', _yes(ck['epnp_worst_at_ends']),
         'outer thirds vs middle third'],
        ['EKF translation error peaks mid-sequence', _yes(ck['ekf_trans_peak_mid_sequence']),
         f'our peak: pose {ck["ekf_trans_peak_frame"]}'],
        ['EPnP ~0 with zero noise', _yes(ck['epnp_zero_at_zero_noise']),
         f'{sw["epnp_trans"][0]:.1e} % of path'],
        ['EKF much less noise-sensitive than EPnP',
         'less sensitive, not much less' if 0.5 <= _slope_ratio(sw) < 0.95 else
         _yes(_slope_ratio(sw) < 0.5),
         f'error grows {_f(_slope_ratio(sw))} x as fast with sigma as EPnP\'s; at 5 px EKF '
         f'{_f(sw["ekf_trans"][-1], 3)} vs EPnP {_f(sw["epnp_trans"][-1], 3)} % of path']])
    return means + '\n\n' + findings


def _bunny_reading(s: dict, sw: dict, b: dict) -> str:
    """The reading of the bunny results: every claim is the one the numbers support."""
    ck, worst = b['checks'], max(b['ratio_ekf_over_epnp'].values())
    k = _slope_ratio(sw)
    everywhere = ck['epnp_above_ekf_everywhere_trans'] and ck['epnp_above_ekf_everywhere_rot']
    if worst < 1.0:
        t = ('The EKF beats per-frame EPnP on average (ratio above), as the paper finds, '
             + ("by a factor in the paper's range" if worst <= 0.59 else
                "but by a smaller factor than the paper's")
             + ('' if everywhere else ' and not at every single pose'))
        if worst > 0.59:
            t += (f': with {s["points"]} points per frame EPnP+LM is already a good '
                  'estimator, so the gain can only come from the motion model, and on this '
                  f'path (accelerations up to {_f(s["gt_peak_accel_m_s2"])} m/s^2 at '
                  f'{s["rate_hz"]:g} Hz) the constant-velocity prior carries about as much '
                  'information as one frame')
        t += '.'
    else:
        t = 'The EKF does not beat per-frame EPnP on average here (ratio above), unlike the paper.'
    if ck['epnp_worst_at_ends']:
        t += (" EPnP's error follows the distance to the object: largest at the ends, where "
              'the object is far and small.')
    else:
        t += (" EPnP's error is not largest at the ends here (outer thirds against the middle "
              'third), unlike the paper.')
    if ck['ekf_trans_peak_mid_sequence']:
        t += (" The paper's mid-sequence EKF peak (constant-velocity error where the velocity "
              f'changes most) appears here too (pose {ck["ekf_trans_peak_frame"]}).')
    else:
        t += (" The paper's mid-sequence EKF peak (constant-velocity error where the velocity "
              f'changes most) does not appear (our peak: pose {ck["ekf_trans_peak_frame"]}): '
              "our filter's process noise is sized to the path's accelerations, so where the "
              'velocity changes the prior simply weighs less and the error stays '
              'measurement-limited.')
    epnp_wins = [f'{x:g}' for x, e, p in zip(sw['sigma_px'], sw['ekf_trans'], sw['epnp_trans'])
                 if p <= e]
    if ck['epnp_zero_at_zero_noise']:
        t += (' With zero noise EPnP is exact while the EKF keeps a small motion-model error '
              f'({_f(sw["ekf_trans"][0], 4)} % of path)')
        if epnp_wins == ['0']:
            t += ': the only noise level where EPnP wins.'
        else:
            t += '.'
    if epnp_wins and epnp_wins != ['0']:
        t += (' EPnP\'s mean translation error is at or below the EKF\'s at sigma = '
              f'{", ".join(epnp_wins)} px (see the table below).')
    if k < 0.5:
        sens = 'much less sensitive, as in the paper'
    elif k < 0.95:
        sens = 'less sensitive, but not "much less" as in the paper'
    else:
        sens = 'not less sensitive, unlike the paper'
    gaps = [p - e for e, p in zip(sw['ekf_trans'], sw['epnp_trans'])]
    t += (' Both errors grow about linearly with the noise, the EKF\'s '
          f'{_f(k)} x as fast: {sens}')
    if k < 0.95 and gaps.index(max(gaps)) == len(gaps) - 1:
        t += ("; the gap is largest at the highest noise, where one frame's measurement is "
              'weakest relative to the motion prior')
    return t + '.'


def _bunny_sweep(s: dict, sw: dict, sweep_runs: int, b: dict) -> str:
    """The reading of the results, and the noise sweep."""
    reading = f"""

**Reading.** {_bunny_reading(s, sw, b)}

![noise sweep](bunny_noise_sweep.png)

"""
    sweep = _table(['sigma [px]'] + [f'{x:g}' for x in sw['sigma_px']], [
        ['EKF translation [% path]'] + [_f(v, 3) for v in sw['ekf_trans']],
        ['EPnP translation [% path]'] + [_f(v, 3) for v in sw['epnp_trans']],
        ['EKF rotation [deg]'] + [_f(v, 3) for v in sw['ekf_rot']],
        ['EPnP rotation [deg]'] + [_f(v, 3) for v in sw['epnp_rot']],
        ['EKF NEES (6 ideal)'] + [_f(v, 2) for v in sw['ekf_nees']]])
    return (reading + sweep + f"\n\n({sweep_runs} runs per noise level; at 0 px the filter "
            "assumes 0.1 px, hence its NEES is low there.)\n")


def _bunny_nees(b: dict, c: dict | None) -> str:
    """Consistency of the published covariance: NEES on the bunny and the orbits."""
    s, n = b['setup'], b['nees']
    rows = [['bunny, sigma = 3 px', f'{s["runs"]} x 53', _f(n['ekf_mean']), _f(n['ekf_median']),
             f'{_f(n["anees_95_bounds"][0])}-{_f(n["anees_95_bounds"][1])}',
             f'{100 * n["frac_frames_anees_in_bounds"]:.0f} %']]
    if c:
        rows.append([f'smooth orbit, sigma = {c["sigma_px"]:g} px, 300 points',
                     f'{c["runs"]} x {c["frames_per_run"]}', _f(c['nees_mean']),
                     _f(c['nees_median']),
                     f'{_f(c["anees_95_bounds"][0])}-{_f(c["anees_95_bounds"][1])}',
                     f'{100 * c["frac_frames_anees_in_bounds"]:.0f} %'])
    return ''.join([
        '\n### Consistency of the published covariance (NEES, docs/method.md §11.2)\n\n',
        'NEES = e^T P^-1 e of the 6-dof pose error (position, world rotation vector) '
        'under the EKF\'s own 6x6 covariance; an honest covariance gives a mean of 6. '
        'The band is the 95 % interval of the NEES averaged over the runs at one frame '
        '(chi-square, Bar-Shalom et al. 2001); ~95 % of the frames should fall in it. '
        '**What the filter was told here**: the true pixel noise, the exact map points and '
        'a ground-truth start: the consistency of the filter itself, not of the product '
        'on images (the full pipeline\'s, bench.pipeline_nees, in the map\'s own gauge: '
        'docs/method.md §12.7 and pipeline_nees.json).\n\n',
        _table(['runs', 'runs x frames', 'mean NEES', 'median', '95 % band (per frame)',
                'frames in band'], rows),
        f"\n\nFor reference, EPnP's Gauss-Newton covariance gives a mean NEES of "
        f"{_f(n['epnp_mean'])} on the bunny runs.\n"])


def section_bunny(b: dict, c: dict | None, quick: bool) -> str:
    """Section 1: the bunny experiment and the consistency (NEES) of the covariance."""
    return ''.join([_bunny_setup(b['setup']), _bunny_findings(b),
                    _bunny_sweep(b['setup'], b['sweep'], b['sweep_runs'], b),
                    _bunny_nees(b, c)])


def _ext_note(summary: dict) -> str:
    e = summary.get('c_yaw70_extended')
    if not e:
        return ''
    return (f' (and {_f(e["heading_max_abs"][-1])} deg with S = {e["S"][-1]:g}, far outside '
            'the paper\'s range)')


#: the turntable scenarios of section 2
_TURNTABLE = ('a_yaw10', 'b_yaw20_pitch20', 'c_yaw70')


def _fading_transients(fm: dict) -> str:
    """What the worst errors of scenario (c) are and what S does to them, as the numbers say."""
    f = fm['focal']['summary']
    c = f['c_yaw70']
    if max(f[n]['plain_heading_max_abs'] for n in _TURNTABLE) != c['plain_heading_max_abs']:
        return ''
    t = (' The worst errors are transients in (c): the 70-deg motion reverses far faster than '
         'the process noise tuned on (a) allows and the prediction overshoots')
    n_fb = sum(fm['focal']['c_yaw70'].get('ransac_fallbacks', [0]))
    if n_fb:
        t += (f'; in {n_fb} frames of (c) (summed over all S values and seeds) 1-point RANSAC '
              'found no supporting hypothesis and the core raised OverflowError (log(1) = 0 '
              'in the hypothesis count; docs/method.md §6.3 now keeps the count at '
              '`ransac_max_hypotheses` while no hypothesis has support), and the bench used '
              'the chi-square-gated update for those frames')
    t += '.'
    if c['tuned_heading_max_abs'] < c['plain_heading_max_abs']:
        t += (' Fading memory then only acts as extra process noise: it reduces the worst '
              f'heading error of (c) slightly ({_f(c["plain_heading_max_abs"])} -> '
              f'{_f(c["tuned_heading_max_abs"])} deg)')
        e = f.get('c_yaw70_extended')
        if e and e['heading_max_abs'][-1] < c['tuned_heading_max_abs']:
            t += (f' and keeps reducing it beyond 1.02 (up to S = {e["S"][-1]:g}), because '
                  'the motion of (c) is faster than the tuning of (a) assumes')
        t += '.'
    else:
        t += ' Fading memory does not reduce the worst heading error of (c) here.'
    return t


def section_fading(fm: dict, quick: bool) -> str:
    s = fm['setup']
    out = [f"""## 2. Fading memory under model error: the turntable (docs/method.md §3.4)

**Setup.** A camera rotating about its own centre at {s['rate_hz']:g} Hz, {s['image']} images,
smooth back-and-forth motion (period 4 s, starting at rest) for {s['seconds']:g} s;
{s['points']} static points 3-10 m around it (about 35 in view). Scenarios as the paper's:
(a) yaw 10 deg, (b) yaw and pitch 20 deg each, (c) yaw 70 deg. **Model error**: the data
are generated with f = {s['f_true_px']:g} px and the filter believes f = {_f(s['f_filter_px'], 0)} px
(2 % focal-length error){'' if quick else f'; a second variant adds unmodelled radial distortion k1 = {s["k1_unmodelled"]:g} instead'}.
Pixel noise {s['noise_px']:g} px (filter sigma {s['filter_sigma_px']:g} px). **The map the filter
uses is the exact point set**: the only errors are the camera model, the noise and the
constant-velocity model. One tuning for all scenarios (process noise of the (a) motion:
sigma_alpha = {s['angular_accel_sigma']:g} rad/s^2), 1-point RANSAC update, S = 1.000 ... 1.020,
{s['seeds']} seeds (point sets and noise) per value. As in the paper S is tuned on (a) and then
applied to (b) and (c).
"""]
    for variant in ('focal', 'k1'):
        if variant not in fm:
            continue
        v = fm[variant]
        sm = v['summary']
        rows = []
        for name, label in (('a_yaw10', '(a) yaw 10'), ('b_yaw20_pitch20', '(b) yaw+pitch 20'),
                            ('c_yaw70', '(c) yaw 70')):
            r = sm[name]
            rows.append([label, _f(r['plain_heading_mean_abs'], 3),
                         _f(r['tuned_heading_mean_abs'], 3), _f(r['plain_heading_max_abs'], 3),
                         _f(r['tuned_heading_max_abs'], 3), _f(r['plain_pitch_mean_abs'], 3),
                         _f(r['tuned_pitch_mean_abs'], 3), _f(r['best_S'], 3)])
        label = '2 % focal-length error' if variant == 'focal' else \
            f'unmodelled radial distortion k1 = {s["k1_unmodelled"]:g}'
        out += [f'\n**Model error: {label}** (S tuned on (a): {_f(sm["S_tuned_on_a"], 3)}; '
                'errors in degrees, mean |e| and max |e| over the run, averaged over seeds)\n\n',
                _table(['scenario', 'heading mean, S=1', 'heading mean, S tuned',
                        'heading max, S=1', 'heading max, S tuned', 'pitch mean, S=1',
                        'pitch mean, S tuned', 'best S (own)'], rows),
                f'\n\n![fading memory {variant}](fading_memory_{variant}.png)\n']
        if 'c_yaw70_extended' in sm:
            e = sm['c_yaw70_extended']
            out += ['\nBeyond the paper\'s range, scenario (c): ',
                    ', '.join(f'S = {S:g}: mean {_f(h, 3)} / max {_f(mx, 3)} deg' for S, h, mx
                              in zip(e['S'], e['heading_mean_abs'], e['heading_max_abs'])),
                    '.\n']
    f = fm['focal']['summary']
    b, c = f['b_yaw20_pitch20'], f['c_yaw70']
    plain = [f[n]['plain_heading_mean_abs'] for n in _TURNTABLE]
    out.append(f"""
**Comparison with the paper.** Paper: S = 1.009 best; (b) mean heading error reduced by
2.4158 deg and pitch by 0.1782 deg; (c) heading within 1.5 deg with S while the plain filter
drifts past 4 deg. Ours: (b) reductions {_f(b['heading_reduction_deg'], 4)} and
{_f(b['pitch_reduction_deg'], 4)} deg; (c) plain max heading error {_f(c['plain_heading_max_abs'])} deg,
with S {_f(c['tuned_heading_max_abs'])} deg{_ext_note(f)}. **The effect is small in our setting, and the
reason is the design, not the factor**: the paper's filter was a 1-point RANSAC EKF-SLAM
whose state holds the (inverse-depth) map, so the model error accumulates in points and
camera together and the overconfident filter drifts; S > 1 keeps it from trusting the old
data. In the hybrid method the map is fixed and (here) exact, each frame's ~35 points pin
the orientation again, and there is nothing to drift: the plain filter's mean heading error
is already {_f(min(plain), 3)}-{_f(max(plain), 3)} deg over the three scenarios (the 2 % focal error biases the rotation a little).{_fading_transients(fm)}
An S this small cannot matter much with a fixed map; it would with in-filter points
(docs/method.md §8, in-filter point refinement), which this experiment does not cover.
""")
    return ''.join(out)


def section_precise(pp: dict, quick: bool) -> str:
    rows = []
    for key in ('synthetic_room', 'kitti06'):
        r = pp.get(key, {})
        if 'fraction_mean' not in r:
            rows.append([key, r.get('skipped', 'no frames scored')] + ['-'] * 6)
            continue
        rows.append([r['what'], f'{r["frames_scored"]}/{r["frames"]}',
                     _f(r['points_per_image_mean'], 0), f'{100 * r["fraction_mean"]:.1f} %',
                     f'{r["pct_points_precise_in_80pct_of_images"]:.1f} %',
                     f'{r["pct_images_above_89pct"]:.1f} %',
                     f'{_f(r["reproj_err_median_px"])} / {_f(r["reproj_err_p90_px"])}'])
    return ''.join([
        """## 3. Precisely reconstructed points (docs/method.md §8 metric)

A map point observed in an image is *precise* when it reprojects within 1 px of its tracked
position under the EKF's pose for that image (Li et al. 2016). Per image we count the map
points tracked in it (not those triangulated in that very frame; a landmark culled as an
outlier in the frame counts as imprecise). The full pipeline runs on images (monocular
bootstrap, no ground truth). Paper (flight test, in-filter refined points): in 80 % of the
images more than 89 % of the points are precise.

""", _table(['sequence', 'images scored', 'points / image', 'mean precise',
              'in 80 % of images, more than', 'images with > 89 % precise',
              'reproj. error median / p90 [px]'], rows),
        """

![precise points](precise_points.png)

""", _precise_reading(pp)])


def _precise_reading(pp: dict) -> str:
    """The reading of section 3, only the claims the scored sequences support."""
    pct = {key: pp[key]['pct_points_precise_in_80pct_of_images'] for key in
           ('synthetic_room', 'kitti06') if 'fraction_mean' in pp.get(key, {})}
    if not pct:
        return ''
    names = {'synthetic_room': 'the rendered room', 'kitti06': 'KITTI 06'}
    below = [names[k] for k, v in pct.items() if v < 89]
    if not below:
        return '**Reading.** We reach the paper\'s 89 % on every scored sequence.\n'
    t = ('**Reading.** We are below the paper' +
         ('' if len(below) == len(pct) else f' on {" and ".join(below)}') + '. ' +
         """The map is refined by the local map's adjustment (docs/method.md §12), so
what is left is mostly the tracks' own error: `python -m bench.track_precision`
triangulates every track from all its views under the TRUE poses, and even so the default
21 px KLT window leaves KITTI 06 at about 52 % precise in 80 % of its images and the
rendered walk at about 71 % (docs/method.md §6.1: with `klt_window_px: 13`, 55 % and 87 %,
and this section's figures rise to 57 % and 92 %; it is not the default because it loses
more tracks in fast motion). Li et al. keep points in
the filter and refine their depth over >= 10 observations before freezing them (our
optional equivalent: docs/method.md §8). The median and p90 reprojection errors in the
table show how far above the 1 px threshold our imprecise points are.""")
    return t + '\n'



def section_real(rc: dict, quick: bool) -> str:
    out = [f"""## 4. Real sequences: EKF vs iterated EKF vs per-frame EPnP

`real_data.compare`, {rc['runs']} seeds per estimator (mean +- std). The same pipeline
(tracking, map, triangulation) with only the pose step swapped: `ekf` (hybrid EKF, 1-point
RANSAC), `iekf` (2 Gauss-Newton iterations), `epnp` (EPnP RANSAC + LM per frame, the
paper's baseline). ATE = RMSE of the positions after Sim(3) alignment (monocular scale), also
as % of the ground-truth path length; RPE = frame-to-frame relative error (RMSE);
rotation drift = orientation error relative to the first frame (mean).
KITTI 06 f0-50: 1226x370, car, ~1.2 m/frame, bootstrap from the images. Middlebury dino
views 1-48: 640x480 turntable ring of an untextured object, ~7.7 deg between views,
bootstrap from the first two ground-truth poses (the paper's protocol).

"""]
    for s in ('kitti06_f0-50', 'middlebury_dino'):
        r = rc.get(s, {})
        if 'ekf' not in r:
            out.append(f'**{s}**: skipped ({r.get("skipped", "?")}).\n\n')
            continue

        def ms(e, k, p=3):
            return f'{r[e][k]["mean"]:.{p}f} +- {r[e][k]["std"]:.{p}f}'
        rows = [[e, ms(e, 'ate_sim3_rmse'), ms(e, 'ate_pct_path', 2), ms(e, 'rpe_trans_rmse'),
                 ms(e, 'rpe_rot_rmse_deg'), ms(e, 'rot_drift_mean_deg', 2),
                 f'{r[e]["pct_tracked"]["mean"]:.1f}'] for e in ('ekf', 'iekf', 'epnp')]
        out += [f'**{s}** ({r["ekf"]["frames"]} frames, path {_f(r["ekf"]["path_length"])} m)\n\n',
                _table(['estimator', 'ATE Sim3 [m]', 'ATE [% path]', 'RPE trans [m]',
                        'RPE rot [deg]', 'rot. drift [deg]', 'tracked %'], rows), '\n\n']
    out.append('![real data](real_data.png)\n\n')
    verdicts = []
    for s in ('kitti06_f0-50', 'middlebury_dino'):
        r = rc.get(s, {})
        if 'ekf' not in r:
            continue
        best_f = min(('ekf', 'iekf'), key=lambda e: r[e]['ate_pct_path']['mean'])
        a, p = r[best_f]['ate_pct_path']['mean'], r['epnp']['ate_pct_path']['mean']
        if a < p:
            verdicts.append(f'on {s} the {best_f.upper()} has {a / p:.2f} x the ATE of EPnP')
        else:
            verdicts.append(f'on {s} **EPnP wins** ({_f(p)} vs {_f(a)} % of path for the '
                            f'{best_f.upper()})')
    if not verdicts:
        return ''.join(out)
    out.append('**Reading.** ' + (lambda t: t[:1].upper() + t[1:])('; '.join(verdicts)) + '. ' + """The paper's
real-data claim is qualitative (error propagates more slowly with the EKF, on dino and
templeRing, against CEPPnP and MLPnP); the papers give no number to put beside these.""" +
               _real_notes(rc) + '\n')
    return ''.join(out)


def _real_notes(rc: dict) -> str:
    """Remarks on section 4's tables, each printed only when its numbers show it."""
    seqs = {s: rc[s] for s in ('kitti06_f0-50', 'middlebury_dino') if 'ekf' in rc.get(s, {})}
    t = ''
    ratios = {s: min(r[e]['ate_pct_path']['mean'] for e in ('ekf', 'iekf')) /
              r['epnp']['ate_pct_path']['mean'] for s, r in seqs.items()}
    if ratios and all(x < 1 for x in ratios.values()):
        t += (' Compare the filter\'s margin over EPnP with the bunny\'s (section 1): with many '
              'well-spread points per frame the per-frame solution is already good and the '
              'motion model adds what one frame lacks.')
    kitti = seqs.get('kitti06_f0-50')
    if kitti and kitti['epnp']['ate_sim3_rmse']['std'] == 0:
        t += (" EPnP's std of 0 on KITTI is not a typo: OpenCV's RANSAC is seeded "
              "deterministically, while the filters' 1-point RANSAC uses the run's seed.")
    dino = seqs.get('middlebury_dino')
    if dino:
        sd = {e: dino[e]['rot_drift_mean_deg']['std'] for e in ('ekf', 'iekf', 'epnp')}
        if sd['epnp'] > 2 * max(sd['ekf'], sd['iekf']):
            t += (" On the dino EPnP's rotation drift varies much more between seeds "
                  f"(std {_f(sd['epnp'])} deg against {_f(sd['ekf'])} and {_f(sd['iekf'])} "
                  'for the EKF and IEKF: occasional bad frames with few corners on the '
                  'untextured object propagate into the map): the paper\'s "error propagates '
                  'more slowly" in our numbers.')
    same = [all(abs(r['iekf'][k]['mean'] - r['ekf'][k]['mean']) <=
                max(r['iekf'][k]['std'], r['ekf'][k]['std'])
                for k in ('ate_pct_path', 'rpe_trans_rmse', 'rpe_rot_rmse_deg'))
            for r in seqs.values()]
    if same and all(same):
        t += (' The iterated update changes ATE and RPE by no more than their spread over the '
              'seeds: nothing measurable here.')
    return t


def section_speed(tp: dict, quick: bool) -> str:
    passes = 'one pass' if tp['repeat'] == 1 else f"best of {tp['repeat']} passes"
    rows = []
    for key, label in (('demo_640x480', 'demo bag 640x480 (300 frames)'),
                       ('kitti_1226x370', 'KITTI 06 1226x370 (51 frames)')):
        r = tp.get(key, {})
        if 'fps' not in r:
            rows.append([label, r.get('skipped', '-')] + ['-'] * 7)
            continue
        st = r['stage_ms_mean']
        rows.append([label, _f(r['fps'], 1), _f(st.get('total'), 1),
                     _f(r['stage_ms_p95'].get('total'), 1), _f(st.get('predict')),
                     _f(st.get('track')), _f(st.get('update')), _f(st.get('top_up')),
                     _f(st.get('map'))])
    lat_rows = []
    for key, what in (('latency', 'demo 640x480, 30 Hz'), ('latency_kitti',
                                                           'KITTI 06 1226x370, 10 Hz')):
        lat = tp.get(key, {})
        if 'e2e_p50_ms' not in lat:
            lat_rows.append([what, f'not measured: {lat.get("skipped", "?")}'] + ['-'] * 4)
            continue
        lat_rows.append([what, f'{lat["frames_sent"]} / {lat["odometry_received"]}',
                         f'{_f(lat["e2e_p50_ms"], 1)} / {_f(lat["e2e_p95_ms"], 1)} / '
                         f'{_f(lat["e2e_max_ms"], 1)}',
                         f'{_f(lat["node_p50_ms"], 1)} / {_f(lat["node_p95_ms"], 1)}',
                         lat['dropped_behind'], _f(lat['node_fps'], 1)])
    lat_txt = _table(['input', 'frames sent / odometry received',
                      'publish->odometry p50 / p95 / max [ms]',
                      'inside vo_node p50 / p95 [ms]', 'dropped (behind)', 'node fps'],
                     lat_rows)
    lat_txt += ('\n\nOdometry messages can be fewer than frames sent: the first frames '
                'are spent on the bootstrap (no pose yet).')
    return ''.join([f"""## 5. Speed ({tp['machine']})

Core only (images decoded beforehand), {passes}, mean ms per frame by
stage. Li et al. processed 2160 frames in 223.56 s on an i7 (~10 frames/s); the papers'
measurement of the reference EKFPnP (Octave) is 5.7 ms per step at 100 points (our update
stage includes 1-point RANSAC over up to 400 points). Wall-clock on the machine named in the
title, shared with other jobs{f" (load average when measured: {tp['loadavg']})" if 'loadavg' in tp else ''}; they slow these figures down,
standalone runs of the same measurement can be ~2x faster on the demo bag.

""", _table(['sequence', 'frames/s', 'mean ms', 'p95 ms', 'predict', 'track', 'update',
                 'top_up', 'map'], rows), '\n\n![speed](speed.png)\n\n',
        '**ROS latency** (vo_node and a map_node, each in its own process, mono8 frames '
        'over DDS):\n\n',
        lat_txt, '\n'])


def section_scaling(sc: dict, quick: bool) -> str:
    cam_note = (' (linear, below 1 because the per-call overhead is still visible at a few '
                'hundred points)' if sc['camera_only_slope'] < 1 else '')
    slam_note = (' (on its way to 3: at these sizes the O(n^2) products still share the time '
                 'with the O(n^3) ones)' if 2 < sc['slam_slope'] < 3 else '')
    rows = []
    slam = dict(zip(sc['slam_n_points'], zip(sc['slam_ms'], sc['slam_working_set_mb'])))
    slam_med = dict(zip(sc['slam_n_points'], sc['slam_ms_median']))
    for n, t, tm in zip(sc['n_points'], sc['camera_only_ms'], sc['camera_only_ms_median']):
        s = slam.get(n)
        rows.append([n, f'{_f(t, 2)} ({_f(tm, 2)})',
                     f'{_f(s[0], 1)} ({_f(slam_med[n], 1)})' if s else 'not run',
                     _f(s[0] / t, 0) if s else '-', _f(s[1], 0) if s else '-'])
    return ''.join([f"""## 6. Update cost vs number of points: camera-only EKF vs EKF-SLAM

Same data for both (n points in view, one noisy image, the same camera prior). Camera-only:
`CameraEKF.update` (13 states, Woodbury gain). EKF-SLAM: a minimal textbook update written
in the bench (state 13 + 3n, P (13+3n)^2, H with the camera block and each point's 2x3
block, S 2n x 2n by Cholesky, K = P H^T S^-1, P - K S K^T). Correctness check: with zero
point covariance the SLAM update's camera estimate equals the camera-only update to
{sc['equivalence_max_abs_diff']:.1e}. Times: best (median) of several repetitions; the slopes
use the best, since on a shared machine the median also measures other
processes' load. SLAM run up to
n = {sc['slam_cap']} (larger sizes would take minutes and GBs; nothing is extrapolated).

""", _table(['points n', 'camera-only [ms] best (median)', 'EKF-SLAM [ms] best (median)',
             'SLAM / camera-only',
             'SLAM working set [MiB]'], rows), f"""

Log-log slopes fitted over n >= {sc['slope_fit_from_n']}: camera-only
**{_f(sc['camera_only_slope'])}**{cam_note}, EKF-SLAM **{_f(sc['slam_slope'])}**{slam_note}.

![scaling](scaling.png)
"""])


def _reset_note(m: dict) -> str:
    if m['n_resets'] == 0:
        return ''
    laps = m['frames'] / m['loop_frames']
    return (f' (about one every {m["frames"] / m["n_resets"]:.0f} frames, {m["n_resets"] / laps:.1f} '
            'per lap: the loop is a brisk 0.8 m/s, 36 deg/s orbit and the tracker loses it at '
            'a few places; robustness, not memory, is what this run shows to improve)')


def _crash_note(m: dict) -> str:
    c = m.get('core_exceptions_at_frames', [])
    if not c:
        return ''
    frames = ', '.join(map(str, c[:10])) + (f', ... ({len(c) - 10} more)' if len(c) > 10 else '')
    return (f'\n**Core bug hit {len(c)} time{"s" if len(c) != 1 else ""}** '
            f'(frame{"s" if len(c) != 1 else ""} {frames}): '
            '`robust_update` raised OverflowError out of `VisualOdometry.process` (1-point '
            'RANSAC with zero support divides by log(1) = 0; docs/method.md §6.3 now keeps the '
            'hypothesis count bounded in that case); the bench caught it and reset the '
            'pipeline' + (', which the resets above include' if m['n_resets'] else '') + '.\n')


def _resets_sentence(m: dict) -> str:
    """What resets do to the map, said only when the run had any."""
    if m['n_resets'] == 0:
        return 'This run had no reset, so the map was never cleared.'
    return ('A reset (tracking lost, re-bootstrap) clears the map: the saw-tooth of the map size '
            'below is those resets.')


def _peak_note(m: dict) -> str:
    before = m.get('peak_rss_before_run_mb')
    if before is None:
        return ''
    if before >= m['rss_peak_mb']:
        return (f' (process-wide: {_f(before, 0)} MiB had already been reached by the earlier '
                'sections)')
    return f' (process-wide; {_f(before, 0)} MiB before this run)'


def section_memory(m: dict, quick: bool) -> str:
    s = m['samples']
    idx = sorted(set([0, len(s['frame']) // 4, len(s['frame']) // 2, 3 * len(s['frame']) // 4,
                      len(s['frame']) - 1]))
    rows = [[s['frame'][i], _f(s['rss_mb'][i], 1), s['map_size'][i], _f(s['fps'][i], 1),
             s['n_resets'][i]] for i in idx]
    return ''.join([f"""## 7. Memory and throughput over {m['frames']} frames

A closed {m['loop_frames']}-frame loop around the synthetic room (640x480, 30 Hz; rendered once in
{_f(m['render_s'], 1)} s) replayed with increasing stamps, so the camera revisits the same
places {m['frames'] // m['loop_frames']} times. The map is bounded at {m['map_bound']} landmarks
(oldest-unseen culled first); landmarks are not re-associated across laps, so without a
reset the bound is what keeps it finite. {_resets_sentence(m)} RSS includes the interpreter,
numpy/OpenCV and the {m['loop_frames']} pre-rendered frames.

""", _table(['frame', 'RSS [MiB]', 'map size', 'frames/s (last 100)', 'resets'], rows), f"""

RSS {_f(m['rss_start_mb'], 0)} MiB after 100 frames, {_f(m['rss_end_mb'], 0)} MiB at the end,
peak {_f(m['rss_peak_mb'], 0)} MiB{_peak_note(m)}; growth over the second half
{_f(m['rss_growth_second_half_mb_per_1000_frames'], 2)} MiB per 1000 frames:
**{'flat' if m['rss_flat'] else 'NOT flat'}**. Map size reaches {m['map_size_max']}
(bound {m['map_bound']}). Throughput {_f(m['fps_first_10pct'], 0)} frames/s over the first 10 %,
{_f(m['fps_last_10pct'], 0)} over the last 10 % ({_f(m['fps_overall'], 0)} overall);
{_f(m['pct_frames_ok'], 1)} % of frames gave a pose, {m['n_resets']} reset{'' if m['n_resets'] == 1 else 's'}{_reset_note(m)}.
{_crash_note(m)}
![memory](memory.png)
"""])


def write_report(R: dict, meta: dict, rows: list, path: Path) -> None:
    quick = meta['quick']
    parts = [f"""# ekf_vo benchmark report{' (quick mode)' if quick else ''}

Generated by `python -m bench.run_all{' --quick' if quick else ''}` on {meta['machine']};
total wall time {meta['wall_s']:.0f} s (per section: {', '.join(f'{k} {v:.0f} s' for k, v in
meta['section_wall_s'].items())}). Every figure is also in `results.json`.
{'**Quick mode**: fewer runs, frames and sizes than the full benchmark; the figures are noisier.' if quick else ''}
Papers' figures are the papers' own (docs/method.md cites them). "EKF" is our hybrid camera-only EKF throughout.

## Summary

""", _table(['figure', 'ours', 'paper / reference', 'verdict'], rows), '\n\n']
    if meta['failed']:
        parts.append('**Failed sections**: ' + ', '.join(
            f'{k} ({v.splitlines()[-1]})' for k, v in meta['failed'].items()) + '\n\n')
    builders = [('bunny', lambda: section_bunny(R['bunny'], R.get('consistency'), quick)),
                ('fading_memory', lambda: section_fading(R['fading_memory'], quick)),
                ('precise_points', lambda: section_precise(R['precise_points'], quick)),
                ('real_compare', lambda: section_real(R['real_compare'], quick)),
                ('local_map', lambda: importlib.import_module(
                    'bench.local_map').report_section(R['local_map'], quick)),
                ('throughput', lambda: section_speed(R['throughput'], quick)),
                ('scaling', lambda: section_scaling(R['scaling'], quick)),
                ('memory', lambda: section_memory(R['memory'], quick))]
    for name, build in builders:
        if name in R and 'skipped' in R[name]:
            parts.append(f'## {name}: skipped ({R[name]["skipped"]})\n\n')
        elif name in R:
            parts.append(build() + '\n')
    path.write_text(''.join(parts), encoding='utf-8')


# ============================================================================ main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--out', type=Path, default=Path('bench/results'))
    parser.add_argument('--quick', action='store_true',
                        help='smaller runs for CI (~2-3 minutes)')
    parser.add_argument('--only', nargs='+', choices=SECTIONS, help='run these sections')
    parser.add_argument('--report-only', action='store_true',
                        help='rewrite report.md from OUT/results.json without running')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        import json
        data = json.loads((out / 'results.json').read_text())
        meta = data.pop('meta')
        rows = summary_rows(data)
        write_report(data, meta, rows, out / 'report.md')
        print(print_summary(rows))
        return 0
    R, failed, section_wall = {}, {}, {}
    t_all = time.perf_counter()
    for name in args.only or SECTIONS:
        t0 = time.perf_counter()
        print(f'[run_all] {name} ...', flush=True)
        try:
            mod = importlib.import_module(f'.{name}', __package__)
            R[name] = mod.run(args.quick, out)
        except Exception:       # noqa: BLE001 - report the failure, run the rest
            failed[name] = traceback.format_exc()
            print(failed[name], file=sys.stderr, flush=True)
        section_wall[name] = time.perf_counter() - t0
        print(f'[run_all] {name} done in {section_wall[name]:.0f} s', flush=True)
    meta = {'quick': args.quick, 'machine': machine(), 'wall_s': time.perf_counter() - t_all,
            'section_wall_s': section_wall, 'failed': failed,
            'date': time.strftime('%Y-%m-%d %H:%M:%S')}
    rows = summary_rows(R)
    write_json(out / 'results.json', {'meta': meta, **R})
    write_report(R, meta, rows, out / 'report.md')
    print()
    print(print_summary(rows))
    print(f'\nwall time {meta["wall_s"]:.0f} s; report: {out / "report.md"}')
    if failed:
        print(f'FAILED sections: {", ".join(failed)}', file=sys.stderr)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())

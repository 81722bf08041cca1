"""Is the published covariance honest on real data? Rotation NEES per sequence.

The core runs on each sequence exactly as a user would (images and calibration; dino
with the paper's ground-truth bootstrap, labelled), and each published pose's rotation
error (orientation aligned at the first published frame) is compared with the rotation
block of its published covariance (tools/consistency.py, docs/method.md §11.2): mean,
median (2.37 ideal), and the share of frames above the chi-square(3) 99.9 % bound (16.27;
0.1 % ideal, the target is <= 5 %), and of those frames the share whose health (what
``~/status`` says) was not OK. Sequences:

- ``kitti_raw`` / ``kitti_jpeg``: KITTI 06 frames 0-50, raw or re-encoded as JPEG
  quality 75 (what image_transport's compressed publisher records); ``kitti_jpegQ``
  (``kitti_jpeg30``) at quality Q.
  ``kitti_2x``: KITTI 06 at twice its speed (every other frame, at 10 Hz: 2.4 m a frame).
  ``kitti_reverse``: its frames backwards, at 10 Hz (the car reversing down the street).
  ``kitti_raw_startN`` / ``kitti_jpeg_startN``: the same frames from recorded frame N on
  (a node started N frames later: which pair the bootstrap takes, and what follows).
  ``kitti_*_from12``: the same run evaluated on the frames recorded from frame 12 on
  (for ``kitti_reverse``, the first 39 it plays): KITTI 06's ground truth turns
  at an exactly constant rate over frames 0-11 (relative rotations equal to 1e-5 deg,
  unlike the rest of the sequence), which the images contradict (docs/method.md §14.4).
- ``dino``: Middlebury dino, ground-truth bootstrap (the paper's protocol).
- ``demo``: bags/demo (rendered, 640x480, 30 Hz).
- ``walk`` / ``orbit`` / ``ground_robot`` / ``handheld_rotation`` / ``drone_nadir``:
  rendered sequences (ekf-vo-synth; the frames of SYNTHETIC), one per seed. With a
  suffix ``_x2`` or ``_x3`` (``orbit_x3``): the camera moving two or three times as fast
  (every second or third frame, stamped 1/30 s apart), as a 15 or 10 Hz camera sees the
  same motion (docs/method.md §15.11). With ``_still`` (``walk_still``): the camera
  stands for 1 s before it moves (its first view 30 times, with fresh sensor noise), as
  a robot waits when the node starts (§15.12). With a camera suffix (``_hd``,
  ``_narrow``, ``_wide``, ``_fisheye``, ``_barrel``, ``_noisy`` (``_noisy10``,
  ``_noisy12``, ``_noisy15``, ``_noisy20``: 10-20 grey levels), ``_ss2``, ``_blur``,
  ``_rs`` (30 ms), ``_rs10``, ``_jpeg``, ``_jpegQ`` at quality Q: ``handheld_rotation_hd``,
  ``walk_jpeg30``, see CAMERAS): the same
  motion seen through another lens or sensor (docs/method.md §15.13). ``car`` and
  ``car_turn`` drive down a rendered street through KITTI's camera (§15.16). With
  ``_repeat``, ``_jitter``, ``_flicker``, ``_exposure``, ``_overlay``, ``_body``,
  ``_hotpixels``, ``_dark`` or ``_vignette`` (``orbit_repeat``, ``walk_x3_jitter``,
  ``ground_robot_body``):
  what a camera driver, the sensor or the camera's mounting does to the stream
  (bench/stream_faults.py, §6.10).

    python -m bench.rotation_nees [--sequences ...] [--seeds 0 1 2] [--set NAME=VALUE ...]
                                  [--json OUT]
"""
from __future__ import annotations

import argparse
import dataclasses
import re
import sys
from pathlib import Path

import cv2
import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.stream import VoStream
from ekf_vo.io.dataset import load_folder
from ekf_vo.tools.consistency import CHI2_3DOF_999, rotation_nees
from ekf_vo.tools.evaluate import evaluate
from ekf_vo.tools.run import run_bag
from . import stream_faults
from .common import machine, overrides_or_report, shared_data, write_json
from .real_data import PRESETS

#: rendered trajectories (ekf-vo-synth) and their length in frames (30 Hz): the ground
#: robot's 760 frames are one loop of its rectangle, four turns in place
SYNTHETIC = {'walk': 300, 'orbit': 300, 'ground_robot': 760, 'handheld_rotation': 300,
             'drone_nadir': 300, 'car': 180, 'car_turn': 200}
SEQUENCES = ('kitti_raw', 'kitti_jpeg', 'kitti_2x', 'kitti_reverse', 'dino', 'demo') + \
    tuple(SYNTHETIC)
REPO = Path(__file__).resolve().parents[1]
#: first KITTI 06 frame whose ground-truth rotation is not the constant-rate segment
KITTI_GT_RELIABLE_FROM = 12


def _folder_frames(name: str):
    """(camera dict, frame iterator (stamp ns, grey, known pose or None), gt stamps s,
    gt poses, preset) of a shared-data sequence."""
    if name == 'dino':
        data = load_folder(shared_data('middlebury_dino'))
        frames = ((t, g, data.gt_at(k)) for k, (t, g) in enumerate(data.frames()))
        return data, frames, PRESETS['middlebury_dino']
    data = load_folder(shared_data('kitti06_f0-50'))
    name, start = _kitti_start(name)
    quality = _jpeg_quality(name.removeprefix('kitti_'))
    n = len(data.stamps_ns)
    if start:
        if start > n - 3:
            raise ValueError(f'{name}_start{start}: KITTI 06 f0-50 has {n} frames')
        data = _Resequenced(data, np.arange(start, n), recorded_stamps=True)
    elif name == 'kitti_2x':
        data = _Resequenced(data, np.arange(0, n, 2))
    elif name == 'kitti_reverse':
        data = _Resequenced(data, np.arange(n - 1, -1, -1))

    def frames():
        for t, g in data.frames():
            yield t, (g if quality is None else _jpeg(g, quality)), None
    return data, frames(), {}


def _kitti_start(name: str) -> tuple[str, int]:
    """('kitti_raw', 8) of 'kitti_raw_start8'; (name, 0) of any other name."""
    m = re.fullmatch(r'(kitti_raw|kitti_jpeg\d*)_start(\d+)', name)
    return (m.group(1), int(m.group(2))) if m else (name, 0)


def _real_sequence(name: str) -> str:
    """The SEQUENCES entry a real sequence's name plays ('kitti_jpeg' of
    'kitti_jpeg30_start6_from12'); the name itself when it is none."""
    name, _ = _kitti_start(name.removesuffix('_from12'))
    return 'kitti_jpeg' if re.fullmatch(r'kitti_jpeg\d+', name) else name


def _jpeg_quality(variant: str) -> int | None:
    """The JPEG quality of an encoding variant: 'jpeg' (``kitti_jpeg``, the ``_jpeg``
    suffix) JPEG_QUALITY, 'jpeg30' 30; None for any other variant."""
    m = re.fullmatch(r'jpeg(\d*)', variant)
    if m is None:
        return None
    quality = int(m.group(1) or JPEG_QUALITY)
    if not 1 <= quality <= 100:
        raise ValueError(f'JPEG quality {quality} is not in 1..100')
    return quality


class _Resequenced:
    """KITTI 06's frames in another order, `source_index` (indices of the recorded
    frames), stamped at the camera's 10 Hz (spaced by its first interval) or with their
    recorded stamps (`recorded_stamps`), with the ground truth reordered alike:
    every other frame is the car at twice its speed (2.4 m a frame, a highway's speed),
    the frames backwards are the car reversing down the street (the scene flows out of
    the image from its middle instead of towards its edges), the frames from N on a
    node started later (with their recorded stamps)."""

    def __init__(self, data, source_index: np.ndarray, recorded_stamps: bool = False
                 ) -> None:
        self._data = data
        self.camera = data.camera
        self.source_index = np.asarray(source_index, np.int64)
        t0, dt = data.stamps_ns[0], data.stamps_ns[1] - data.stamps_ns[0]
        # recorded_stamps: the frames keep theirs (a later start of the same recording)
        self.stamps_ns = [int(data.stamps_ns[i]) for i in self.source_index] \
            if recorded_stamps else [int(t0 + k * dt) for k in range(len(self.source_index))]
        self.gt_stamps_s = np.asarray(self.stamps_ns, float) * 1e-9
        self.gt_T_world_cam = np.asarray(data.gt_T_world_cam)[self.source_index]

    def frames(self):
        recorded = list(self._data.frames())
        for k, i in enumerate(self.source_index):
            yield self.stamps_ns[k], recorded[i][1]


def _gt_reliable_window_s(data) -> tuple[float, float]:
    """First and last stamp [s] of the frames recorded from KITTI_GT_RELIABLE_FROM on
    (for the ``_from12`` evaluation), in whatever order `data` plays them."""
    source = getattr(data, 'source_index', np.arange(len(data.stamps_ns)))
    t = np.asarray(data.stamps_ns, float)[source >= KITTI_GT_RELIABLE_FROM] * 1e-9
    return float(t.min()), float(t.max())


def _run_stream(camera: dict, frames, overrides: dict, seed: int, on_result=None):
    """Feed frames through VoStream; (stamps s, poses, covariances, ok per frame,
    resets, located per published pose, the self-calibrations: the rolling shutter's
    readout, the most applied and the last estimate [ms], docs/method.md §15.17, and the
    largest corners' drop of a lens fall-off correction in force, §6.11). `on_result`:
    called with each frame's result (bench.keyframe_pairs reads its checks)."""
    cfg = dataclasses.replace(VoConfig(), **overrides).validate()
    stream = VoStream(cfg, seed=seed)
    stream.set_camera(PinholeCamera.from_camera_info(camera))
    stamps, poses, covs, oks, located, health = [], [], [], [], [], []
    calibration = {'readout_applied_ms_max': 0.0, 'readout_estimate_ms': float('nan'),
                   'lens_falloff_drop_max': 0.0}
    for stamp_ns, gray, known in frames:
        res = stream.process(gray, stamp_ns,
                             known if stream.state.value == 'initialising' else None)
        if on_result is not None:
            on_result(res)
        calibration['readout_applied_ms_max'] = max(calibration['readout_applied_ms_max'],
                                                    res.readout_s * 1e3)
        if np.isfinite(res.readout_estimate_s):
            calibration['readout_estimate_ms'] = res.readout_estimate_s * 1e3
        calibration['lens_falloff_drop_max'] = max(calibration['lens_falloff_drop_max'],
                                                   res.lens_falloff_drop)
        oks.append(bool(res.ok))
        if oks[-1]:
            stamps.append(stamp_ns * 1e-9)
            poses.append(res.T_world_cam)
            covs.append(res.pose_cov)
            located.append(not res.orientation_only)
            health.append(res.health)
    if stream.vo is not None:
        stream.vo.close()
    return (np.array(stamps), np.array(poses), np.array(covs), oks, stream.n_resets,
            np.array(located, bool), health, calibration)


#: the rendered sequences through other cameras (a name's suffix: SynthConfig fields);
#: the renders are 640x480 at a 525 px focal length (62 deg across), no lens distortion
CAMERAS = {
    'hd': {'width': 1280, 'height': 720, 'fx': 900.0},  # 1280x720, 71 deg across
    'narrow': {'fx': 900.0},                            # 640x480, 39 deg across
    'wide': {'fx': 320.0},                              # 640x480, 90 deg across
    'fisheye': {'distortion': (-0.28, 0.07, 0.0, 0.0, 0.0)},    # a wide-angle webcam
    'barrel': {'distortion': (-0.1, 0.01, 0.001, -0.001, 0.0)},  # mild, decentred
    'noisy': {'noise_px': 5.0},                         # 5 grey levels (2 rendered)
    'noisy10': {'noise_px': 10.0},                      # a dim sensor's 10 grey levels
    'noisy12': {'noise_px': 12.0},
    'noisy15': {'noise_px': 15.0},
    'noisy20': {'noise_px': 20.0},
    'ss2': {'supersample': 2},                          # anti-aliased texture
    'blur': {'blur': 4.0},                              # 4 px of motion blur
    'rs': {'rolling_shutter_s': 0.03},                  # a webcam's 30 ms readout
    'rs10': {'rolling_shutter_s': 0.01},                # a phone camera's 10 ms
    'jpeg': {},                     # each frame through JPEG at quality JPEG_QUALITY
}
#: the camera a trajectory is rendered through unless a suffix says otherwise: the car's
#: is KITTI's (1226x370, 707 px, 10 Hz)
TRAJECTORY_CAMERAS = {t: {'width': 1226, 'height': 370, 'fx': 707.0, 'rate': 10.0}
                      for t in ('car', 'car_turn')}
#: the ``_jpeg`` suffix's quality (a CompressedImage stream's usual 75)
JPEG_QUALITY = 75
#: frames the camera of a ``_still`` sequence stands before it moves (1 s at 30 Hz)
STILL_FRAMES = 30
#: the standing camera's fresh sensor noise [grey levels]
STILL_NOISE = 2.0


def _synthetic_name(name: str) -> tuple[str, int, int, str, str] | None:
    """(trajectory, speed-up, frames standing first, stream fault or '', camera or '')
    of a rendered sequence's name ('orbit', 'orbit_x3', 'walk_still', 'orbit_repeat',
    'handheld_rotation_hd'), or None for a real one."""
    fault = next((f for f in stream_faults.FAULTS if name.endswith('_' + f)), '')
    name = name.removesuffix('_' + fault) if fault else name
    quality = re.search(r'_(jpeg\d+)$', name)
    camera = quality.group(1) if quality else \
        next((c for c in CAMERAS if name.endswith('_' + c)), '')
    name = name.removesuffix('_' + camera) if camera else name
    still = STILL_FRAMES if name.endswith('_still') else 0
    name = name.removesuffix('_still')
    trajectory, _, factor = name.partition('_x')
    if name in SYNTHETIC:
        return name, 1, still, fault, camera
    if trajectory in SYNTHETIC and factor in ('2', '3'):
        return trajectory, int(factor), still, fault, camera
    return None


def _jpeg(gray: np.ndarray, quality: int = JPEG_QUALITY) -> np.ndarray:
    """A grey image through JPEG at `quality` and back."""
    _, buf = cv2.imencode('.jpg', gray, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def _synthetic(trajectory: str, seed: int, overrides: dict, speedup: int = 1,
               still: int = 0, fault: str = '', run=None, camera: str = ''):
    """Render a sequence (ground-truth stamps [s] and T_world_cam) and feed it to
    `run(camera info, frames, overrides, seed)` (default: _run_stream), whose result is
    returned third. `camera`: a CAMERAS variant ('' the renders' own) or 'jpegQ'."""
    from ekf_vo.tools.synth import SynthConfig, render_sequence
    quality = _jpeg_quality(camera)                        # a bad one before rendering
    scfg = SynthConfig(frames=SYNTHETIC[trajectory], seed=seed, trajectory=trajectory,
                       **{**TRAJECTORY_CAMERAS.get(trajectory, {}), **CAMERAS.get(camera, {})})
    seq = list(render_sequence(scfg))
    dt = seq[1][0] - seq[0][0]
    if speedup > 1:            # every k-th frame, at the renderer's frame interval
        seq = [(seq[0][0] + k * dt, im, T) for k, (_, im, T) in enumerate(seq[::speedup])]
    if still:                  # the first view, standing, with fresh sensor noise
        rng = np.random.default_rng([seed, 30])
        t0, im0, T0 = seq[0]
        standing = [(t0 + k * dt, np.clip(im0 + rng.normal(0.0, STILL_NOISE, im0.shape),
                                          0, 255).astype(im0.dtype), T0)
                    for k in range(still)]
        seq = standing + [(t + still * dt, im, T) for t, im, T in seq]
    if fault:
        seq = stream_faults.apply(fault, seq, seed)
    if quality is not None:
        # the encoder comes after the sensor and the optics (vignetting, flicker, a clock
        # burned in); the stream's timing faults (repeat, jitter) commute with it
        seq = [(s, _jpeg(im, quality), T) for s, im, T in seq]
    info = {'width': scfg.width, 'height': scfg.height, 'K': scfg.K(), 'D': scfg.D(),
            'distortion_model': 'plumb_bob'}
    gt_s = np.array([s for s, _, _ in seq]) * 1e-9
    gt_T = np.array([T for _, _, T in seq])
    return gt_s, gt_T, (run or _run_stream)(info, ((s, im, None) for s, im, _ in seq),
                                            overrides, seed)


def run_one(name: str, seed: int, overrides: dict) -> dict:
    """One sequence (and seed): tracking figures and the rotation NEES."""
    start, end = 0.0, np.inf
    base = name.removesuffix('_from12')
    if _synthetic_name(base) is not None:
        trajectory, speedup, still, fault, camera = _synthetic_name(base)
        gt_s, gt_T, out = _synthetic(trajectory, seed, overrides, speedup, still, fault,
                                     camera=camera)
    elif base == 'demo':
        from ekf_vo.io.bag import read_ground_truth
        s = run_bag(REPO / 'bags' / 'demo', overrides=overrides, seed=seed)
        gt_ns, gt_T = read_ground_truth(REPO / 'bags' / 'demo')
        gt_s = np.asarray(gt_ns) * 1e-9
        out = (np.array(s.est_stamps_s), np.array(s.est_T_world_cam),
               np.array(s.est_pose_cov), [f.ok for f in s.frame_stats], s.n_resets,
               np.array(s.est_located, bool), [f.health for f in s.frame_stats if f.ok], {})
    else:
        data, frames, preset = _folder_frames(base)
        gt_s, gt_T = data.gt_stamps_s, data.gt_T_world_cam
        out = _run_stream(data.camera, frames, dict(preset, **overrides), seed)
        if name.endswith('_from12'):
            start, end = _gt_reliable_window_s(data)
    return figures(name, seed, gt_s, gt_T, out, start, end)


def figures(name: str, seed: int, gt_s: np.ndarray, gt_T: np.ndarray, out: tuple,
            start: float = 0.0, end: float = np.inf) -> dict:
    """A run's tracking figures and rotation NEES (run_one): `out` is _run_stream's,
    the NEES over the published poses stamped within [start, end] s."""
    stamps, poses, covs, oks, resets, located, health, calibration = out
    if len(stamps) < 3:
        return {'sequence': name, 'seed': seed, 'pct_tracked': 0.0, 'first_pose_frame': None,
                'pct_tracked_after_first': 0.0, 'ate_pct_path': float('nan'),
                'resets': resets, 'rot_err_max_deg': float('nan'), 'rot_nees_mean': float('nan'),
                'rot_nees_median': float('nan'), 'rot_nees_pct_above_99_9': float('nan'),
                'rot_nees_frames': 0, **calibration}
    # the ATE over the poses that have a position: orientation-only poses before a map
    # (docs/method.md §15.9) publish the attach point with an unknown position
    ate = float('nan')
    if np.count_nonzero(located) >= 3:
        ate = evaluate(gt_s, gt_T, stamps[located], poses[located], max_time_diff_s=1e-3,
                       n_frames_total=len(oks)).ate_sim3_pct_of_path
    first = oks.index(True) if True in oks else len(oks)
    after = oks[first:]
    keep = (stamps >= start - 1e-6) & (stamps <= end + 1e-6)
    rn = rotation_nees(gt_s, gt_T, stamps[keep], poses[keep], stamps[keep], covs[keep],
                       1e-3)
    # of the frames above the bound, the share whose ~/status did not say OK: a
    # covariance that is too small where the status warns is half honest
    # (rn.times_s are some of the published stamps, which increase)
    above = [health[i] for i in np.searchsorted(
        stamps, np.asarray(rn.times_s)[np.asarray(rn.nees) > CHI2_3DOF_999])]
    flagged = 100.0 * sum(h != 'ok' for h in above) / len(above) if above else float('nan')
    return {'sequence': name, 'seed': seed, 'pct_tracked': 100.0 * sum(oks) / len(oks),
            'first_pose_frame': first,
            'first_position_frame': int(np.flatnonzero(oks)[np.argmax(located)])
            if located.any() else None,
            'pct_tracked_after_first': 100.0 * sum(after) / max(len(after), 1),
            'ate_pct_path': ate, 'resets': resets,
            'rot_err_max_deg': float(np.max(rn.err_deg)), **rn.to_dict(),
            'above_flagged_pct': flagged, **calibration}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--sequences', nargs='+', default=list(SEQUENCES) + [
        'kitti_raw_from12', 'kitti_jpeg_from12'])
    p.add_argument('--seeds', nargs='+', type=int, default=[0])
    p.add_argument('--set', nargs='+', default=[], metavar='NAME=VALUE')
    p.add_argument('--json', type=Path)
    args = p.parse_args(argv)
    overrides = overrides_or_report(args.set, 'bench.rotation_nees')
    if overrides is None:
        return 2
    missing = [s for s in args.sequences
               if _real_sequence(s) not in SEQUENCES and _synthetic_name(s) is None]
    if missing:
        print(f'bench.rotation_nees: unknown sequence {missing[0]}', file=sys.stderr)
        return 2
    rows = []
    print(f'# rotation NEES of the published covariance ({machine()})')
    print('| sequence | seed | first pose | tracked % after it | resets | ATE % path | '
          'max rot err deg | NEES mean | median | % > 16.27 | of those, % not OK | '
          'readout ms applied / est | fall-off % |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    for name in args.sequences:
        real = _synthetic_name(name) is None
        for seed in (args.seeds[:1] if real else args.seeds):
            if real and name != 'demo' and shared_data(
                    'middlebury_dino' if name == 'dino' else 'kitti06_f0-50') is None:
                print(f'| {name} | - | skipped: ../shared/data absent | | | | | | | | | | |')
                continue
            try:
                r = run_one(name, seed, overrides)
            except ValueError as exc:
                print(f'bench.rotation_nees: {exc}', file=sys.stderr)
                return 2
            rows.append(r)
            label = name + (' (ground-truth bootstrap)' if name == 'dino' else '')
            print(f"| {label} | {seed} | {r['first_pose_frame']} | "
                  f"{r['pct_tracked_after_first']:.1f} | {r['resets']} | "
                  f"{r['ate_pct_path']:.3f} | {r['rot_err_max_deg']:.2f} | "
                  f"{r['rot_nees_mean']:.1f} | {r['rot_nees_median']:.2f} | "
                  f"{r['rot_nees_pct_above_99_9']:.1f} | "
                  f"{r.get('above_flagged_pct', float('nan')):.0f} | "
                  f"{r.get('readout_applied_ms_max', float('nan')):.1f} / "
                  f"{r.get('readout_estimate_ms', float('nan')):.1f} | "
                  f"{100 * r.get('lens_falloff_drop_max', float('nan')):.0f} |", flush=True)
    if args.json:
        write_json(args.json, {'machine': machine(), 'overrides': overrides, 'runs': rows})
    return 0


if __name__ == '__main__':
    sys.exit(main())

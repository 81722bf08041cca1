"""Memory and speed over a long run: does the pipeline stay flat over 10,000 frames?

Rendering 10k frames would take minutes (~35 frames/s), so a closed loop of 300 frames
(10 s at 30 Hz) is rendered once and replayed with increasing stamps: the camera circles
the synthetic room (radius 1.3 m, height, heading, pitch and roll all periodic with the
loop), so frame 300 continues frame 299 smoothly and the camera keeps revisiting the same
places. The map is bounded (VoConfig.max_map_points, oldest-unseen culled first) and
landmarks are not re-associated across laps, so new points keep arriving: the test is
that memory and time per frame stay flat anyway. Every 100 frames: resident set size
(/proc/self/statm), peak RSS (getrusage), map size, frames/s of the last 100 frames.

    python -m bench.memory [--quick] [--out DIR]
"""
from __future__ import annotations

import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ekf_vo.config import VoConfig
from ekf_vo.core.camera import PinholeCamera
from ekf_vo.core.stream import VoStream
from .common import pyplot, section_main

LOOP_FRAMES = 300
RATE_HZ = 30.0
SAMPLE_EVERY = 100
R_BODY_OPT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def loop_pose(k: int) -> np.ndarray:
    """T_world_cam of loop frame k: every DoF is periodic over LOOP_FRAMES."""
    th = 2 * np.pi * (k % LOOP_FRAMES) / LOOP_FRAMES
    yaw = th + np.pi / 2 - 0.6 + 0.12 * np.sin(3 * th)
    pitch = 0.1 + 0.12 * np.sin(2 * th + 1.0)
    roll = 0.06 * np.sin(3 * th)
    T = np.eye(4)
    # body x forward, z up; pitch > 0 looks down (as tools/synth.py)
    T[:3, :3] = Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_matrix() @ R_BODY_OPT
    T[:3, 3] = [1.3 * np.cos(th), 1.3 * np.sin(th), 1.5 + 0.12 * np.sin(2 * th)]
    return T


def render_loop() -> tuple[PinholeCamera, list[np.ndarray]]:
    from ekf_vo.tools.synth import SequenceRenderer, SynthConfig
    cfg = SynthConfig(frames=LOOP_FRAMES, rate=RATE_HZ)
    seq = SequenceRenderer(cfg)
    rng = np.random.default_rng(5)
    frames = []
    for k in range(LOOP_FRAMES):
        img = seq.render_clean(loop_pose(k)).astype(np.float32)
        img += rng.normal(0.0, cfg.noise_px, img.shape).astype(np.float32)
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return PinholeCamera(cfg.width, cfg.height, cfg.K()), frames


def rss_mb() -> float:
    with open('/proc/self/statm', encoding='ascii') as f:
        return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE') / 2 ** 20


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # KiB on Linux


def run(quick: bool = False, out: Path | None = None) -> dict:
    n_frames = 1000 if quick else 10000
    peak_before = peak_rss_mb()     # process-wide: earlier benchmark sections count too
    t0 = time.perf_counter()
    camera, loop = render_loop()
    render_s = time.perf_counter() - t0
    cfg = VoConfig()
    stream = VoStream(cfg, seed=0)
    stream.set_camera(camera)
    vo = stream.vo      # the estimator behind the front door, for its internals
    start_ns = 1_700_000_000 * 10 ** 9
    samples = {'frame': [], 'rss_mb': [], 'peak_rss_mb': [], 'map_size': [], 'fps': [],
               'n_resets': [], 'frames_ok': []}
    ok, t_last = 0, time.perf_counter()
    t_run = t_last
    crashes = []
    for i in range(n_frames):
        try:
            res = stream.process(loop[i % LOOP_FRAMES], start_ns + round(i * 1e9 / RATE_HZ))
            ok += int(res.ok)
        except OverflowError as exc:
            # core/ransac.py: a 1-point RANSAC round where the best hypothesis has zero
            # support divides by log(1) = 0 and raises out of VisualOdometry.process.
            # Work around it here (reset and go on) and report how often it happened.
            crashes.append(i)
            vo.reset(f'core exception: {exc}')
        if (i + 1) % SAMPLE_EVERY == 0:
            now = time.perf_counter()
            samples['frame'].append(i + 1)
            samples['rss_mb'].append(rss_mb())
            samples['peak_rss_mb'].append(peak_rss_mb())
            samples['map_size'].append(len(vo.map))
            samples['fps'].append(SAMPLE_EVERY / (now - t_last))
            samples['n_resets'].append(vo.n_resets)
            samples['frames_ok'].append(ok)
            t_last = now
    wall = time.perf_counter() - t_run
    rss = np.array(samples['rss_mb'])
    fps = np.array(samples['fps'])
    half = len(rss) // 2
    # growth over the second half of the run, per 1000 frames (least squares)
    slope = float(np.polyfit(samples['frame'][half:], rss[half:], 1)[0] * 1000) \
        if len(rss) - half >= 2 else float('nan')
    res = {'frames': n_frames, 'loop_frames': LOOP_FRAMES, 'render_s': render_s,
           'wall_s': wall, 'fps_overall': n_frames / wall, 'samples': samples,
           'rss_start_mb': float(rss[0]), 'rss_end_mb': float(rss[-1]),
           'rss_peak_mb': float(max(samples['peak_rss_mb'])),
           'rss_growth_second_half_mb_per_1000_frames': slope,
           'rss_flat': bool(abs(slope) < 2.0),
           'fps_first_10pct': float(fps[:max(1, len(fps) // 10)].mean()),
           'fps_last_10pct': float(fps[-max(1, len(fps) // 10):].mean()),
           'map_size_max': int(max(samples['map_size'])), 'map_bound': cfg.max_map_points,
           'pct_frames_ok': 100.0 * ok / n_frames, 'n_resets': vo.n_resets,
           'core_exceptions_at_frames': crashes, 'peak_rss_before_run_mb': peak_before}
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    s = res['samples']
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ax[0].plot(s['frame'], s['rss_mb'], 'b-', label='RSS')
    ax[0].plot(s['frame'], s['peak_rss_mb'], 'r--', label='peak RSS (whole process)')
    ax[0].set(xlabel='frame', ylabel='MiB', title='resident memory (includes the '
              f'{res["loop_frames"]} pre-rendered frames)')
    ax[0].set_ylim(0, 1.2 * max(s['peak_rss_mb'] + s['rss_mb']))
    ax[1].plot(s['frame'], s['map_size'], 'g-')
    ax[1].axhline(res['map_bound'], color='k', ls=':', label='max_map_points')
    ax[1].set(xlabel='frame', ylabel='landmarks', title='map size')
    ax[2].plot(s['frame'], s['fps'], 'm-')
    ax[2].set(xlabel='frame', ylabel='frames/s (last 100)', title='throughput')
    ax[2].set_ylim(bottom=0)
    for a in ax:
        a.grid(alpha=0.3)
    ax[0].legend()
    ax[1].legend()
    fig.tight_layout()
    p = out / 'memory.png'
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return [p.name]


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'memory',
                        lambda res: print({k: v for k, v in res.items() if k != 'samples'}))


if __name__ == '__main__':
    sys.exit(main())

"""A rendered sequence through the pipeline, judged on its orientation (the benchmark's
renders and stream faults, bench/rotation_nees.py and bench/stream_faults.py)."""
from __future__ import annotations

import cv2
import numpy as np


def rotation_errors_deg(trajectory: str, seed: int, fault: str, overrides: dict
                        ) -> tuple[np.ndarray, float]:
    """Every published orientation's error [deg] (aligned at the first published pose)
    on a rendered sequence through a stream fault of bench/stream_faults.py, and the
    share of frames published after the first."""
    from bench import rotation_nees as bench
    gt_s, gt_T, out = bench._synthetic(trajectory, seed, overrides, fault=fault)
    stamps, poses, _, oks = out[:4]
    first = oks.index(True)
    k = np.searchsorted(gt_s, stamps - 1e-6)
    R0 = gt_T[k[0]][:3, :3] @ poses[0][:3, :3].T
    err = [np.degrees(np.linalg.norm(cv2.Rodrigues(gt_T[i][:3, :3] @ (R0 @ P[:3, :3]).T)[0]))
           for i, P in zip(k, poses)]
    return np.array(err), float(np.mean(oks[first:]))


def standing_first(frames: list, standing: int, rng: np.random.Generator,
                   noise_grey: float = 2.0) -> list:
    """Rendered `frames` (stamp, image, T_world_cam) whose first view is held for
    `standing` frames first, each with fresh sensor noise of `noise_grey` grey levels,
    as a robot waits when the node starts (bench.rotation_nees's ``_still``)."""
    dt = frames[1][0] - frames[0][0]
    t0, im0, T0 = frames[0]
    held = [(t0 + k * dt, np.clip(im0 + rng.normal(0.0, noise_grey, im0.shape), 0, 255)
             .astype(im0.dtype), T0) for k in range(standing)]
    return held + [(t + standing * dt, im, T) for t, im, T in frames]

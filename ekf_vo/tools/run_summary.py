"""What ekf-vo-run reports: the per-frame rows, the run's summary, and their text, CSV and
JSON forms."""
from __future__ import annotations

import csv
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import VoConfig

#: per-frame CSV columns before the per-stage timings (``ms_<stage>``) and the message
STATS_COLUMNS = ('stamp_ns', 'stamp_s', 'state', 'ok', 'n_tracks', 'n_matches', 'n_inliers',
                 'n_new_points', 'map_size', 'health')


@dataclass
class FrameStats:
    """One row of the per-frame statistics (one image fed to the core)."""

    stamp_ns: int
    state: str
    ok: bool
    n_tracks: int
    n_matches: int
    n_inliers: int
    n_new_points: int
    map_size: int
    timings_ms: dict[str, float]
    message: str = ''
    #: the online checks' verdict ('ok', 'degraded', 'lost'; '' before a map), as ~/status
    health: str = ''

    @classmethod
    def of(cls, stamp_ns: int, res: Any) -> 'FrameStats':
        """The row of a core FrameResult."""
        return cls(stamp_ns, res.state.value, bool(res.ok), int(res.n_tracks),
                   int(res.n_matches), int(res.n_inliers), int(res.n_new_points),
                   int(res.map_size), dict(res.timings_ms), res.message,
                   res.health)


@dataclass
class RunSummary:
    """Result of :func:`run_bag`.

    Attributes:
        bag: the bag path.
        image_topic, info_topic: topics used; gt_topic: ground-truth topic or None.
        config: the core parameters used.
        frames: images fed to the core.
        frames_skipped: images not fed (before the first valid CameraInfo, undecodable).
        frames_ok: frames with ``result.ok`` (poses in the trajectory).
        pct_tracked: ``100 * frames_ok / frames`` [%].
        frames_orientation_only: of frames_ok, poses published before a map with the
            orientation alone (docs/method.md §15.9): not in the ATE.
        wall_s: wall time of the loop (bag reading, decoding, core) [s].
        fps: ``frames / wall_s`` [frames/s].
        core_fps: frames per second of ``process()`` alone (sum of its 'total' timings).
        stage_ms: mean duration per pipeline stage over the frames that ran it [ms].
        n_resets: tracking resets inside the core (summed over VO instances).
        n_camera_changes: calibration changes that re-created the VO.
        local_map: the local map's keyframe and adjustment figures ({} when off).
        scale: the metric scale's figures at the end (metric_scale.ScaleStatus).
        est_stamps_s: (N,) stamps [s] of the trajectory.
        est_T_world_cam: (N, 4, 4) camera optical frame -> world (VO world frame, VO scale).
        frame_stats: per-frame statistics, in order.
        eval: :class:`ekf_vo.tools.evaluate.EvalResult` or None (no ground truth / failed).
        eval_error: why the evaluation failed, or None.
        gt_bootstrap: whether ground truth was given to the bootstrap.
    """

    bag: str
    image_topic: str
    info_topic: str
    gt_topic: str | None
    config: VoConfig
    frames: int = 0
    frames_skipped: int = 0
    frames_ok: int = 0
    pct_tracked: float = 0.0
    frames_orientation_only: int = 0
    wall_s: float = 0.0
    fps: float = 0.0
    core_fps: float = 0.0
    stage_ms: dict[str, float] = field(default_factory=dict)
    n_resets: int = 0
    n_camera_changes: int = 0
    scale: dict = field(default_factory=dict)
    local_map: dict = field(default_factory=dict)
    est_stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    #: (N, 6, 6) their published covariances (position, world rotation vector)
    est_pose_cov: list = field(default_factory=list, repr=False)
    #: (N, 6) their twists (v, w in the camera frame) and (N, 6, 6) its covariances
    est_twist: list = field(default_factory=list, repr=False)
    est_twist_cov: list = field(default_factory=list, repr=False)
    #: (N,) whether each pose has a position (False: orientation only, §15.9)
    est_located: list = field(default_factory=list, repr=False)
    est_T_world_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)),
                                        repr=False)
    frame_stats: list[FrameStats] = field(default_factory=list, repr=False)
    eval: Any = None
    eval_error: str | None = None
    gt_bootstrap: bool = False

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (no per-frame data)."""
        out: dict[str, Any] = {
            'bag': self.bag, 'image_topic': self.image_topic, 'info_topic': self.info_topic,
            'gt_topic': self.gt_topic, 'frames': self.frames,
            'frames_skipped': self.frames_skipped, 'frames_ok': self.frames_ok,
            'frames_orientation_only': self.frames_orientation_only,
            'pct_tracked': self.pct_tracked, 'wall_s': self.wall_s, 'fps': self.fps,
            'core_fps': self.core_fps, 'stage_ms': dict(self.stage_ms),
            'n_resets': self.n_resets, 'n_camera_changes': self.n_camera_changes,
            'local_map': dict(self.local_map), 'scale': dict(self.scale),
            'gt_bootstrap': self.gt_bootstrap,
            'config': dataclasses.asdict(self.config),
            'eval': self.eval.to_dict() if self.eval is not None else None,
            'eval_error': self.eval_error,
        }
        return _finite(out)


def _finite(obj: Any) -> Any:
    """Replace NaN/inf floats by None (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_stats_csv(path: str | Path, rows: Sequence[FrameStats]) -> None:
    """Per-frame CSV: :data:`STATS_COLUMNS`, ``ms_<stage>`` for every stage seen (empty when
    a frame did not run it), ``message``."""
    stages: list[str] = []
    for row in rows:
        for key in row.timings_ms:
            if key not in stages:
                stages.append(key)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open('w', newline='', encoding='utf-8') as f:
        w = csv.writer(f)
        w.writerow([*STATS_COLUMNS, *(f'ms_{s}' for s in stages), 'message'])
        for r in rows:
            w.writerow([r.stamp_ns, f'{r.stamp_ns * 1e-9:.9f}', r.state, int(r.ok), r.n_tracks,
                        r.n_matches, r.n_inliers, r.n_new_points, r.map_size, r.health,
                        *(f'{r.timings_ms[s]:.3f}' if s in r.timings_ms else ''
                          for s in stages), r.message])


def format_summary(s: RunSummary) -> str:
    """Human-readable report of a run."""
    lines = [
        f'bag            {s.bag}',
        f'topics         {s.image_topic}, {s.info_topic}, ground truth: {s.gt_topic or "none"}',
        f'frames         {s.frames} processed, {s.frames_skipped} skipped, '
        f'{s.frames_ok} tracked ({s.pct_tracked:.1f} %)' + (
            f', {s.frames_orientation_only} of them orientation only (no map yet)'
            if s.frames_orientation_only else ''),
        f'speed          {s.fps:.1f} frames/s overall, {s.core_fps:.1f} frames/s core',
        'stage ms       ' + ', '.join(f'{k} {v:.2f}' for k, v in s.stage_ms.items()),
        f'resets         {s.n_resets} (calibration changes: {s.n_camera_changes})',
        *([f"scale          {s.scale['scale']:.4f} m per map unit +- "
           f"{s.scale['scale_sigma_pct']:.1f} % ({s.scale['scale_source']}, "
           f"{s.scale['scale_updates']} measurements, {s.scale['scale_state']})"]
          if s.scale.get('scale_source', 'none') != 'none' else []),
    ]
    if s.gt_bootstrap:
        lines.append('bootstrap      ground truth (known_T_world_cam while initialising)')
    if s.eval is not None:
        from .evaluate import format_table
        lines += ['', format_table(s.eval)]
    elif s.eval_error:
        lines.append(f'evaluation     failed: {s.eval_error}')
    return '\n'.join(lines)


# ============================================================================ CLI

"""How much of its own map the filter uses: the local-map baseline.

Per tracking frame of the full pipeline (images in, monocular bootstrap, no ground truth):
- track share: the fraction of the frame's KLT tracks that carry a map point;
- found share: of the map points that the frame's pose puts inside the image (in front of
  the camera, within the image bounds), the fraction that a track carries, i.e. that are
  measured this frame. Points that left every track stay in the map but are never seen
  again: that is what re-finding points by descriptor (the local map) would recover.
  The pose is the EKF's after the update (the prior is not kept per frame); for points a
  frame sees, both put them in the image almost always alike.
- twins: of the map points a track carries, the share with a twin, an untracked map
  point in view that the pose puts within TWIN_PX of it in the image and within
  TWIN_DEPTH_SHARE of its depth of it in 3D: most likely the same corner, triangulated
  again after its track broke (issue 14's "two points found to be one are merged"; how
  often it happens decides whether merging is worth building, docs/method.md §12.5).
- map size, for context.
Sequences: the demo bag (compressed 640x480, rendered room) and KITTI 06 frames 0-50 when
the developers' data folder is present; each with the defaults and with the points
triangulated once (`local_map: false`, the design before docs/method.md §12), for a
before/after, and with map points found again (`refind_map_points: true`, §12.5).

    python -m bench.map_usage [--quick] [--out DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ekf_vo.config import VoConfig
from ekf_vo.core.stream import VoStream
from ekf_vo.tools.demo import load_demo_frames
from .common import section_main, shared_data


#: image distance [px] and 3D distance (share of the tracked point's depth) within which
#: an untracked map point is counted as a tracked one's twin
TWIN_PX = 3.0
TWIN_DEPTH_SHARE = 0.10


def twins(uv: np.ndarray, X: np.ndarray, depth: np.ndarray, tracked: np.ndarray
          ) -> int:
    """How many of the `tracked` (bool) points have a twin among the others: image
    positions uv (n,2) within TWIN_PX, world positions X (n,3) within TWIN_DEPTH_SHARE of
    the tracked point's depth (n,)."""
    a, b = np.flatnonzero(tracked), np.flatnonzero(~tracked)
    if len(a) == 0 or len(b) == 0:
        return 0
    near_px = np.linalg.norm(uv[a][:, None] - uv[b][None], axis=2) < TWIN_PX
    near_3d = np.linalg.norm(X[a][:, None] - X[b][None], axis=2) \
        < TWIN_DEPTH_SHARE * depth[a][:, None]
    return int(np.count_nonzero((near_px & near_3d).any(axis=1)))


def frame_usage(stream: VoStream, res) -> tuple[float, float, int, float] | None:
    """(track share, found share, map points in view, share of the tracked ones with a
    twin) of one ok frame, or None."""
    if not res.ok or res.track_has_point is None \
            or len(res.track_ids) == 0:
        return None
    vo = stream.vo
    X = vo.map.X_world
    if len(X) == 0:
        return None
    px, front, _ = vo.ekf.observe(X, with_jacobian=False)
    in_image = front & vo.camera.in_image(vo.camera.distort(px))
    n_view = int(np.count_nonzero(in_image))
    tracked = vo.map.contains(res.track_ids) & res.track_has_point
    found = np.isin(vo.map.ids[in_image], res.track_ids[tracked])
    n_found = int(np.count_nonzero(found))
    R_wc, t_wc = vo.ekf.T_world_cam[:3, :3], vo.ekf.T_world_cam[:3, 3]
    depth = (X[in_image] - t_wc) @ R_wc[:, 2]
    n_twins = twins(px[in_image], X[in_image], depth, found)
    return (float(np.mean(res.track_has_point)),
            n_found / n_view if n_view else float('nan'), n_view,
            n_twins / n_found if n_found else float('nan'))


def run_sequence(frames, info, cfg: VoConfig) -> dict:
    stream = VoStream(cfg, seed=0)
    stream.set_camera(info)
    rows = []
    for stamp, gray in frames:
        if stream.admit(stamp) is not None:
            continue
        row = frame_usage(stream, stream.process(gray, stamp))
        if row is not None:
            rows.append(row)
    if not rows:
        return {'skipped': 'no tracked frame'}
    a = np.array(rows, dtype=float)
    return {'frames_scored': len(rows), 'frames': len(frames),
            'track_share_mean': float(np.nanmean(a[:, 0])),
            'found_share_mean': float(np.nanmean(a[:, 1])),
            'found_share_median': float(np.nanmedian(a[:, 1])),
            'in_view_mean': float(np.mean(a[:, 2])),
            'twin_share_mean': float(np.nanmean(a[:, 3])),
            'twin_share_max': float(np.nanmax(a[:, 3])),
            'map_size_final': int(len(stream.vo.map))}


#: the configurations compared: today's defaults, and the map before the local map
CONFIGS = {'defaults': VoConfig(), 'triangulated once': VoConfig(local_map=False),
           'points found again': VoConfig(refind_map_points=True)}


def run(quick: bool = False, out: Path | None = None) -> dict:
    info, frames = load_demo_frames()
    res = {f'demo, {name}': run_sequence(frames[:120] if quick else frames, info, cfg)
           for name, cfg in CONFIGS.items()}
    folder = shared_data('kitti06_f0-50')
    if folder is None:
        res['kitti06'] = {'skipped': "KITTI 06 is not in the developers' data folder"}
    else:
        from ekf_vo.io.dataset import load_folder
        data = load_folder(folder)
        for name, cfg in CONFIGS.items():
            res[f'kitti06, {name}'] = run_sequence(list(data.frames()), data.camera, cfg)
    return res


def summarize(res: dict) -> None:
    for name, r in res.items():
        if 'skipped' in r:
            print(f'{name}: skipped ({r["skipped"]})')
            continue
        print(f'{name}: {r["frames_scored"]}/{r["frames"]} frames scored; tracks with a map '
              f'point {100 * r["track_share_mean"]:.0f} %; map points in view that are '
              f'measured {100 * r["found_share_mean"]:.0f} % (median '
              f'{100 * r["found_share_median"]:.0f} %) of {r["in_view_mean"]:.0f} in view; '
              f'measured points with an untracked twin {100 * r["twin_share_mean"]:.1f} % '
              f'(frame max {100 * r["twin_share_max"]:.1f} %); '
              f'map {r["map_size_final"]} points at the end')


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'map_usage', summarize)


if __name__ == '__main__':
    sys.exit(main())

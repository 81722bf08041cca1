"""Map growth of the hybrid method: tracks without a point wait as candidates until their
rays have enough parallax, then are triangulated with the filter's poses (docs/method.md
§7.1-7.2).

A candidate remembers the frame of its first observation, its ideal pixel there and its
world bearing. Each tracked frame, candidates whose bearing now differs by
`triangulation_min_parallax_deg` are triangulated from that frame's pose and the current
one; a track that fails with three times that parallax is banned (unreliable). Ids are
never reused, so ended tracks are simply forgotten.

With `triangulation_depth_debias`, each new point is moved towards its first camera by its
depth's small-parallax bias, at the pixel noise the new points' residuals show
(docs/method.md §7.2.1).
"""
from __future__ import annotations

from collections import deque

import numpy as np

from ..config import VoConfig
from . import geometry as geo
from .camera import PinholeCamera
from .local_ba import point_covariances
from .map import LandmarkMap
from .triangulation import depth_debiased, triangulate_points_from

#: new points whose triangulation residuals make the pixel-noise estimate of the depth
#: correction (docs/method.md §7.2.1): a few frames' worth on a car, a second on a slow camera
NOISE_WINDOW_POINTS = 500


class MapGrowth:
    """Triangulation candidates and the poses they were first seen from."""

    def __init__(self, cfg: VoConfig, camera: PinholeCamera) -> None:
        self.cfg = cfg
        self.camera = camera
        #: (sum of squared residuals, count) of recent new points, newest last; a
        #: property of the camera and its images, so kept across map resets
        self._residuals: deque[tuple[float, int]] = deque()
        self.reset()

    def reset(self) -> None:
        self._frame: dict[int, int] = {}         # id -> frame index of first observation
        self._px: dict[int, np.ndarray] = {}     # id -> ideal pixel there
        self._bearing: dict[int, np.ndarray] = {}  # id -> world bearing there
        #: id -> (published covariance, camera centre) of the frame of first observation
        self._anchor: dict[int, tuple] = {}
        #: tracks never to triangulate (failed with a wide baseline, culled, rejected)
        self.banned: set[int] = set()
        self._T_world_cam_at: dict[int, np.ndarray] = {}

    def remember_pose(self, frame_index: int, T_world_cam: np.ndarray) -> None:
        self._T_world_cam_at[frame_index] = T_world_cam

    def add(self, tid: int, frame_index: int, px_ideal: np.ndarray,
            T_world_cam: np.ndarray, anchor: tuple) -> None:
        """A candidate first seen at `frame_index` (whose pose must be remembered), whose
        pose had the published (covariance, centre) `anchor`."""
        self.add_many(np.array([tid]), frame_index, np.reshape(px_ideal, (1, 2)),
                      T_world_cam, anchor)

    def add_many(self, tids: np.ndarray, frame_index: int, px_ideal: np.ndarray,
                 T_world_cam: np.ndarray, anchor: tuple) -> None:
        """`add` for the (n,) ids `tids` at (n, 2) ideal pixels, all first seen in one
        frame: one unprojection for all (a frame on a car brings ~100 new tracks)."""
        px_ideal = np.array(px_ideal, float).reshape(-1, 2)      # a copy: kept per id
        bearings = self.camera.unproject(px_ideal) @ T_world_cam[:3, :3].T
        for tid, px_k, b_k in zip(np.asarray(tids).tolist(), px_ideal, bearings):
            self._frame[tid] = frame_index
            self._px[tid] = px_k
            self._bearing[tid] = b_k
            self._anchor[tid] = anchor

    def drop(self, tid: int) -> None:
        self._frame.pop(tid, None)
        self._px.pop(tid, None)
        self._bearing.pop(tid, None)
        self._anchor.pop(tid, None)

    def rays(self, ids: np.ndarray, frame_index: int, centre: np.ndarray,
             max_baseline: float, max_n: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The candidates among the track ids first seen before `frame_index` from a
        camera centre within max_baseline of `centre`, oldest first, at most max_n:
        (rows into ids, centres (b,3), world bearings (b,3), anchor covariances
        (b,6,6), anchor centres (b,3)) (bearing.py)."""
        rows, first = [], []
        for k, tid in enumerate(ids):
            f = self._frame.get(int(tid), frame_index)
            if f < frame_index and np.linalg.norm(
                    self._T_world_cam_at[f][:3, 3] - centre) <= max_baseline:
                rows.append(k)
                first.append(f)
        rows = [rows[i] for i in np.argsort(first, kind='stable')[:max_n]]
        if not rows:
            return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                    np.zeros((0, 6, 6)), np.zeros((0, 3)))
        tids = [int(ids[k]) for k in rows]
        centres = np.array([self._T_world_cam_at[self._frame[t]][:3, 3] for t in tids])
        return (np.array(rows, np.int64), centres,
                np.array([self._bearing[t] for t in tids]),
                np.array([self._anchor[t][0] for t in tids]),
                np.array([self._anchor[t][1] for t in tids]))

    def two_view_covariances(self, X_world: np.ndarray, T_world_a: np.ndarray,
                             T_world_b: np.ndarray) -> np.ndarray:
        """Position covariances of points triangulated from two views (poses taken as
        exact: the uncertainty of the pixels only)."""
        return point_covariances(X_world, [geo.invert_T(T_world_a), geo.invert_T(T_world_b)],
                                 self.camera.K, self.cfg.pixel_sigma_px)

    def grow(self, landmarks: LandmarkMap, frame_index: int, ids: np.ndarray,
             px: np.ndarray, has_point: np.ndarray, T_world_cam: np.ndarray,
             anchor: tuple) -> int:
        """Triangulate the candidates among the tracks (ids, ideal px) without a point
        whose rays now differ by enough parallax; new points get `anchor`
        (map_uncertainty.py). Returns how many were added to `landmarks`."""
        alive = set(int(i) for i in ids)
        for tid in [t for t in self._frame if t not in alive]:
            self.drop(tid)
        self.banned &= alive          # ids are never reused: forget ended tracks
        cand_rows, new_rows = [], []
        for k in np.flatnonzero(~has_point).tolist():
            tid = int(ids[k])
            if tid in self.banned:
                continue
            first = self._frame.get(tid)
            if first is None:
                new_rows.append(k)
            elif first != frame_index:
                cand_rows.append(k)
        if new_rows:
            self.add_many(ids[new_rows], frame_index, px[new_rows], T_world_cam, anchor)
        n_added = 0
        if cand_rows:
            n_added = self._triangulate(landmarks, frame_index, ids, px,
                                        np.array(cand_rows), T_world_cam, anchor)
        # forget poses no candidate refers to any more
        needed = set(self._frame.values()) | {frame_index, frame_index - 1}
        for f in [f for f in self._T_world_cam_at if f not in needed]:
            del self._T_world_cam_at[f]
        return n_added

    def _triangulate(self, landmarks: LandmarkMap, frame_index: int, all_ids: np.ndarray,
                     px: np.ndarray, cand_rows: np.ndarray, T_world_cam: np.ndarray,
                     anchor: tuple) -> int:
        c = self.cfg
        ids = all_ids[cand_rows]
        bearings_now = self.camera.unproject(px[cand_rows]) @ T_world_cam[:3, :3].T
        bearings_then = np.array([self._bearing[int(i)] for i in ids])
        cos = np.clip(np.sum(bearings_now * bearings_then, axis=1), -1, 1)
        parallax = np.degrees(np.arccos(cos))
        ready = parallax >= c.triangulation_min_parallax_deg
        frames = np.array([self._frame[int(i)] for i in ids])
        rows = np.flatnonzero(ready)
        if len(rows) == 0:
            return 0
        # all the ready candidates at once, in the order of their first frames (the
        # order in which they enter the map); one DLT per first frame (§17.8)
        rows = rows[np.argsort(frames[rows], kind='stable')]
        sel_ids = ids[rows]
        first_frames, first = np.unique(frames[rows], return_inverse=True)
        T_cam_world_then = [geo.invert_T(self._T_world_cam_at[int(f)]) for f in first_frames]
        px_then = np.array([self._px[int(i)] for i in sel_ids])
        T_cam_world_now = geo.invert_T(T_world_cam)
        tri = triangulate_points_from(
            T_cam_world_then, first, T_cam_world_now, px_then, px[cand_rows[rows]],
            self.camera.K, c.triangulation_max_reproj_px, c.triangulation_min_parallax_deg)
        good = tri.valid
        X_new = tri.X_world[good]
        T_then = np.stack(T_cam_world_then)[first[good]]
        cov = point_covariances(X_new, [T_then, T_cam_world_now], self.camera.K,
                                c.pixel_sigma_px)
        if c.triangulation_depth_debias and len(X_new):
            self._note_residuals(tri.sq_err_sum_px2[good])
            ratio = self.pixel_noise_px() ** 2 / c.pixel_sigma_px ** 2
            centre = -np.einsum('nji,nj->ni', T_then[:, :3, :3], T_then[:, :3, 3])
            X_new = depth_debiased(X_new, centre, cov * ratio)
        landmarks.add(sel_ids[good], X_new, frame_index, cov=cov, anchor=anchor)
        for tid in sel_ids[good].tolist():
            self.drop(tid)
        # a track that fails with a wide baseline is unreliable: stop trying
        hopeless = ~good & (parallax[rows] > 3 * c.triangulation_min_parallax_deg)
        for tid in sel_ids[hopeless].tolist():
            self.drop(tid)
            self.banned.add(tid)
        return int(np.count_nonzero(good))

    def _note_residuals(self, sq_err_sum_px2: np.ndarray) -> None:
        """Add new points' summed squared two-view residuals to the noise window."""
        e = np.asarray(sq_err_sum_px2, float)
        e = e[np.isfinite(e)]
        if len(e) == 0:
            return
        self._residuals.append((float(e.sum()), len(e)))
        n = sum(k for _, k in self._residuals)
        while len(self._residuals) > 1 and n - self._residuals[0][1] >= NOISE_WINDOW_POINTS:
            n -= self._residuals.popleft()[1]

    def pixel_noise_px(self) -> float:
        """The tracks' pixel noise as the recent new points' residuals show it [px]:
        each point fits four coordinates with three unknowns, so its summed squared
        residual is sigma^2 chi-square(1), of mean sigma^2 (the residual across the
        epipolar line stands for the one along it, which sets the depth). Before any
        point: pixel_sigma_px."""
        n = sum(k for _, k in self._residuals)
        if n == 0:
            return float(self.cfg.pixel_sigma_px)
        return float(np.sqrt(sum(s for s, _ in self._residuals) / n))

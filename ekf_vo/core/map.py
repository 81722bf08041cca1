"""The fixed, triangulated sparse map of the hybrid method.

A landmark is identified by the id of the feature track that created it, so a frame's
tracks look their landmarks up directly (no descriptor matching). Landmarks stay in the
map after their track ends (they are still part of the published map) until culled:
- after `cull_after_misses` consecutive outlier verdicts (a bad triangulation or a track
  that slid onto another surface),
- or, when the map exceeds `max_points`, the longest-unseen landmarks first.
Each landmark carries a 3x3 covariance of its position (triangulation or the local map's
adjustment, docs/method.md §12.3); zero means "treated as exact".
Arrays are kept in a dict of id -> row with numpy storage so lookups are vectorised.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)


@dataclass
class MapChanges:
    """Landmarks added/updated and removed since the last call of `pop_changes`."""

    ids: np.ndarray          #: (n,) int64 added or updated
    X_world: np.ndarray      #: (n,3) their positions
    n_obs: np.ndarray        #: (n,) int32 observation counts
    removed_ids: np.ndarray  #: (m,) int64 culled


class LandmarkMap:
    """Sparse map: ids (N,) int64, X_world (N,3), observation bookkeeping."""

    def __init__(self, max_points: int, cull_after_misses: int) -> None:
        self.max_points = int(max_points)
        self.cull_after_misses = int(cull_after_misses)
        self.clear()

    #: the per-landmark columns (row = landmark): name -> (shape of one row, dtype).
    #: _desc: ORB descriptor for finding it again; _noise_dof / _noise_sum: residual
    #: components seen and their sum of normalised squares (noise_model.py); _anchor_cov /
    #: _anchor_c: world covariance and centre of the pose the landmark was made from
    #: (map_uncertainty.py)
    _COLUMNS = {'_ids': ((), np.int64), '_X': ((3,), np.float64),
                '_cov': ((3, 3), np.float64), '_anchor_cov': ((6, 6), np.float64),
                '_anchor_c': ((3,), np.float64), '_desc': ((32,), np.uint8),
                '_has_desc': ((), bool), '_noise_dof': ((), np.float64),
                '_noise_sum': ((), np.float64), '_n_obs': ((), np.int32),
                '_misses': ((), np.int32), '_last_seen': ((), np.int64)}

    def clear(self) -> None:
        self._row: dict[int, int] = {}
        for name, (shape, dtype) in self._COLUMNS.items():
            setattr(self, name, np.zeros((256,) + shape, dtype))
        self._size = 0
        self._changed: set[int] = set()
        self._removed: set[int] = set()
        self.n_culled = 0

    def __len__(self) -> int:
        return self._size

    @property
    def ids(self) -> np.ndarray:
        return self._ids[:self._size]

    @property
    def X_world(self) -> np.ndarray:
        return self._X[:self._size]

    @property
    def n_obs(self) -> np.ndarray:
        return self._n_obs[:self._size]

    def _grow(self, need: int) -> None:
        cap = len(self._ids)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in self._COLUMNS:
            arr = getattr(self, name)
            out = np.zeros((new,) + arr.shape[1:], arr.dtype)
            out[:cap] = arr
            setattr(self, name, out)

    def add(self, ids: np.ndarray, X_world: np.ndarray, frame_index: int,
            n_obs: int = 2, cov: np.ndarray | None = None,
            anchor: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Insert new landmarks (ids already present are overwritten); `cov` (n,3,3)
        their position covariances (None: zero); `anchor` (6x6 world covariance, centre)
        of the pose they were made from (None: exact)."""
        ids = np.asarray(ids, np.int64)
        anchor_cov, anchor_c = (np.zeros((6, 6)), np.zeros(3)) if anchor is None else anchor
        covs = np.zeros((len(ids), 3, 3)) if cov is None else np.asarray(cov, float)
        for lid, X, C in zip(ids, np.asarray(X_world, float), covs):
            lid = int(lid)
            row = self._row.get(lid)
            if row is None:
                self._grow(self._size + 1)
                row = self._size
                self._size += 1
                self._row[lid] = row
                self._ids[row] = lid
            self._X[row] = X
            self._cov[row] = C
            self._anchor_cov[row], self._anchor_c[row] = anchor_cov, anchor_c
            self._has_desc[row] = False
            self._noise_dof[row] = 0.0
            self._noise_sum[row] = 0.0
            self._n_obs[row] = n_obs
            self._misses[row] = 0
            self._last_seen[row] = frame_index
            self._changed.add(lid)
            self._removed.discard(lid)
        self._enforce_bound()

    def _rows(self, ids: np.ndarray, missing_ok: bool = False) -> np.ndarray:
        """Rows (n,) of landmarks `ids`; -1 for absent ones if missing_ok, else all must
        be in the map (KeyError)."""
        ids = np.asarray(ids, np.int64).reshape(-1).tolist()      # Python ints: fast keys
        if missing_ok:
            get = self._row.get
            return np.array([get(i, -1) for i in ids], dtype=np.int64)
        row = self._row
        return np.array([row[i] for i in ids], dtype=np.int64)

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For track ids (n,): mask (n,) of those with a landmark, and their X (m,3)."""
        rows = self._rows(ids, missing_ok=True)
        mask = rows >= 0
        return mask, self._X[rows[mask]]

    def covariances(self, ids: np.ndarray) -> np.ndarray:
        """Position covariances (n,3,3) of landmarks `ids` (all must be in the map)."""
        rows = self._rows(ids)
        return self._cov[rows]

    def anchors(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Anchor covariances (n,6,6) and centres (n,3) of landmarks `ids` (all in the map)."""
        rows = self._rows(ids)
        return self._anchor_cov[rows], self._anchor_c[rows]

    def refine(self, ids: np.ndarray, X_world: np.ndarray, cov: np.ndarray,
               anchor: tuple[np.ndarray, np.ndarray] | None = None) -> int:
        """Move landmarks to refined positions with new covariances (the local map's
        adjustment), and re-anchor them (None: keep their anchors); ids no longer in the
        map are skipped. Returns how many moved."""
        n = 0
        for lid, X, C in zip(np.asarray(ids, np.int64), X_world, cov):
            row = self._row.get(int(lid))
            if row is None:
                continue
            self._X[row], self._cov[row] = X, C
            if anchor is not None:
                self._anchor_cov[row], self._anchor_c[row] = anchor
            self._changed.add(int(lid))
            n += 1
        return n

    def noise_record(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual components seen and their sum of normalised squares (n,), (n,) of
        landmarks `ids` (all in the map), for noise_model.noise_scales."""
        rows = self._rows(ids)
        return self._noise_dof[rows], self._noise_sum[rows]

    def add_residuals(self, ids: np.ndarray, normalised_sq: np.ndarray) -> None:
        """Record one update's normalised squared residuals (2 components each)."""
        rows = self._rows(ids)
        self._noise_dof[rows] += 2.0
        self._noise_sum[rows] += normalised_sq

    def set_descriptors(self, ids: np.ndarray, desc: np.ndarray) -> None:
        """Binary descriptors (n,32) uint8 of landmarks `ids` (the latest keyframe's)."""
        rows = self._rows(ids, missing_ok=True)
        ok = rows >= 0
        self._desc[rows[ok]] = desc[ok]
        self._has_desc[rows[ok]] = True

    def described(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landmarks that have a descriptor: ids (k,), X_world (k,3), descriptors (k,32)."""
        rows = np.flatnonzero(self._has_desc[:self._size])
        return self._ids[rows], self._X[rows], self._desc[rows]

    def contains(self, ids: np.ndarray) -> np.ndarray:
        row = self._row
        return np.array([i in row for i in np.asarray(ids, np.int64).reshape(-1).tolist()],
                        dtype=bool)

    def record_observations(self, ids: np.ndarray, inlier: np.ndarray,
                            frame_index: int) -> np.ndarray:
        """Count inlier / outlier verdicts; cull repeated outliers. Returns culled ids."""
        rows = self._rows(ids)
        inlier = np.asarray(inlier, bool)
        self._n_obs[rows[inlier]] += 1
        self._misses[rows[inlier]] = 0
        self._last_seen[rows] = frame_index
        self._misses[rows[~inlier]] += 1
        bad = ids[~inlier][self._misses[rows[~inlier]] >= self.cull_after_misses]
        self.remove(bad)
        return bad

    def remove(self, ids: np.ndarray) -> None:
        """Delete landmarks (swap-with-last keeps the arrays compact)."""
        for lid in np.asarray(ids, np.int64):
            lid = int(lid)
            row = self._row.pop(lid, None)
            if row is None:
                continue
            last = self._size - 1
            if row != last:
                moved = int(self._ids[last])
                for name in self._COLUMNS:
                    arr = getattr(self, name)
                    arr[row] = arr[last]
                self._row[moved] = row
            self._size -= 1
            self._changed.discard(lid)
            self._removed.add(lid)
            self.n_culled += 1

    def _enforce_bound(self) -> None:
        excess = self._size - self.max_points
        if excess > 0:
            oldest = np.argsort(self._last_seen[:self._size], kind='stable')[:excess]
            self.remove(self._ids[oldest].copy())

    def pop_changes(self) -> MapChanges:
        """Changes since the previous call (for the map_node landmark stream)."""
        changed = np.array(sorted(self._changed), dtype=np.int64)
        mask, X = self.lookup(changed)
        rows = self._rows(changed[mask])
        out = MapChanges(ids=changed[mask], X_world=X,
                         n_obs=self._n_obs[rows] if len(rows) else np.zeros(0, np.int32),
                         removed_ids=np.array(sorted(self._removed), dtype=np.int64))
        self._changed.clear()
        self._removed.clear()
        return out

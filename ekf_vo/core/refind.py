"""Map points found again: descriptor search around the filter's predicted pixels.

docs/method.md §12.5. A map point whose KLT track has ended is not lost for good: when
the filter's prior puts it back in the image, we look for it there. Each keyframe gives
its observed map points a binary ORB descriptor (Rublee et al., ICCV 2011) computed at the
tracked pixel (OpenCV's ORB.compute on given keypoints: the tracker's Shi-Tomasi corners
are not ORB's own keypoints, so the descriptor is taken where the track is, at the
original scale and orientation 0 - frame-to-frame VO does not need the invariance).
Every frame, Shi-Tomasi corners of the image within a point's search window (its radius from
the innovation covariance, as in active search, Davison 2003) are compared with the
point's descriptor; the best match under `refind_max_hamming` whose distance beats the
second best by the ratio test becomes a measurement and a track again. Corners near a
live track are skipped (that place is already measured; two tracks on one corner would
count it twice).
"""
from __future__ import annotations

import cv2
import numpy as np

from ..config import VoConfig

#: ORB's descriptor patch (31 px) needs this much room from the image border
_ORB_BORDER_PX = 16
#: Shi-Tomasi quality level of the candidates (relative to the strongest corner in the
#: windows): low, the descriptor test does the rejecting
_CORNER_QUALITY = 0.001
#: pixels kept around a mask's bounding box when corners are searched in it: the 3x3
#: Sobel and the 3x3 block of the eigenvalue image, and the 3x3 non-maximum suppression
#: on it, each reach one or two pixels further out
_CROP_MARGIN_PX = 6
#: Lowe's ratio test: best distance < ratio * second best
_RATIO = 0.8


#: map points are searched for only this far inside the image (the descriptor's patch)
_SEARCH_MARGIN_PX = 16.0


def _keypoints(px: np.ndarray) -> list:
    # class_id carries the row: ORB.compute drops keypoints it cannot describe
    return [cv2.KeyPoint(float(u), float(v), 31.0, 0.0, 0.0, 0, int(i))
            for i, (u, v) in enumerate(px)]


class Describer:
    """ORB descriptors at given pixels, and FAST corners with their descriptors."""

    def __init__(self) -> None:
        self._orb = cv2.ORB_create(edgeThreshold=_ORB_BORDER_PX, patchSize=31)

    def describe(self, gray: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB descriptors (k,32) uint8 of the pixels that can be described, and their
        rows in `px` (k,)."""
        if len(px) == 0:
            return np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        kps, desc = self._orb.compute(gray, _keypoints(px))
        if desc is None or not kps:
            return np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        return desc, np.array([k.class_id for k in kps], np.int64)

    def corners(self, gray: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Shi-Tomasi corners (n,2) RAW px where `mask` (uint8, HxW) is non-zero: the
        tracker's own detector, so a map point's corner is found where it was made.

        With a mask, only the mask's bounding box (plus _CROP_MARGIN_PX) is searched: the
        same corners in the same order as over the whole frame (the eigenvalue image
        inside the box does not depend on pixels further out, the quality threshold is
        taken over the mask), at the cost of the box. Over a whole 1226x370 frame the
        call took ~10 ms (docs/method.md §17.8: the eigenvalue image's allocation)."""
        x0 = y0 = 0
        if mask is not None:
            x, y, w, h = cv2.boundingRect(mask)
            if w == 0 or h == 0:
                return np.zeros((0, 2))
            m = _CROP_MARGIN_PX
            x0, y0 = max(x - m, 0), max(y - m, 0)
            x1 = min(x + w + m, gray.shape[1])
            y1 = min(y + h + m, gray.shape[0])
            gray, mask = gray[y0:y1, x0:x1], mask[y0:y1, x0:x1]
        pts = cv2.goodFeaturesToTrack(gray, 2000, _CORNER_QUALITY, 2.0, mask=mask,
                                      blockSize=3)
        if pts is None:
            return np.zeros((0, 2))
        return pts.reshape(-1, 2).astype(float) + (x0, y0)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances (n,m) between binary descriptors a (n,32) and b (m,32)."""
    x = np.bitwise_xor(a[:, None, :], b[None, :, :])
    return np.unpackbits(x, axis=2).sum(axis=2)


def match_in_windows(pred_px: np.ndarray, radius_px: np.ndarray, desc: np.ndarray,
                     corner_px: np.ndarray, corner_desc: np.ndarray, max_hamming: int
                     ) -> np.ndarray:
    """For each predicted point (n,) the row of its matching corner, or -1: the nearest
    descriptor among the corners within its radius, under max_hamming, passing the ratio
    test; a corner claimed by two points goes to neither (ambiguous)."""
    n = len(pred_px)
    out = -np.ones(n, np.int64)
    if n == 0 or len(corner_px) == 0:
        return out
    d2 = np.sum((pred_px[:, None, :] - corner_px[None, :, :]) ** 2, axis=2)
    near = d2 <= radius_px[:, None] ** 2
    rows = np.flatnonzero(near.any(axis=1))
    for i in rows:
        cand = np.flatnonzero(near[i])
        dist = hamming(desc[i:i + 1], corner_desc[cand])[0]
        order = np.argsort(dist)
        best = dist[order[0]]
        if best > max_hamming:
            continue
        if len(order) > 1 and best >= _RATIO * dist[order[1]]:
            continue
        out[i] = cand[order[0]]
    taken, counts = np.unique(out[out >= 0], return_counts=True)
    out[np.isin(out, taken[counts > 1])] = -1
    return out


class MapPointFinder:
    """Keyframe descriptors of the map points, and the per-frame search for the lost ones."""

    def __init__(self, cfg: VoConfig) -> None:
        self.cfg = cfg
        self.describer = Describer()

    def describe(self, gray: np.ndarray, tracks, landmarks) -> None:
        """A keyframe's ORB descriptors for the map points its tracks carry."""
        has_point = landmarks.contains(tracks.ids)
        desc, rows = self.describer.describe(gray, tracks.px[has_point])
        landmarks.set_descriptors(tracks.ids[has_point][rows], desc)

    def _search_windows(self, X: np.ndarray, ekf, camera, shape, rng
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows of X searched, their predicted RAW pixels, radii): points the updated
        pose puts inside the image, window = refind_search_sigmas x the innovation's
        largest axis (H P H^T + sigma^2 I), bounded."""
        c = self.cfg
        px_ideal, front, H = ekf.observe(X)
        raw = camera.distort(px_ideal)
        h, w = shape
        m = _SEARCH_MARGIN_PX
        inside = front & np.all(np.isfinite(raw), axis=1) & (raw[:, 0] >= m) & \
            (raw[:, 0] < w - m) & (raw[:, 1] >= m) & (raw[:, 1] < h - m)
        rows = np.flatnonzero(inside)
        if len(rows) > c.refind_max_points:
            rows = np.sort(rng.choice(rows, c.refind_max_points, replace=False))
        Hn = H.reshape(-1, 2, H.shape[1])[rows]
        S = Hn @ ekf.P @ np.transpose(Hn, (0, 2, 1)) + np.eye(2) * c.pixel_sigma_px ** 2
        tr, det = S[:, 0, 0] + S[:, 1, 1], np.linalg.det(S)
        radius = c.refind_search_sigmas * np.sqrt(tr / 2 + np.sqrt(np.maximum(
            tr ** 2 / 4 - det, 0)))
        ok = radius <= c.refind_max_radius_px          # a wider prior is too ambiguous
        return rows[ok], raw[rows[ok]], np.maximum(radius[ok], c.refind_min_radius_px)

    def find_again(self, gray: np.ndarray, tracks, landmarks, ekf, camera, tracker,
                   rng: np.random.Generator) -> np.ndarray:
        """Map points the updated pose puts in the image without a live track, searched
        by descriptor around their predicted pixel; the matches become tracks (the
        tracker adopts them) that the next frames measure. Searched after the update,
        where the pose is known to a few pixels: with the prior, the windows on KITTI at
        10 Hz were ~150 px wide. Returns the ids found."""
        ids, X, desc = landmarks.described()
        lost = ~np.isin(ids, tracks.ids)
        ids, X, desc = ids[lost], X[lost], desc[lost]
        if not len(ids):
            return np.zeros(0, np.int64)
        rows, pred, radius = self._search_windows(X, ekf, camera, gray.shape[:2], rng)
        if not len(rows):
            return np.zeros(0, np.int64)
        # Shi-Tomasi corners in the search windows, away from the live tracks
        mask = np.zeros(gray.shape[:2], np.uint8)
        # np.rint rounds half to even, as round() did; one conversion, not one per pixel
        for (u, v), r in zip(np.rint(pred).astype(int).tolist(),
                             np.ceil(radius).astype(int).tolist()):
            cv2.circle(mask, (u, v), r, 255, -1)
        keep_off = int(self.cfg.min_feature_distance_px)
        for u, v in np.rint(tracks.px).astype(int).tolist():
            cv2.circle(mask, (u, v), keep_off, 0, -1)
        corners = self.describer.corners(gray, mask)
        corner_desc, ok = self.describer.describe(gray, corners)
        match = match_in_windows(pred, radius, desc[rows], corners[ok], corner_desc,
                                 self.cfg.refind_max_hamming)
        found = match >= 0
        tracker.adopt(ids[rows][found], corners[ok][match[found]])
        return ids[rows][found]

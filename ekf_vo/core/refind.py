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

from dataclasses import dataclass

import cv2
import numpy as np

#: ORB's descriptor patch (31 px) needs this much room from the image border
_ORB_BORDER_PX = 16
#: Shi-Tomasi quality level of the candidates (relative to the strongest corner in the
#: windows): low, the descriptor test does the rejecting
_CORNER_QUALITY = 0.001
#: Lowe's ratio test: best distance < ratio * second best
_RATIO = 0.8


@dataclass
class RefindResult:
    """Map points found again in one frame."""

    ids: np.ndarray      #: (k,) landmark ids
    px: np.ndarray       #: (k,2) RAW pixels of their matches
    n_searched: int = 0  #: map points predicted in the image and searched for


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
        tracker's own detector, so a map point's corner is found where it was made."""
        pts = cv2.goodFeaturesToTrack(gray, 2000, _CORNER_QUALITY, 2.0, mask=mask,
                                      blockSize=3)
        return np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(float)


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

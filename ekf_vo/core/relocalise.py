"""Relocalisation: after a loss, find the camera in the map it already has.

docs/method.md §15.6. When tracking is lost (dark frames, a covered lens, blur, a gap in
the stream), the map is kept. Each new frame's Shi-Tomasi corners get ORB descriptors the
way the keyframes gave them to the map points (refind.Describer: the same corners, the same
descriptor, so a point is found where it was made); each is matched to the described map
points by Hamming distance (OpenCV's brute-force matcher, Lowe's ratio 0.8, one corner per
point), and EPnP inside RANSAC with Levenberg-Marquardt refinement (pnp.solve_epnp) poses
the camera from the matches. Enough inliers resume tracking in the same world frame and
scale; the pipeline re-bootstraps only when this fails for `relocalise_timeout_s`.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..config import VoConfig
from .camera import PinholeCamera
from .map import LandmarkMap
from .pnp import solve_epnp
from .refind import Describer

#: Lowe's ratio test of the descriptor matches
_RATIO = 0.8


@dataclass
class Relocalisation:
    T_world_cam: np.ndarray      #: 4x4
    pose_cov: np.ndarray         #: 6x6 (position, world rotation vector) of the PnP fit
    ids: np.ndarray              #: (k,) map points matched as inliers
    px: np.ndarray               #: (k,2) their RAW pixels in this frame


class Relocaliser:
    """Poses a frame against the described map points (see the module docstring)."""

    def __init__(self, cfg: VoConfig, camera: PinholeCamera) -> None:
        self.cfg = cfg
        self.camera = camera
        self.describer = Describer()
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def attempt(self, gray: np.ndarray, landmarks: LandmarkMap) -> Relocalisation | None:
        """The frame's pose in the map, or None when the map is not recognised."""
        c = self.cfg
        ids, X, desc = landmarks.described()
        if len(ids) < c.relocalise_min_inliers:
            return None
        corners = self.describer.corners(gray)
        cdesc, rows = self.describer.describe(gray, corners)
        if len(rows) < c.relocalise_min_inliers:
            return None
        corners = corners[rows]
        best: dict[int, tuple[float, int]] = {}        # map row -> (distance, corner)
        for pair in self._matcher.knnMatch(cdesc, desc, k=2):
            if len(pair) < 2:
                continue
            m, n = pair
            if m.distance <= c.relocalise_max_hamming and m.distance < _RATIO * n.distance:
                if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                    best[m.trainIdx] = (m.distance, m.queryIdx)
        if len(best) < c.relocalise_min_inliers:
            return None
        t_rows = np.fromiter(best.keys(), np.int64)
        q_rows = np.array([best[int(t)][1] for t in t_rows], np.int64)
        px_ideal = self.camera.undistort(corners[q_rows])
        fit = solve_epnp(px_ideal, X[t_rows], self.camera.K, c.pixel_sigma_px,
                         c.ransac_inlier_px)
        if not fit.ok or np.count_nonzero(fit.inliers) < c.relocalise_min_inliers:
            return None
        inl = fit.inliers
        return Relocalisation(fit.T_world_cam, fit.pose_cov, ids[t_rows][inl],
                              corners[q_rows][inl])

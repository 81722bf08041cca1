"""Pinhole camera with the distortion models of ROS CameraInfo (REP-104).

The estimator works in *ideal* pixel coordinates: the pixels a distortion-free pinhole
camera with intrinsics K would see. Feature positions are measured on the raw image and
undistorted once (`undistort`); the EKF then uses the plain pinhole projection
u = fx X/Z + cx, v = fy Y/Z + cy (docs/method.md §4), whose Jacobian is analytic.

Supported models (image_geometry semantics):
- `plumb_bob` (k1 k2 t1 t2 k3) and `rational_polynomial` (k1 k2 t1 t2 k3 k4 k5 k6):
  OpenCV's standard model (cv2.undistortPoints / cv2.projectPoints).
- `equidistant` (k1 k2 k3 k4): OpenCV's fisheye model (cv2.fisheye).
- rectified input (`rectified=True`): the image was already rectified, so the projection
  is P[:3,:3] and there is no distortion.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: number of distortion coefficients each model needs (REP-104)
DISTORTION_LENGTHS = {'plumb_bob': (5,), 'rational_polynomial': (8, 5, 4, 12, 14),
                      'equidistant': (4,), 'none': (0,)}


class CameraModelError(ValueError):
    """The calibration is missing, uncalibrated or inconsistent."""


@dataclass
class PinholeCamera:
    """Calibrated camera. K (3x3) is the ideal pinhole used by the estimator."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(0))
    model: str = 'none'

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.D = np.asarray(self.D, dtype=float).ravel()
        if self.model in ('', 'plumb_bob', 'rational_polynomial') and \
                (self.D.size == 0 or not np.any(self.D)):
            self.model = 'none'        # all-zero D: skip the undistortion work
            self.D = np.zeros(0)
        self.validate()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_camera_info(cls, info: Mapping[str, Any], rectified: bool = False
                         ) -> 'PinholeCamera':
        """From a CameraInfo as a dict (keys width, height, K, D, distortion_model, P).

        With `rectified`, the images are rectified (image_rect): P's left 3x3 is the
        camera matrix and the distortion is zero, as image_geometry does.
        """
        try:
            width, height = int(info['width']), int(info['height'])
            K = np.asarray(info['K'], dtype=float).reshape(3, 3)
            D = np.asarray(info.get('D', ()), dtype=float).ravel()
            model = str(info.get('distortion_model', '') or '')
        except (KeyError, TypeError, ValueError) as exc:
            raise CameraModelError(f'CameraInfo incomplete: {exc}') from exc
        if rectified:
            P = np.asarray(info.get('P', np.zeros(12)), dtype=float).reshape(3, 4)
            if P[0, 0] == 0.0:
                raise CameraModelError('rectified=True but P is zero (uncalibrated)')
            return cls(width, height, P[:, :3].copy(), np.zeros(0), 'none')
        return cls(width, height, K, D, model or 'none')

    def validate(self) -> None:
        """Raise CameraModelError with the reason if the model cannot be used."""
        if self.width <= 0 or self.height <= 0:
            raise CameraModelError(f'image size {self.width}x{self.height} is not positive')
        if not np.all(np.isfinite(self.K)) or not np.all(np.isfinite(self.D)):
            raise CameraModelError('K or D contains NaN/inf')
        if self.K[0, 0] == 0.0:
            raise CameraModelError('K[0] == 0: the camera is uncalibrated (REP-104)')
        if self.fx <= 0 or self.fy <= 0:
            raise CameraModelError(f'focal lengths must be positive (fx={self.fx}, '
                                   f'fy={self.fy})')
        if self.K[2, 2] != 1.0 or self.K[1, 0] != 0.0 or self.K[2, 0] != 0.0 \
                or self.K[2, 1] != 0.0:
            raise CameraModelError(f'K is not an upper-triangular camera matrix: {self.K}')
        if not (-self.width < self.cx < 2 * self.width and
                -self.height < self.cy < 2 * self.height):
            raise CameraModelError(f'principal point ({self.cx}, {self.cy}) is far '
                                   f'outside the {self.width}x{self.height} image')
        if self.model not in DISTORTION_LENGTHS:
            raise CameraModelError(f'unsupported distortion model {self.model!r}; '
                                   f'supported: {sorted(DISTORTION_LENGTHS)}')
        if self.D.size not in DISTORTION_LENGTHS[self.model]:
            raise CameraModelError(f'{self.model} needs {DISTORTION_LENGTHS[self.model]} '
                                   f'coefficients, got {self.D.size}')

    # ------------------------------------------------------------------ intrinsics
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def same_as(self, other: 'PinholeCamera | None') -> bool:
        """True when `other` describes the same calibration (to float tolerance)."""
        return (other is not None and self.width == other.width
                and self.height == other.height and self.model == other.model
                and np.allclose(self.K, other.K) and self.D.shape == other.D.shape
                and np.allclose(self.D, other.D))

    # ------------------------------------------------------------------ projections
    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Ideal pinhole projection of (N,3) camera-frame points to (N,2) pixels.

        Points with Z <= 0 give NaN (behind the camera; callers mask them)."""
        X_cam = np.atleast_2d(np.asarray(X_cam, dtype=float))
        Z = X_cam[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            inv_z = np.where(Z > 1e-12, 1.0 / Z, np.nan)
        return np.column_stack((self.fx * X_cam[:, 0] * inv_z + self.cx,
                                self.fy * X_cam[:, 1] * inv_z + self.cy))

    def unproject(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N,2) ideal pixels -> (N,3) unit bearing vectors in the camera frame."""
        px = np.atleast_2d(np.asarray(px_ideal, dtype=float))
        rays = np.column_stack(((px[:, 0] - self.cx) / self.fx,
                                (px[:, 1] - self.cy) / self.fy, np.ones(len(px))))
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def undistort(self, px_raw: np.ndarray) -> np.ndarray:
        """(N,2) raw image pixels -> (N,2) ideal pinhole pixels (same K)."""
        px = np.asarray(px_raw, dtype=np.float64).reshape(-1, 1, 2)
        if self.model == 'none' or len(px) == 0:
            return px.reshape(-1, 2).copy()
        if self.model == 'equidistant':
            out = cv2.fisheye.undistortPoints(px, self.K, self.D, P=self.K)
        else:
            # iterative inversion; more iterations than the default for strong lenses
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-6)
            out = cv2.undistortPoints(px, self.K, self.D, R=np.eye(3), P=self.K,
                                      criteria=criteria)
        return out.reshape(-1, 2)

    def distort(self, px_ideal: np.ndarray) -> np.ndarray:
        """(N,2) ideal pixels -> (N,2) raw image pixels (inverse of `undistort`)."""
        px = np.atleast_2d(np.asarray(px_ideal, dtype=np.float64))
        if self.model == 'none' or len(px) == 0:
            return px.copy()
        norm = np.column_stack(((px[:, 0] - self.cx) / self.fx,
                                (px[:, 1] - self.cy) / self.fy))
        if self.model == 'equidistant':
            out = cv2.fisheye.distortPoints(norm.reshape(-1, 1, 2), self.K, self.D)
            return out.reshape(-1, 2)
        pts = np.column_stack((norm, np.ones(len(norm))))
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.D)
        return out.reshape(-1, 2)

    def in_image(self, px: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the image with a margin."""
        px = np.atleast_2d(px)
        return ((px[:, 0] >= margin) & (px[:, 0] <= self.width - 1 - margin)
                & (px[:, 1] >= margin) & (px[:, 1] <= self.height - 1 - margin))

"""A noisy sensor's frames, smoothed before KLT and the detector (docs/method.md §6.12).

A dim sensor at a high gain adds noise of 10-15 grey levels to every pixel. KLT's image
gradients are then mostly that noise, the tracks wander by pixels, and on the rendered
orbit and ground robot at 15 grey levels the estimate drifted 10-19 deg off. A Gaussian
of about a pixel takes most of the noise out of the gradients (by about 3.5x at
sigma 1 px) and brought those runs back to under 2 deg; but on a clean sensor it only
blurs the corners (KITTI 06 through JPEG went from 0.10 to 0.25 % of the path). So the
frames are smoothed only while the sensor is found noisy, and only when
`denoise_min_noise_grey` is set (off by default: docs/method.md §6.12).

The noise's standard deviation is estimated from the images themselves, by Immerkær's
method (J. Immerkær, "Fast noise variance estimation", Computer Vision and Image
Understanding 64(2), 1996): the image convolved with the difference of two Laplacians,
a 3x3 mask that cancels intensity that is locally linear, leaves mostly the noise,

    sigma = sqrt(pi / 2) / (6 (W - 2) (H - 2)) * sum |I * N|,   N = [[1 -2 1] [-2 4 -2] [1 -2 1]].

On the renders it reads the noise added to within 0.1 grey level (2, 5, 10, 15), and
2.7 on KITTI 06's raw frames, 1.1-1.6 on them through JPEG (which smooths), 0.6 on the
demo: texture and edges raise it a little, never near the threshold.

The decision is the median of the recent estimates (one every few frames: the
convolution costs about 0.5 ms at 1226x370), with hysteresis, so that the frames KLT
compares are smoothed alike: KLT assumes the same image model in both.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

#: Immerkær's mask: the difference of two discrete Laplacians
_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
#: every frame is estimated until this many estimates are in, then one frame in _EVERY
_FIRST = 5
_EVERY = 10
#: the median of this many recent estimates decides
_WINDOW = 9
#: smoothing stops when that median falls below this share of the threshold
_OFF_SHARE = 0.8


def noise_sigma(gray: np.ndarray) -> float:
    """The standard deviation [grey levels] of white noise in the (H, W) grey image,
    by Immerkær's method (module docstring)."""
    h, w = gray.shape[:2]
    if h < 3 or w < 3:
        return 0.0
    response = cv2.filter2D(gray.astype(np.float32), -1, _MASK)[1:-1, 1:-1]
    return math.sqrt(math.pi / 2.0) * float(np.abs(response).sum()) / (6.0 * (w - 2) * (h - 2))


class SensorNoise:
    """The sensor's noise from the frames, and whether they are smoothed.

    Args:
        min_noise_grey: smooth the frames while the estimate is at least this (grey
            levels); 0 = never (nothing is estimated).
        sigma_px: the Gaussian's standard deviation [px].
    """

    def __init__(self, min_noise_grey: float, sigma_px: float) -> None:
        self.min_noise_grey = float(min_noise_grey)
        self.sigma_px = float(sigma_px)
        self.enabled = self.min_noise_grey > 0.0 and self.sigma_px > 0.0
        self.reset()

    def reset(self) -> None:
        """Forget the estimates (`observe` does when the image size changes)."""
        self._estimates: list[float] = []
        self._frames = 0
        self._shape: tuple[int, ...] | None = None
        #: the median of the recent estimates [grey levels]; nan before any
        self.estimate_grey = float('nan')
        #: whether the frames are smoothed
        self.smoothing = False

    def observe(self, raw: np.ndarray) -> bool:
        """Estimate the noise of the raw frame when it is due; True when the smoothing
        has just started (the previous frame, which KLT compares with this one, was not
        smoothed)."""
        if not self.enabled:
            return False
        if raw.shape != self._shape:
            self.reset()                # another camera: its own noise
            self._shape = raw.shape
        self._frames += 1
        if len(self._estimates) >= _FIRST and self._frames % _EVERY:
            return False
        self._estimates = (self._estimates + [noise_sigma(raw)])[-_WINDOW:]
        self.estimate_grey = float(np.median(self._estimates))
        was = self.smoothing
        if self.estimate_grey >= self.min_noise_grey:
            self.smoothing = True
        elif self.estimate_grey < _OFF_SHARE * self.min_noise_grey:
            self.smoothing = False
        return self.smoothing and not was

    def smooth(self, gray: np.ndarray) -> np.ndarray:
        """`gray` smoothed while the sensor is found noisy, else itself."""
        if not self.smoothing:
            return gray
        return cv2.GaussianBlur(gray, (0, 0), self.sigma_px)

"""Is the light steady? The brightness change between frames, measured at the tracks.

docs/method.md §6.1. A translational KLT window is more precise the smaller it is
(bench/track_precision.py), but under a gain that changes from frame to frame (a light
that flickers, an auto-exposure that hunts) a small window loses far more tracks than a
large one. So the tracker can use a small window (`klt_window_px`) while the light is
steady, and the large one (`klt_flicker_window_px`) from the first sign it is not (13 and
21 px by default). A small window also loses more tracks in fast motion, so while it is
used the tracks it loses are tracked again with the large one (features.py
`_track_wide`, §6.1).

The measure: for each frame pair, the median over the tracks of log(m1 / m0), where m0
and m1 are the grey-level means of a 31x31 square around a track in the previous frame
and in this one. The square is large because the gain moves the tracks themselves: KLT,
which has no gain in its model, shifts a corner towards darker or brighter pixels to
match it, and a 7x7 mean (the lens fall-off's, vignetting.py) around the shifted corner
then saw a 6 % gain as 1 %. Its root mean square over the last
`WINDOW_PAIRS` pairs is compared with `klt_flicker_log_gain`; a single pair at twice
that is enough. On KITTI 06 (a car's auto-exposure) the root mean square peaks at 0.035
(one pair at 0.061); under a +-10 % flicker it is about 0.08.

The same measure decides whether the tracker divides the change out of the frame before
KLT (klt_gain_compensation, features.py): it tries only while the light is changing (or
on a single jump), and keeps the division only when the change is common to the tracks
(at least COMMON_RATIO times the spread of the tracks' own log ratios, on that pair or
as the median of the window: `common`), that is a gain of the whole frame and not each
patch changing on its own, as a driving scene's do.
"""
from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

from .vignetting import GREY_MAX, GREY_MIN, square_mean

#: frame pairs whose log gains make the root mean square
WINDOW_PAIRS = 10
#: pairs measured before the light may be called steady (the start is judged flickering)
WARMUP_PAIRS = 5
#: frames the light stays "not steady" after the last change that exceeded the threshold
HOLD_FRAMES = 30
#: a single pair beyond this many times the threshold is a change on its own
SPIKE_FACTOR = 2.0
#: fewest well-exposed tracks for a pair to be measured
MIN_SAMPLES = 20
#: half the side [px] of the square whose mean grey level is compared
HALF_SQUARE_PX = 15
#: a change is common to the tracks, a gain of the whole frame, when its log ratio is at
#: least this many times the spread of the tracks' own (1.4826 x their median absolute
#: deviation): under a rendered flicker the median over pairs is 9-11; on KITTI 06,
#: where each patch's brightness changes on its own by about 3 % as the car drives, below
#: 1 (at twice its frame interval at most 2.9 for a single pair, about 1 over ten)
COMMON_RATIO = 3.0
#: the smallest spread a ratio is taken against (a noise-free render has none)
_MIN_SPREAD = 1e-3


class ExposureChange:
    """The frame-to-frame brightness change at the tracks, and whether the light is
    steady (`steady`)."""

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen (a new image size, a new stream)."""
        self._prev: np.ndarray | None = None
        self._gains: deque = deque(maxlen=WINDOW_PAIRS)
        self._commonness: deque = deque(maxlen=WINDOW_PAIRS)   # |log gain| / spread
        self._hold = 0
        #: log gain of the last measured pair, and the root mean square over the window
        self.last_log_gain = 0.0
        self.rms_log_gain = 0.0

    @property
    def changing(self) -> bool:
        """True while a recent pair changed brightness by more than the threshold (its
        root mean square over the window, or a single pair at SPIKE_FACTOR times it),
        and for HOLD_FRAMES frames after the last one."""
        return self._hold > 0

    @property
    def common(self) -> bool:
        """True when the recent pairs' changes were common to their tracks (the median
        over the window of |log gain| / spread at least COMMON_RATIO): a gain of the whole
        frame, which can be divided out, rather than each patch changing on its own."""
        return bool(self._commonness) and \
            float(np.median(self._commonness)) >= COMMON_RATIO

    def is_spike(self, log_gain: float) -> bool:
        """True when one pair's log gain is a change on its own."""
        return abs(log_gain) > SPIKE_FACTOR * self.threshold

    @property
    def steady(self) -> bool:
        """True when the recent pairs changed brightness by less than the threshold."""
        return len(self._gains) >= WARMUP_PAIRS and self._hold == 0

    def observe(self, gray: np.ndarray, p_prev: np.ndarray, p_cur: np.ndarray,
                integral: np.ndarray | None = None) -> None:
        """Measure the pair (previous frame, `gray`) at the tracks that went from p_prev
        (N, 2) to p_cur (raw pixels, the uncorrected image; `integral` its cv2.integral,
        CV_32S, when the caller has it)."""
        if integral is None:
            integral = cv2.integral(gray, sdepth=cv2.CV_32S)
        prev, self._prev = self._prev, integral
        if prev is None or prev.shape != integral.shape:
            return
        measured = log_gain(prev, integral, p_prev, p_cur)
        if measured is None:
            return
        g, spread = measured
        self._gains.append(g)
        self._commonness.append(abs(g) / max(spread, _MIN_SPREAD))
        self.last_log_gain = g
        self.rms_log_gain = math.sqrt(float(np.mean(np.square(self._gains))))
        if self.rms_log_gain > self.threshold or self.is_spike(g):
            self._hold = HOLD_FRAMES
        elif self._hold > 0:
            self._hold -= 1


def log_gain(integral0: np.ndarray, integral1: np.ndarray, p0: np.ndarray,
             p1: np.ndarray) -> tuple[float, float] | None:
    """The brightness change from one frame to the next: the median over the points of
    log(m1 / m0), m0 and m1 the grey-level means of the 31x31 square around p0 (N, 2) in
    the first frame and around p1 in the second (integral images of the same size, from
    cv2.integral); and the spread of the points' own log ratios around it (1.4826 x their
    median absolute deviation). Squares that leave the image or are under- or
    over-exposed in either frame do not count; None when fewer than MIN_SAMPLES remain."""
    if len(p1) < MIN_SAMPLES:
        return None
    h, w = integral1.shape[0] - 1, integral1.shape[1] - 1
    m = HALF_SQUARE_PX
    c0 = np.rint(np.asarray(p0, np.float64)).astype(np.int64)
    c1 = np.rint(np.asarray(p1, np.float64)).astype(np.int64)
    inside = ((c0 >= m) & (c0 < [w - m, h - m]) & (c1 >= m) &
              (c1 < [w - m, h - m])).all(axis=1)
    i0 = square_mean(integral0, c0[inside], m)
    i1 = square_mean(integral1, c1[inside], m)
    lit = (i0 >= GREY_MIN) & (i0 <= GREY_MAX) & (i1 >= GREY_MIN) & (i1 <= GREY_MAX)
    if np.count_nonzero(lit) < MIN_SAMPLES:
        return None
    ratios = np.log(i1[lit]) - np.log(i0[lit])
    g = float(np.median(ratios))
    return g, 1.4826 * float(np.median(np.abs(ratios - g)))

"""The lens's fall-off of brightness towards the corners, estimated from the tracks and
divided out before tracking (docs/method.md §6.11).

KLT assumes a patch keeps its grey levels as it moves. Under vignetting a patch that
moves outwards darkens: 1 - 0.5 r^2 (half the brightness in the corners) moved the
rendered orbit's and ground robot's orientation by 9-20 deg (§6.10). A wide-angle lens,
a cheap board camera or a lens stopped down to f/1.4 does that.

The fall-off is learnt from what the tracker already has, the same scene point seen at
two radii (Goldman & Chen, "Vignette and exposure calibration and compensation", ICCV
2005; Bergmann, Wang & Cremers, "Online photometric calibration of auto exposure video",
RA-L 2018, estimate it with an exposure per frame as well). With r the distance from the
image's centre over its half-diagonal and the grey level of a point I = k V(r) L (k the
frame's exposure, L the point's radiance; a camera's gamma makes that (k V L)^g, the same
form), a track's log grey levels in two frames differ by

    log I2 - log I1 = log(k2 / k1) + f(r2) - f(r1),    f(r) = log V(r) = a r^2 + b r^4.

The exposure ratio is the same for every track of a frame pair, so it is removed by
taking each pair's samples less their mean (a flickering light or an auto-exposure does
not bias the fall-off). The rest is a linear least-squares problem in (a, b) over the
last MAX_SAMPLES samples, with Huber weights (a track on a moving object, an occlusion's
edge or a specular highlight is an outlier) and a covariance that treats the samples of
a pair as one cluster (they share its KLT's errors). The samples are taken from the raw
images, so the fit is of the whole fall-off whatever correction is in force. A point's
grey level is the mean over a square of SAMPLE_HALF_PX around it; dark and saturated
points say nothing and are left out.

**Put in force only when it matters and is known.** The fall-off is judged at the
tracks' reach, the radius REACH_QUANTILE of the samples lie within (beyond it the fit
is an extrapolation, and no track cares). Once it says the image is darker there by
more than APPLY_DROP, and differs from none by APPLY_SIGMAS of its standard deviations,
every image is divided by V(r) before tracking and detection. It is updated when the
fit, from the pairs tracked under the correction, moves V by more than UPDATE_DROP
anywhere within the reach. Without a fall-off (KITTI 06 at 5-8 %, the dino at 4 %, the
demo and the renders at about 0) nothing is applied, and the tracker sees the images as
they come; a lens that falls off by less costs KLT little (§6.11).
"""
from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

#: half side [px] of the square whose mean grey level is a point's
SAMPLE_HALF_PX = 3
#: grey levels (of 255) outside which a point's mean says nothing (dark: noise and the
#: black level dominate; bright: the sensor saturates)
GREY_MIN, GREY_MAX = 12.0, 240.0
#: fewest tracks of a frame pair for its samples to count (its mean must be meaningful)
MIN_PAIR_SAMPLES = 20
#: the radial move [px] below which a track's sample is left out of the fit (it still
#: counts in its pair's mean). Such a sample measures no fall-off, only KLT's jitter and
#: the one-pixel jumps of its rounded square, whose change of grey level comes with the
#: jump's direction: a camera standing still for 20 frames, with fresh sensor noise,
#: gave a "fall-off" of 99.999 % at the corners and lost 211 of 297 tracks to it
#: (docs/method.md §6.11)
MIN_RADIAL_MOVE_PX = 2.0
#: samples, and frame pairs, before the fall-off is applied
MIN_SAMPLES, MIN_FRAMES = 2000, 20
#: the drop in brightness at the radius the tracks reach, 1 - V(reach), above which the
#: fall-off is applied; the reach is REACH_QUANTILE of the samples' radii (where there
#: are no tracks, as in the black background around Middlebury's dino, the fit is an
#: extrapolation, and the correction matters to no track)
APPLY_DROP, REACH_QUANTILE = 0.15, 0.9
#: standard deviations of log V(reach) by which the fall-off must differ from none
APPLY_SIGMAS = 6.0
#: |log V(reach)| beyond which a fit is not a lens's (a fifth of the brightness, or five
#: times it, where the tracks still reach: a wide-angle lens at full aperture loses about
#: half in its far corners) and is never put in force; a fit from degenerate samples said
#: 99.999 % (MIN_RADIAL_MOVE_PX)
MAX_ABS_LOG_V = math.log(5.0)
#: |log V| at which brightness() is bounded (a factor of 5e8)
_LOG_V_BOUND = 20.0
#: change of the brightness at any radius that updates the correction in force
UPDATE_DROP = 0.02
#: Huber's threshold, in robust standard deviations of the residuals, and the
#: reweighting iterations (from least squares)
HUBER_K, HUBER_ITERATIONS = 1.5, 3
#: samples kept (the latest pairs'); the fall-off is fitted every SOLVE_EVERY pairs
MAX_SAMPLES, SOLVE_EVERY = 15_000, 10


class LensFalloff:
    """The estimate of the lens's fall-off V(r) and the correction applied to images.
    `enabled` False: nothing is estimated and images pass unchanged."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = bool(enabled)
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new image size)."""
        #: per frame pair since the correction in force was put in force, one row per
        #: sample: (x1, x2, y, r^2 in this frame)
        self._samples: deque[np.ndarray] = deque()
        self.n_samples = 0
        self.n_pairs_seen = 0               # frame pairs learnt from, all told
        self._fitted = False                # coeffs come from a fit
        self.coeffs = np.zeros(2)           # (a, b) of the current estimate
        self.reach = 1.0                    # REACH_QUANTILE of the samples' radii
        self.reach_sigma = math.inf         # standard deviation of log V(reach)
        self.applied = np.zeros(2)          # (a, b) of the correction in force
        self._shape: tuple[int, int] | None = None
        self._r2: np.ndarray | None = None
        self._half_diag = 1.0               # px, of the image the radii are over
        self._gain: np.ndarray | None = None
        self._prev: np.ndarray | None = None

    def brightness(self, r: float, applied: bool = False) -> float:
        """V(r): the brightness at r (over the half-diagonal) relative to the centre, of
        the current estimate or (`applied`) of the correction in force."""
        a, b = self.applied if applied else self.coeffs
        # bounded so that no fit, however wild, overflows or gives log(0)
        return math.exp(min(max(a * r * r + b * r ** 4, -_LOG_V_BOUND), _LOG_V_BOUND))

    @property
    def n_pairs(self) -> int:
        """Frame pairs learnt from since the correction in force was put in force."""
        return len(self._samples)

    @property
    def corner_drop(self) -> float:
        """1 - V(1) of the current estimate: the corners' loss of brightness."""
        return 1.0 - self.brightness(1.0)

    @property
    def applied_drop(self) -> float:
        """1 - V(1) of the correction in force (0 when none is)."""
        return 1.0 - self.brightness(1.0, applied=True)

    def correct(self, gray: np.ndarray) -> np.ndarray:
        """`gray` (HxW uint8) with the fall-off in force divided out; `gray` itself when
        none is."""
        if self._gain is None or gray.shape != self._shape:
            return gray
        return cv2.multiply(gray, self._gain, dtype=cv2.CV_8U)

    def observe(self, gray: np.ndarray, p_prev: np.ndarray, p_cur: np.ndarray,
                integral: np.ndarray | None = None) -> bool:
        """Learn from the tracks that went from p_prev (N, 2) in the previous frame to
        p_cur in `gray` (the raw, uncorrected image; `integral` its cv2.integral, CV_32S,
        when the caller has it). Returns True when the correction in force changed (the
        caller corrects the previous frame again with `correct`)."""
        if not self.enabled:
            return False
        h, w = gray.shape
        if self._shape != (h, w):
            self.reset()
            self._shape = (h, w)
            half_diag2 = ((w - 1) / 2.0) ** 2 + ((h - 1) / 2.0) ** 2
            self._half_diag = math.sqrt(half_diag2)
            u2 = ((np.arange(w, dtype=np.float32) - (w - 1) / 2.0) ** 2)[None, :]
            v2 = ((np.arange(h, dtype=np.float32) - (h - 1) / 2.0) ** 2)[:, None]
            self._r2 = ((u2 + v2) / half_diag2).astype(np.float32)
        # grey sums over squares from the integral image: 0.1 ms a frame at 1226x370
        if integral is None:
            integral = cv2.integral(gray, sdepth=cv2.CV_32S)
        prev, self._prev = self._prev, integral
        if prev is None or prev.shape != integral.shape or len(p_cur) < MIN_PAIR_SAMPLES:
            return False
        self._learn(prev, integral, np.asarray(p_prev), np.asarray(p_cur))
        return self._decide()

    def _learn(self, prev: np.ndarray, integral: np.ndarray, p_prev: np.ndarray,
               p_cur: np.ndarray) -> None:
        """Add the samples of a frame pair (the integral images of the previous frame and
        of this one, the tracks' positions in each) and fit again every SOLVE_EVERY."""
        h, w = self._shape
        m = SAMPLE_HALF_PX
        c0 = np.rint(p_prev).astype(np.int64)
        c1 = np.rint(p_cur).astype(np.int64)
        inside = (c0[:, 0] >= m) & (c0[:, 0] < w - m) & (c0[:, 1] >= m) & \
                 (c0[:, 1] < h - m) & (c1[:, 0] >= m) & (c1[:, 0] < w - m) & \
                 (c1[:, 1] >= m) & (c1[:, 1] < h - m)
        c0, c1 = c0[inside], c1[inside]
        i0 = square_mean(prev, c0)
        i1 = square_mean(integral, c1)
        lit = (i0 >= GREY_MIN) & (i0 <= GREY_MAX) & (i1 >= GREY_MIN) & (i1 <= GREY_MAX)
        if np.count_nonzero(lit) < MIN_PAIR_SAMPLES:
            return
        r2_0 = self._r2[c0[lit, 1], c0[lit, 0]].astype(np.float64)
        r2_1 = self._r2[c1[lit, 1], c1[lit, 0]].astype(np.float64)
        y = np.log(i1[lit]) - np.log(i0[lit])
        x = np.stack((r2_1 - r2_0, r2_1 ** 2 - r2_0 ** 2), axis=1)
        y -= y.mean()                       # the pair's exposure ratio
        x -= x.mean(axis=0)
        moved = np.abs(np.sqrt(r2_1) - np.sqrt(r2_0)) * self._half_diag >= MIN_RADIAL_MOVE_PX
        if not moved.any():
            return
        self._samples.append(np.column_stack((x, y, r2_1))[moved])
        self.n_samples += int(np.count_nonzero(moved))
        while self.n_samples - len(self._samples[0]) >= MAX_SAMPLES:
            self.n_samples -= len(self._samples.popleft())
        self.n_pairs_seen += 1
        if len(self._samples) >= MIN_FRAMES and self.n_pairs_seen % SOLVE_EVERY == 0:
            self.coeffs, cov = _huber_fit(list(self._samples),
                                          self.coeffs if self._fitted else None)
            self._fitted = True
            r2 = np.concatenate([b[:, 3] for b in self._samples])
            self.reach = math.sqrt(float(np.quantile(r2, REACH_QUANTILE)))
            g = np.array([self.reach ** 2, self.reach ** 4])
            self.reach_sigma = math.sqrt(max(float(g @ cov @ g), 0.0))

    def _decide(self) -> bool:
        """Put the current estimate in force when it is known and matters; True when
        the correction in force changed."""
        if self.n_samples < MIN_SAMPLES or len(self._samples) < MIN_FRAMES:
            return False
        in_force = self._gain is not None
        # put in force only when the drop at the reach is above APPLY_DROP and far from
        # none: the first fits, from pairs that barely moved, said 14-19 % (2.5-3.5 of
        # their standard deviations) on the rendered drone's seed 7, a lens without a
        # fall-off; the drone through a lens with one said 18 % at 11 of them
        log_v = math.log(self.brightness(self.reach))
        if not abs(log_v) <= MAX_ABS_LOG_V:
            return False
        if not in_force and (1.0 - math.exp(log_v) < APPLY_DROP
                             or -log_v < APPLY_SIGMAS * self.reach_sigma):
            return False
        if in_force and max(abs(self.brightness(r) - self.brightness(r, applied=True))
                            for r in self.reach * _RADII) < UPDATE_DROP:
            return False
        self.applied = self.coeffs.copy()
        # KLT takes part of a patch's change of brightness for motion, so samples tracked
        # under a fall-off see less of it than there is; those tracked under the new
        # correction see what is left (docs/method.md §6.11)
        self._samples.clear()
        self.n_samples = 0
        a, b = self.applied
        self._gain = np.exp(-(a * self._r2 + b * self._r2 ** 2)).astype(np.float32)
        return True


#: radii, over the tracks' reach, at which the estimate and the correction in force are
#: compared
_RADII = np.array((0.25, 0.5, 0.75, 1.0))


def square_mean(integral: np.ndarray, centres: np.ndarray, half: int = SAMPLE_HALF_PX
                ) -> np.ndarray:
    """Mean grey level over the square of `half` px around each of `centres` (N, 2)
    int (u, v), all at least `half` inside the image, from its integral image."""
    side = 2 * half + 1
    u0, v0 = centres[:, 0] - half, centres[:, 1] - half
    u1, v1 = u0 + side, v0 + side
    total = integral[v1, u1] - integral[v0, u1] - integral[v1, u0] + integral[v0, u0]
    return total.astype(np.float64) / (side * side)


def _huber_fit(blocks: list[np.ndarray], start: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) minimising Huber's cost of y - x @ (a, b) over the frame pairs' samples
    `blocks`, each (n, 4) = (x, y, r^2), by iteratively reweighted least squares (the
    scale the residuals' median absolute deviation): HUBER_ITERATIONS reweightings from
    the least-squares fit, or one from `start`, the fit of ten pairs before, which shares
    most of the samples (the reweightings are spread over the fits; a fit costs 0.6 ms
    instead of 1.8). And their covariance, robust to what the samples of a pair share
    (the pairs as clusters, the sandwich estimator: a pair's tracks share its KLT's and
    its exposure's errors, so they are not independent)."""
    samples = np.concatenate(blocks)
    x, y = np.ascontiguousarray(samples[:, :2]), np.ascontiguousarray(samples[:, 2])
    wgt = np.ones(len(y))
    coeffs = start
    for _ in range(HUBER_ITERATIONS + 1 if start is None else 1):
        if coeffs is not None:
            res = np.abs(y - x @ coeffs)
            scale = HUBER_K * 1.4826 * float(np.median(res))
            if scale > 0.0:
                wgt = np.minimum(1.0, scale / np.maximum(res, 1e-12))
        xw = x * wgt[:, None]
        try:
            bread = np.linalg.inv(xw.T @ x)
        except np.linalg.LinAlgError:
            return np.zeros(2), np.full((2, 2), np.inf)
        coeffs = bread @ (xw.T @ y)
    res = y - x @ coeffs
    starts = np.cumsum([0] + [len(b) for b in blocks[:-1]])
    per_pair = np.add.reduceat(xw * res[:, None], starts, axis=0)
    return coeffs, bread @ (per_pair.T @ per_pair) @ bread

"""A rolling shutter's readout time, estimated from the update's residuals.

docs/method.md §15.17. `rolling_shutter_s` corrects each tracked pixel to the stamp's
time (rolling_shutter.py), but users seldom know their sensor's readout, and left at 0 on
a rolling-shutter camera the skew of every turn reads as motion: a ground robot turning
in place with a phone camera's 10 ms readout had 7-14 % of its frames outside the
covariance's 99.9 % bound.

The readout leaves a signature no pose can take up. If the pixels were corrected with a
readout tau_used and the camera's is tau, a map point's corrected pixel is off its
projection by (tau - tau_used) d, where d (`correction_rate`) is its row's time offset
per second of readout times the image motion there. So, per tracked
frame, the post-update residuals r (2n) of the map points the update kept are regressed
on d with the camera's six degrees of freedom projected out of both (the pinhole's
interaction matrix at each point's depth, so that nothing a pose correction explains is
taken for a readout):

    delta = d_perp . r_perp / |d_perp|^2,   var = s^2 / |d_perp|^2,

s^2 the residuals' own variance after the fit (2n - 7 degrees of freedom). Each frame
gives tau_used + delta with that variance; the frames are fused with a fading memory
(`MEMORY_FRAMES`), so that errors common to many frames (the map's, KLT's) cannot make
the estimate ever more certain, and its sigma is widened by the frames' scatter about
it (the Birge ratio, `sigma_s`). The estimate is applied once it is significant
(`SIGNIFICANCE` standard deviations above zero) and at least `MIN_APPLIED_S`, from
`MIN_FRAMES_APPLIED` frames on; until then the user's `rolling_shutter_s` is. Applied,
its uncertainty (at least `MIN_RELATIVE_SIGMA` of it) goes into the pixels' noise. A
camera that does not turn or move gives frames of little weight, and the estimate stays
where it was.
"""
from __future__ import annotations

import math

import numpy as np

from .camera import PinholeCamera
from .rolling_shutter import row_time_offsets_s

#: frames over which the per-frame estimates are averaged (a weight decaying as
#: exp(-age / MEMORY_FRAMES)); bounds how certain errors shared by frames can make it
MEMORY_FRAMES = 150.0
#: the estimate is applied when it is this many of its standard deviations above zero
SIGNIFICANCE = 4.0
#: and at least this [s]: a readout under 2 ms skews a turn at 100 deg/s by 0.2 deg
MIN_APPLIED_S = 0.002
#: fewest map points for a frame to be used
MIN_POINTS = 20
#: frames used before an estimate may first be applied. The first frames after a
#: bootstrap measure against a two-view map whose errors can look like a readout: on
#: the rendered walk (a global shutter), seed 11, their estimates averaged 5.6 ms, and
#: applied at frame 8, the 8.5 ms the pixels were then corrected with were taken into the
#: new points, which kept confirming it; never applied, the frames' estimates fell to
#: -1.7-3 ms within 40 frames (docs/method.md §15.17)
MIN_FRAMES_APPLIED = 60
#: a frame whose readout is this uncertain [s] is not used (no turn, no motion)
MAX_FRAME_SIGMA_S = 0.05
#: the uncertainty of an applied estimate is at least this share of it: under a steady
#: turn the map takes in part of the skew (its points were triangulated from frames
#: skewed alike), so the estimate falls short, by up to a quarter on the rendered ground
#: robot (23 ms of 30), however many frames agree
MIN_RELATIVE_SIGMA = 0.3


def interaction_matrix(px_ideal: np.ndarray, depth: np.ndarray, camera: PinholeCamera
                       ) -> np.ndarray:
    """L (n,2,6): how the ideal pixels (n,2) of static points at optical depths (n,) move
    [px/s] per camera twist (v_cam [map units/s], omega_cam [rad/s], both in the camera
    frame): the pinhole's interaction matrix, X_cam' = -v_cam - omega_cam x X_cam."""
    x = (px_ideal[:, 0] - camera.cx) / camera.fx
    y = (px_ideal[:, 1] - camera.cy) / camera.fy
    inv_z = 1.0 / depth
    L = np.zeros((len(x), 2, 6))
    L[:, 0, 0], L[:, 0, 2] = -inv_z, x * inv_z
    L[:, 0, 3], L[:, 0, 4], L[:, 0, 5] = x * y, -(1 + x * x), y
    L[:, 1, 1], L[:, 1, 2] = -inv_z, y * inv_z
    L[:, 1, 3], L[:, 1, 4], L[:, 1, 5] = 1 + y * y, -x * y, -x
    L[:, 0] *= camera.fx
    L[:, 1] *= camera.fy
    return L


def correction_rate(L: np.ndarray, rows_px: np.ndarray, twist: np.ndarray,
                    camera: PinholeCamera) -> np.ndarray:
    """d (n,2) [px/s]: the image motion (`interaction_matrix` L times the camera's twist
    (6,)) times each raw row's time offset per second of readout. A pixel seen on its
    row at t + offset * tau is off the stamp's by offset * tau * motion, so pixels
    corrected with a readout tau_used are off their projection by (tau - tau_used) d
    when the camera's is tau (rolling_shutter.py corrects them to first order alike)."""
    offset = row_time_offsets_s(rows_px, camera.height, 1.0)
    return offset[:, None] * (L @ np.asarray(twist, float))


class ReadoutEstimate:
    """The rolling shutter's readout [s], fused over the tracked frames."""

    def __init__(self, prior_s: float, max_s: float, enabled: bool = True) -> None:
        self.prior_s = float(prior_s)
        self.max_s = float(max_s)
        self.enabled = bool(enabled)
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen (a new camera, a new stream); a map reset keeps them:
        the readout is the sensor's."""
        self._info = 0.0          # sum of weights 1 / var, faded
        self._weighted = 0.0      # sum of estimate / var, faded
        self._weighted_sq = 0.0   # sum of estimate^2 / var, faded
        self._count = 0.0         # frames, faded
        self._frames = 0          # frames used, all told

    @property
    def estimate_s(self) -> float | None:
        """The fused readout estimate [s], or None before any frame."""
        return self._weighted / self._info if self._info > 0.0 else None

    @property
    def sigma_s(self) -> float:
        """Its standard deviation [s] (inf before two frames): the fused one, widened
        by how much more the frames' estimates scatter than their own variances say
        (the square root of their reduced chi-square, when above 1; the Birge ratio).
        The frames' residuals share errors a frame's variance does not count (KLT's,
        the map's, a motion the model does not follow): on the demo, the frames said
        -0.6 +- 0.07 ms of a global shutter."""
        if self._info <= 0.0 or self._count <= 1.0:
            return math.inf
        chi2 = max(self._weighted_sq - self._weighted ** 2 / self._info, 0.0)
        birge = max(1.0, chi2 / (self._count - 1.0))
        return math.sqrt(birge / self._info)

    @property
    def applied_s(self) -> float:
        """The readout the pixels are corrected with: the estimate once significant,
        after MIN_FRAMES_APPLIED frames, else the configured one."""
        est = self.estimate_s
        if not self.enabled or est is None or est < MIN_APPLIED_S or \
                est < SIGNIFICANCE * self.sigma_s or self._frames < MIN_FRAMES_APPLIED:
            return self.prior_s
        return min(est, self.max_s)

    @property
    def in_force(self) -> bool:
        """True while the pixels are corrected with the estimate (not the configured
        readout)."""
        return self.applied_s != self.prior_s

    @property
    def applied_sigma_s(self) -> float:
        """The uncertainty [s] of the readout applied: 0 for the configured one (the
        user's, from the datasheet), else the estimate's, at least MIN_RELATIVE_SIGMA of
        it. The pixels' noise takes it in (`extra_pixel_variance`)."""
        if not self.in_force:
            return 0.0
        return max(self.sigma_s, MIN_RELATIVE_SIGMA * self.applied_s)

    def extra_pixel_variance(self, d_px_per_s: np.ndarray) -> np.ndarray | None:
        """Each pixel's added variance [px^2] (n,), per axis, from the applied
        readout's uncertainty, given its `correction_rate` d (n,2): sigma^2 |d|^2, the
        whole of the error along d, on both axes. None while none is."""
        sigma = self.applied_sigma_s
        if sigma <= 0.0:
            return None
        return sigma ** 2 * np.sum(np.square(d_px_per_s), axis=1)

    def observe(self, px_ideal: np.ndarray, rows_px: np.ndarray, depth: np.ndarray,
                residual_px: np.ndarray, twist: np.ndarray, camera: PinholeCamera,
                used_s: float) -> float | None:
        """One tracked frame: the map points' ideal pixels (n,2), raw rows (n,) and
        optical depths (n,), their post-update residuals z - h (n,2) [px], the camera's
        twist (v_cam, omega_cam) after the update, and the readout the pixels were
        corrected with. Returns this frame's estimate [s] when it was used."""
        if not self.enabled:
            return None
        ok = np.isfinite(residual_px).all(axis=1) & (depth > 0.0)
        n = int(np.count_nonzero(ok))
        if n < MIN_POINTS:
            return None
        L = interaction_matrix(px_ideal[ok], depth[ok], camera)
        d = correction_rate(L, rows_px[ok], twist, camera).reshape(-1)
        A = L.reshape(2 * n, 6)
        r = residual_px[ok].reshape(-1)
        # what a pose correction explains is projected out of both (least squares on
        # the 6x6 normal equations: a tenth of a QR of the (2n, 6) matrix here)
        rd = np.column_stack((r, d))
        try:
            rd_perp = rd - A @ np.linalg.solve(A.T @ A, A.T @ rd)
        except np.linalg.LinAlgError:
            return None
        r_perp, d_perp = rd_perp[:, 0], rd_perp[:, 1]
        dd = float(d_perp @ d_perp)
        if dd <= 0.0:
            return None
        delta = float(d_perp @ r_perp) / dd
        s2 = float(np.sum((r_perp - delta * d_perp) ** 2)) / max(2 * n - 7, 1)
        var = s2 / dd
        if not (var > 0.0) or var > MAX_FRAME_SIGMA_S ** 2:
            return None
        frame_estimate = used_s + delta
        fade = math.exp(-1.0 / MEMORY_FRAMES)
        self._info = fade * self._info + 1.0 / var
        self._weighted = fade * self._weighted + frame_estimate / var
        self._weighted_sq = fade * self._weighted_sq + frame_estimate ** 2 / var
        self._count = fade * self._count + 1.0
        self._frames += 1
        return frame_estimate

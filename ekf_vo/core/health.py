"""Online consistency checks of a tracked frame: OK, DEGRADED or LOST, and why.

docs/method.md §15. Without ground truth, a filter can only be judged by its own
measurements. Per tracked frame, after the update:

- innovations: the normalised innovation squared of the last `health_window_frames`
  updates, summed, against the chi-square bound of their summed degrees of freedom. Its
  ratio to the degrees of freedom is the a-posteriori variance factor: when the
  innovations are larger than the filter's covariance says, the published covariance is
  multiplied by it (the evidence says the filter is that much less certain), and above
  `health_max_variance_factor` the frame is DEGRADED.
- map points found: of the map points the prior puts in the image, the share that the
  update used as inliers. Below `health_min_found_share` the map in view is not the map
  the camera sees (a wrong pose, or a scene that changed): DEGRADED.
- inliers: fewer than twice `min_tracking_inliers` is DEGRADED (LOST is decided by the
  pipeline, §7.4).

The inflation only ever grows the published covariance; the filter's own state and `P`
are left alone, so a transient does not teach the filter anything. Pure numpy.
"""
from __future__ import annotations

import collections
import enum
from dataclasses import dataclass

import numpy as np

from ..config import VoConfig

#: standard normal 99.9 % quantile (Wilson-Hilferty bound of the chi-square)
_Z_999 = 3.090


class Health(enum.Enum):
    OK = 'ok'
    DEGRADED = 'degraded'
    LOST = 'lost'


@dataclass(frozen=True)
class HealthReport:
    status: Health
    reason: str = ''             #: why not OK ('' when OK)
    inflation: float = 1.0       #: factor on the published covariance (>= 1)
    variance_factor: float = 1.0  #: windowed NIS / dof
    found_share: float = 1.0     #: inliers / map points the prior puts in the image


def found_share(n_found: float, n_in_view: int) -> float:
    """The share of the map points the prior put in the image that the update used
    (1 when it put none there)."""
    return n_found / n_in_view if n_in_view else 1.0


def chi2_upper(dof: float) -> float:
    """Chi-square 99.9 % quantile for `dof` degrees of freedom (Wilson-Hilferty)."""
    k = max(float(dof), 1.0)
    return k * (1.0 - 2.0 / (9.0 * k) + _Z_999 * np.sqrt(2.0 / (9.0 * k))) ** 3


class HealthMonitor:
    """The checks of one VisualOdometry (see the module docstring)."""

    def __init__(self, cfg: VoConfig) -> None:
        self.cfg = cfg
        self._window: collections.deque = collections.deque(
            maxlen=cfg.health_window_frames)
        self._flag, self._flag_frames = '', 0

    def reset(self) -> None:
        self._window.clear()
        self._flag, self._flag_frames = '', 0

    def flag(self, reason: str) -> None:
        """A check outside the update failed (rotation_check.py): DEGRADED, with this
        reason, for the next `health_window_frames` frames."""
        self._flag, self._flag_frames = reason, self.cfg.health_window_frames

    def assess(self, nis: float, dof: int, n_inliers: int, n_in_view: int) -> HealthReport:
        """Verdict on a tracked frame: its update's NIS over `dof` innovation
        components, its inliers, and the map points its prior put in the image."""
        c = self.cfg
        if dof > 0 and np.isfinite(nis):
            self._window.append((float(nis), int(dof)))
        total_nis = sum(n for n, _ in self._window)
        total_dof = sum(d for _, d in self._window)
        factor = total_nis / total_dof if total_dof else 1.0
        # inflate only when the innovations are beyond what chance explains
        inflation = factor if total_dof and total_nis > chi2_upper(total_dof) else 1.0
        found = found_share(n_inliers, n_in_view)
        reasons = []
        if inflation > c.health_max_variance_factor:
            reasons.append(f'innovations {factor:.1f}x their covariance over the last '
                           f'{len(self._window)} frames')
        if n_in_view >= c.min_tracking_inliers and found < c.health_min_found_share:
            reasons.append(f'only {100 * found:.0f} % of the {n_in_view} map points in '
                           f'view found')
        if n_inliers < 2 * c.min_tracking_inliers:
            reasons.append(f'only {n_inliers} inliers')
        if self._flag_frames > 0:
            self._flag_frames -= 1
            reasons.append(self._flag)
        status = Health.DEGRADED if reasons else Health.OK
        return HealthReport(status, '; '.join(reasons), max(1.0, inflation), factor,
                            min(1.0, found))

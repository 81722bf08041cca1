"""Robust EKF update: 1-point RANSAC (Civera, Grasa, Davison, Montiel, JFR 2010).

METHOD.md section 2. With the EKF prior, a single match fixes a hypothesis, so few
hypotheses are needed:
  1. for a random match i: partial update with i alone (state only), predict every other
     match from that state, count those within `inlier_px` as its support;
     n_hyp = log(1 - p) / log(1 - eps), eps = best inlier ratio so far (m = 1), adapted;
  2. low-innovation inliers: a full EKF update with the supporters of the best hypothesis;
  3. high-innovation rescue: re-predict the remaining matches with the updated state and
     covariance; those whose Mahalanobis distance passes the chi-square gate (2 dof,
     `gate_probability`) are inliers too; a second update with them.
Without RANSAC (`one_point=False`), the prior innovation gate of step 3 alone is used.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from . import geometry as geo
from .ekf import POS, QUAT, CameraEKF, UpdateStats, chi2_2dof_quantile

logger = logging.getLogger(__name__)


@dataclass
class RobustUpdateResult:
    """Outcome of one robust update; index arrays refer to the input rows."""

    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  #: (n,) bool
    n_low_innovation: int = 0     #: inliers of the best hypothesis (step 2)
    n_rescued: int = 0            #: high-innovation inliers rescued (step 3)
    n_hypotheses: int = 0
    stats: UpdateStats = field(default_factory=UpdateStats)

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def _project_states(states: np.ndarray, X_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Ideal pixels of (n,3) points for (h,13) states -> (h,n,2); NaN behind a camera."""
    R_wc = np.stack([geo.quat_to_matrix(q) for q in states[:, QUAT]])      # (h,3,3)
    # X^C = R_wc^T (X^W - r): einsum over the h hypotheses at once
    X_cam = np.einsum('hji,hnj->hni', R_wc, X_world[None, :, :] - states[:, None, POS])
    Z = X_cam[..., 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        inv_z = np.where(Z > 1e-6, 1.0 / Z, np.nan)
    u = K[0, 0] * X_cam[..., 0] * inv_z + K[0, 2]
    v = K[1, 1] * X_cam[..., 1] * inv_z + K[1, 2]
    return np.stack((u, v), axis=-1)


def robust_update(ekf: CameraEKF, z_px: np.ndarray, X_world: np.ndarray,
                  sigma_px: float | np.ndarray,
                  rng: np.random.Generator, one_point: bool = True,
                  inlier_px: float = 2.0, probability: float = 0.99,
                  max_hypotheses: int = 50, gate_probability: float = 0.99,
                  iterations: int = 1) -> RobustUpdateResult:
    """Update `ekf` in place with the inliers among n matches (z_px (n,2) ideal pixels
    of the fixed map points X_world (n,3)). Returns which rows were used."""
    n = len(z_px)
    result = RobustUpdateResult(inliers=np.zeros(n, bool))
    if n == 0:
        return result
    sigma = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
    px_pred, in_front, H = ekf.observe(X_world)
    y = (z_px - px_pred)
    valid = in_front & np.all(np.isfinite(y), axis=1)
    gate = chi2_2dof_quantile(gate_probability)

    low = np.zeros(n, bool)
    if one_point and np.count_nonzero(valid) >= 2:
        candidates = np.flatnonzero(valid)
        n_hyp, best_support, tried = max_hypotheses, -1, 0
        while tried < n_hyp:
            # draw a batch so numpy does the projections of several hypotheses at once
            batch = rng.choice(candidates, size=min(n_hyp - tried, 16), replace=True)
            states = ekf.single_point_states(H, y, batch, sigma)
            px_h = _project_states(states, X_world, ekf.K)                  # (h,n,2)
            err = np.linalg.norm(px_h - z_px[None], axis=2)
            support = (err < inlier_px) & valid[None]
            counts = support.sum(axis=1)
            tried += len(batch)
            b = int(np.argmax(counts))
            if counts[b] > best_support:
                best_support = int(counts[b])
                low = support[b]
                eps = best_support / len(candidates)
                if eps >= 1.0:
                    break
                if eps > 0.0:
                    # adaptive hypothesis count for m = 1 (Civera 2010, eq. 19); with no
                    # support yet (eps = 0) the bound stays at max_hypotheses
                    n_hyp = min(max_hypotheses, int(np.ceil(
                        np.log(1.0 - probability) / np.log(1.0 - eps))))
        result.n_hypotheses = tried
    else:
        # plain innovation gate on the prior
        S = ekf.innovation_covariances(H, sigma)
        d2 = np.einsum('ni,nij,nj->n', y, np.linalg.inv(S), y)
        low = valid & (d2 < gate)

    result.n_low_innovation = int(np.count_nonzero(low))
    if result.n_low_innovation == 0:
        return result
    result.stats = ekf.update(z_px[low], X_world[low], sigma[low], iterations)
    inliers = low.copy()

    if one_point:
        # high-innovation inlier rescue with the updated state and covariance
        rest = np.flatnonzero(valid & ~low)
        if len(rest):
            px_r, front_r, H_r = ekf.observe(X_world[rest])
            y_r = z_px[rest] - px_r
            S_r = ekf.innovation_covariances(H_r, sigma[rest])
            d2 = np.einsum('ni,nij,nj->n', y_r, np.linalg.inv(S_r), y_r)
            rescued = rest[front_r & (d2 < gate)]
            if len(rescued):
                ekf.update(z_px[rescued], X_world[rescued], sigma[rescued], iterations)
                inliers[rescued] = True
                result.n_rescued = len(rescued)
    result.inliers = inliers
    return result
